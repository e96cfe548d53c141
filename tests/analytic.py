"""Closed-form and semi-analytic reference solutions for the finite-element tests.

This module is deliberately independent of ``lungmech`` (and of DOLFINx/UFL): it is plain
NumPy/SciPy, every stress is differentiated BY HAND, and ``tests/test_analytic.py`` checks each
hand derivation against independent numerics (complex-step / finite differences of the energy).
It doubles as the documentation of the formulas the FE code is compared against.

Conventions
-----------
``F`` is a 3×3 deformation gradient (any function taking ``F`` also accepts a stack of shape
``(..., 3, 3)``; real or complex, so complex-step differentiation works), ``J = det F``,
``C = FᵀF``, ``I1 = tr C``, ``I2 = ½(I1² − tr C²)``. Energies ψ are per unit reference volume,
``P = ∂ψ/∂F`` is the first Piola–Kirchhoff stress and ``σ = P Fᵀ / J`` the Cauchy stress.

Derivatives used throughout (``F⁻ᵀ = (F⁻¹)ᵀ``)::

    ∂I1/∂F = 2F,   ∂I2/∂F = 2(I1 F − F C),   ∂J/∂F = J F⁻ᵀ,   ∂(ln J)/∂F = F⁻ᵀ.

Laws (registry :data:`LAWS`; parameters are the frozen dataclasses below)
-------------------------------------------------------------------------
Each entry: name [parameters]: ψ(F);  linearisation (μ, λ) at F = I (:func:`lame_of`).

* ``linear`` [LameParams]: μ ε:ε + λ/2 (tr ε)², ε = sym(F − I);  (μ, λ). Not objective.
* ``svk`` [LameParams]: μ E:E + λ/2 (tr E)², E = ½(C − I);  (μ, λ).
* ``neo_hookean`` [LameParams]: μ/2 (I1 − 3) − μ ln J + λ/2 (ln J)²;  (μ, λ).
* ``ciarlet_geymonat`` [CiarletGeymonatParams]:
  c0(J² − 1 − 2 ln J) + c1(I1 − 3 − 2 ln J) + c2(I2 − 3 − 4 ln J);  (2(c1 + c2), 4(c0 + c2)).
* ``exponential_cg`` [ExponentialCGParams]: α(exp(γ(J² − 1 − 2 ln J)) − 1);  (0, 4αγ).
* ``stable_neo_hookean`` [LameParams] (Smith, de Goes & Kim 2018):
  μ'/2 (I1 − 3) + λ'/2 (J − a)² − μ'/2 ln(I1 + 1) − ψ_rest, μ' = 4μ/3, λ' = λ + 5μ/6,
  a = 1 + 3μ'/(4λ'), ψ_rest = ψ-part at F = I;  (μ, λ).
* ``mooney_rivlin`` [MooneyRivlinParams]: c1(I1 − 3 − 2 ln J) + c2(I2 − 3 − 4 ln J) + κ/2 (ln J)²;
  (2(c1 + c2), κ + 4c2).

Reference problems
------------------
* homogeneous: :func:`uniaxial` (free lateral faces, any law), :func:`uniaxial_incompressible_limit`,
  incompressible closed forms, :func:`simple_shear_neo_hookean`;
* thick sphere under internal pressure: incompressible neo-Hookean closed form
  (:func:`thick_sphere_pressure`, inverse, limit point, displacement field), linear Lamé
  (:func:`thick_sphere_lame`) and the compressible radial BVP for any law
  (:func:`thick_sphere_compressible`);
* Euler–Bernoulli cantilever: tip deflection, natural frequencies, mode shapes.

Use either the generic functions ``psi(law, params, F)``, ``piola(law, params, F)``,
``cauchy(law, params, F)``, ``lame_of(law, params)`` or a bound :class:`Material`
(``material(law, params).piola(F)``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.integrate import solve_bvp
from scipy.optimize import brentq

__all__ = [
    "CANTILEVER_BETA_L",
    "LAWS",
    "CiarletGeymonatParams",
    "ExponentialCGParams",
    "LameParams",
    "LameSphere",
    "Law",
    "Material",
    "MooneyRivlinParams",
    "SphereSolution",
    "cantilever_beta_l",
    "cantilever_frequencies",
    "cantilever_mode_shape",
    "cantilever_tip_deflection",
    "cauchy",
    "incompressible_mooney_rivlin_uniaxial",
    "incompressible_neo_hookean_equibiaxial",
    "incompressible_neo_hookean_uniaxial",
    "lame_from_young",
    "lame_of",
    "material",
    "piola",
    "principal_piola",
    "psi",
    "simple_shear_neo_hookean",
    "thick_sphere_compressible",
    "thick_sphere_incompressible_displacement",
    "thick_sphere_inner_stretch",
    "thick_sphere_lame",
    "thick_sphere_limit_point",
    "thick_sphere_pressure",
    "uniaxial",
    "uniaxial_incompressible_limit",
]

Array = npt.NDArray[Any]  # float64 or complex128 (complex-step), shape (..., 3, 3) or (...)


# ============================================================================================
# Parameters
# ============================================================================================


def lame_from_young(E: float, nu: float) -> tuple[float, float]:
    """Lamé parameters ``(μ, λ)`` from Young's modulus and Poisson's ratio.

    μ = E / (2(1 + ν)),  λ = E ν / ((1 + ν)(1 − 2ν)).  Requires −1 < ν < 0.5.
    """
    if not -1.0 < nu < 0.5:
        raise ValueError(f"need -1 < nu < 0.5, got nu = {nu}")
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


@dataclass(frozen=True)
class LameParams:
    """μ and λ (``lmbda``): for ``linear``, ``svk``, ``neo_hookean`` and ``stable_neo_hookean``."""

    mu: float
    lmbda: float

    @classmethod
    def from_young(cls, E: float, nu: float) -> LameParams:
        """Parameters from Young's modulus E and Poisson's ratio ν (see :func:`lame_from_young`)."""
        return cls(*lame_from_young(E, nu))


@dataclass(frozen=True)
class CiarletGeymonatParams:
    """c0 (bulk, J-term), c1 (I1-term), c2 (I2-term); any of them may be zero."""

    c0: float = 0.0
    c1: float = 0.0
    c2: float = 0.0


@dataclass(frozen=True)
class ExponentialCGParams:
    """α (stress scale) and γ (dimensionless exponent)."""

    alpha: float
    gamma: float


@dataclass(frozen=True)
class MooneyRivlinParams:
    """c1, c2 (deviatoric) and κ (``kappa``, bulk-like coefficient of (ln J)²/2)."""

    c1: float
    c2: float
    kappa: float


# ============================================================================================
# Tensor helpers (batched over leading axes, complex-safe: no abs/conj anywhere)
# ============================================================================================

_I3 = np.eye(3)


def _T(A: Array) -> Array:
    return np.swapaxes(A, -1, -2)


def _tr(A: Array) -> Array:
    return np.einsum("...ii->...", A)


def _ddot(A: Array, B: Array) -> Array:
    return np.einsum("...ij,...ij->...", A, B)


def _scalar_times(s: Array, A: Array) -> Array:
    """``s[..., None, None] * A`` for a batch of scalars ``s``."""
    return np.asarray(s)[..., None, None] * A


def _as_F(F: npt.ArrayLike) -> Array:
    F = np.asarray(F)
    if F.shape[-2:] != (3, 3):
        raise ValueError(f"F must have shape (..., 3, 3), got {F.shape}")
    if not np.iscomplexobj(F):
        F = F.astype(float)
    return F


def _invariants(F: Array) -> tuple[Array, Array, Array, Array]:
    """``(C, I1, I2, J)`` of F."""
    C = _T(F) @ F
    I1 = _tr(C)
    I2 = 0.5 * (I1**2 - _ddot(C, _T(C)))  # tr(C²) = C:Cᵀ
    J = np.linalg.det(F)
    return C, I1, I2, J


def _dI2_dF(F: Array, C: Array, I1: Array) -> Array:
    """∂I2/∂F = 2(I1 F − F C)."""
    return 2.0 * (_scalar_times(I1, F) - F @ C)


def _unwrap(x: Array) -> Any:
    """0-d arrays -> numpy scalars."""
    return x[()] if np.ndim(x) == 0 else x


# ============================================================================================
# The laws: psi and hand-derived first Piola stress
# ============================================================================================
# linear ---------------------------------------------------------------------------------------


def psi_linear(F: npt.ArrayLike, p: LameParams) -> Any:
    """ψ = μ ε:ε + λ/2 (tr ε)²,  ε = sym(F − I)  (small-strain; NOT objective)."""
    F = _as_F(F)
    H = F - _I3
    eps = 0.5 * (H + _T(H))
    return _unwrap(p.mu * _ddot(eps, eps) + 0.5 * p.lmbda * _tr(eps) ** 2)


def piola_linear(F: npt.ArrayLike, p: LameParams) -> Array:
    """P = σ = 2μ ε + λ tr(ε) I  (∂(ε:ε)/∂F = 2ε because ε is the symmetric part of F − I)."""
    F = _as_F(F)
    H = F - _I3
    eps = 0.5 * (H + _T(H))
    return 2.0 * p.mu * eps + _scalar_times(p.lmbda * _tr(eps), np.broadcast_to(_I3, F.shape))


def lame_linear(p: LameParams) -> tuple[float, float]:
    """Exactly (μ, λ)."""
    return p.mu, p.lmbda


# svk --------------------------------------------------------------------------------------------


def psi_svk(F: npt.ArrayLike, p: LameParams) -> Any:
    """ψ = μ E:E + λ/2 (tr E)²,  E = ½(C − I)."""
    F = _as_F(F)
    E = 0.5 * (_T(F) @ F - _I3)
    return _unwrap(p.mu * _ddot(E, E) + 0.5 * p.lmbda * _tr(E) ** 2)


def piola_svk(F: npt.ArrayLike, p: LameParams) -> Array:
    """P = F S,  S = 2μ E + λ tr(E) I."""
    F = _as_F(F)
    E = 0.5 * (_T(F) @ F - _I3)
    S = 2.0 * p.mu * E + _scalar_times(p.lmbda * _tr(E), np.broadcast_to(_I3, F.shape))
    return F @ S


def lame_svk(p: LameParams) -> tuple[float, float]:
    """Exactly (μ, λ): E = ε + O(|F − I|²)."""
    return p.mu, p.lmbda


# neo_hookean ----------------------------------------------------------------------------------


def psi_neo_hookean(F: npt.ArrayLike, p: LameParams) -> Any:
    """ψ = μ/2 (I1 − 3) − μ ln J + λ/2 (ln J)²."""
    F = _as_F(F)
    _, I1, _, J = _invariants(F)
    lnJ = np.log(J)
    return _unwrap(0.5 * p.mu * (I1 - 3.0) - p.mu * lnJ + 0.5 * p.lmbda * lnJ**2)


def piola_neo_hookean(F: npt.ArrayLike, p: LameParams) -> Array:
    """P = μ (F − F⁻ᵀ) + λ ln J F⁻ᵀ."""
    F = _as_F(F)
    FiT = _T(np.linalg.inv(F))
    lnJ = np.log(np.linalg.det(F))
    return p.mu * (F - FiT) + _scalar_times(p.lmbda * lnJ, FiT)


def lame_neo_hookean(p: LameParams) -> tuple[float, float]:
    """Exactly (μ, λ)."""
    return p.mu, p.lmbda


# ciarlet_geymonat -----------------------------------------------------------------------------


def psi_ciarlet_geymonat(F: npt.ArrayLike, p: CiarletGeymonatParams) -> Any:
    """ψ = c0(J² − 1 − 2 ln J) + c1(I1 − 3 − 2 ln J) + c2(I2 − 3 − 4 ln J)."""
    F = _as_F(F)
    _, I1, I2, J = _invariants(F)
    lnJ = np.log(J)
    return _unwrap(p.c0 * (J**2 - 1.0 - 2.0 * lnJ) + p.c1 * (I1 - 3.0 - 2.0 * lnJ) + p.c2 * (I2 - 3.0 - 4.0 * lnJ))


def piola_ciarlet_geymonat(F: npt.ArrayLike, p: CiarletGeymonatParams) -> Array:
    """P = 2c0(J² − 1) F⁻ᵀ + 2c1(F − F⁻ᵀ) + c2(2(I1 F − F C) − 4 F⁻ᵀ)."""
    F = _as_F(F)
    C, I1, _, J = _invariants(F)
    FiT = _T(np.linalg.inv(F))
    return (
        _scalar_times(2.0 * p.c0 * (J**2 - 1.0), FiT) + 2.0 * p.c1 * (F - FiT) + p.c2 * (_dI2_dF(F, C, I1) - 4.0 * FiT)
    )


def lame_ciarlet_geymonat(p: CiarletGeymonatParams) -> tuple[float, float]:
    """μ = 2(c1 + c2), λ = 4(c0 + c2).

    With E = ½(C − I) = ε + O(H²) and ln J = ½ Σ ln(1 + 2Eᵢ) = tr E − E:E + O(E³):
    J² − 1 − 2 ln J ≈ 2(tr ε)²,  I1 − 3 − 2 ln J ≈ 2 ε:ε,  I2 − 3 − 4 ln J ≈ 2 ε:ε + 2(tr ε)².
    """
    return 2.0 * (p.c1 + p.c2), 4.0 * (p.c0 + p.c2)


# exponential_cg -------------------------------------------------------------------------------


def psi_exponential_cg(F: npt.ArrayLike, p: ExponentialCGParams) -> Any:
    """ψ = α(exp(γ g) − 1),  g = J² − 1 − 2 ln J."""
    F = _as_F(F)
    J = np.linalg.det(F)
    g = J**2 - 1.0 - 2.0 * np.log(J)
    return _unwrap(p.alpha * (np.exp(p.gamma * g) - 1.0))


def piola_exponential_cg(F: npt.ArrayLike, p: ExponentialCGParams) -> Array:
    """P = 2αγ exp(γ g) (J² − 1) F⁻ᵀ   (∂g/∂F = (2J² − 2) F⁻ᵀ)."""
    F = _as_F(F)
    J = np.linalg.det(F)
    g = J**2 - 1.0 - 2.0 * np.log(J)
    FiT = _T(np.linalg.inv(F))
    return _scalar_times(2.0 * p.alpha * p.gamma * np.exp(p.gamma * g) * (J**2 - 1.0), FiT)


def lame_exponential_cg(p: ExponentialCGParams) -> tuple[float, float]:
    """μ = 0, λ = 4αγ  (g ≈ 2(tr ε)², so ψ ≈ 2αγ (tr ε)²): a purely volumetric law."""
    return 0.0, 4.0 * p.alpha * p.gamma


# stable_neo_hookean ---------------------------------------------------------------------------


def _snh_constants(p: LameParams) -> tuple[float, float, float, float]:
    """(μ', λ', a, ψ_rest) of Smith, de Goes & Kim (2018) from the Lamé parameters."""
    mu_p = 4.0 * p.mu / 3.0
    lam_p = p.lmbda + 5.0 * p.mu / 6.0
    a = 1.0 + 3.0 * mu_p / (4.0 * lam_p)
    psi_rest = 0.5 * lam_p * (1.0 - a) ** 2 - 0.5 * mu_p * math.log(4.0)
    return mu_p, lam_p, a, psi_rest


def psi_stable_neo_hookean(F: npt.ArrayLike, p: LameParams) -> Any:
    """ψ = μ'/2 (I1 − 3) + λ'/2 (J − a)² − μ'/2 ln(I1 + 1) − ψ_rest.

    μ' = 4μ/3, λ' = λ + 5μ/6, a = 1 + 3μ'/(4λ'), ψ_rest = λ'/2 (1 − a)² − μ'/2 ln 4 so ψ(I) = 0.
    """
    F = _as_F(F)
    mu_p, lam_p, a, psi_rest = _snh_constants(p)
    _, I1, _, J = _invariants(F)
    return _unwrap(0.5 * mu_p * (I1 - 3.0) + 0.5 * lam_p * (J - a) ** 2 - 0.5 * mu_p * np.log(I1 + 1.0) - psi_rest)


def piola_stable_neo_hookean(F: npt.ArrayLike, p: LameParams) -> Array:
    """P = μ'(1 − 1/(I1 + 1)) F + λ'(J − a) J F⁻ᵀ."""
    F = _as_F(F)
    mu_p, lam_p, a, _ = _snh_constants(p)
    _, I1, _, J = _invariants(F)
    FiT = _T(np.linalg.inv(F))
    return _scalar_times(mu_p * (1.0 - 1.0 / (I1 + 1.0)), F) + _scalar_times(lam_p * (J - a) * J, FiT)


def lame_stable_neo_hookean(p: LameParams) -> tuple[float, float]:
    """Exactly (μ, λ).

    Expanding with H = F − I: ψ ≈ 3μ'/4 ε:ε + (λ'/2 − 5μ'/16)(tr H)², i.e. μ = 3μ'/4 and
    λ = λ' − 5μ'/8, which the definitions of μ', λ' invert exactly.
    """
    return p.mu, p.lmbda


# mooney_rivlin --------------------------------------------------------------------------------


def psi_mooney_rivlin(F: npt.ArrayLike, p: MooneyRivlinParams) -> Any:
    """ψ = c1(I1 − 3 − 2 ln J) + c2(I2 − 3 − 4 ln J) + κ/2 (ln J)²."""
    F = _as_F(F)
    _, I1, I2, J = _invariants(F)
    lnJ = np.log(J)
    return _unwrap(p.c1 * (I1 - 3.0 - 2.0 * lnJ) + p.c2 * (I2 - 3.0 - 4.0 * lnJ) + 0.5 * p.kappa * lnJ**2)


def piola_mooney_rivlin(F: npt.ArrayLike, p: MooneyRivlinParams) -> Array:
    """P = 2c1(F − F⁻ᵀ) + c2(2(I1 F − F C) − 4 F⁻ᵀ) + κ ln J F⁻ᵀ."""
    F = _as_F(F)
    C, I1, _, J = _invariants(F)
    FiT = _T(np.linalg.inv(F))
    return 2.0 * p.c1 * (F - FiT) + p.c2 * (_dI2_dF(F, C, I1) - 4.0 * FiT) + _scalar_times(p.kappa * np.log(J), FiT)


def lame_mooney_rivlin(p: MooneyRivlinParams) -> tuple[float, float]:
    """μ = 2(c1 + c2), λ = κ + 4c2 (same expansion as Ciarlet–Geymonat, (ln J)² ≈ (tr ε)²)."""
    return 2.0 * (p.c1 + p.c2), p.kappa + 4.0 * p.c2


# registry ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Law:
    """One constitutive law: energy, hand-derived Piola stress and small-strain Lamé values."""

    name: str
    params_type: type
    psi: Callable[[npt.ArrayLike, Any], Any]
    piola: Callable[[npt.ArrayLike, Any], Array]
    lame: Callable[[Any], tuple[float, float]]
    objective: bool = True  # False only for the small-strain "linear" law


LAWS: dict[str, Law] = {
    "linear": Law("linear", LameParams, psi_linear, piola_linear, lame_linear, objective=False),
    "svk": Law("svk", LameParams, psi_svk, piola_svk, lame_svk),
    "neo_hookean": Law("neo_hookean", LameParams, psi_neo_hookean, piola_neo_hookean, lame_neo_hookean),
    "ciarlet_geymonat": Law(
        "ciarlet_geymonat",
        CiarletGeymonatParams,
        psi_ciarlet_geymonat,
        piola_ciarlet_geymonat,
        lame_ciarlet_geymonat,
    ),
    "exponential_cg": Law(
        "exponential_cg", ExponentialCGParams, psi_exponential_cg, piola_exponential_cg, lame_exponential_cg
    ),
    "stable_neo_hookean": Law(
        "stable_neo_hookean",
        LameParams,
        psi_stable_neo_hookean,
        piola_stable_neo_hookean,
        lame_stable_neo_hookean,
    ),
    "mooney_rivlin": Law(
        "mooney_rivlin", MooneyRivlinParams, psi_mooney_rivlin, piola_mooney_rivlin, lame_mooney_rivlin
    ),
}


def _law(law: str | Law, params: Any) -> Law:
    obj = LAWS[law] if isinstance(law, str) else law
    if not isinstance(params, obj.params_type):
        raise TypeError(f"law '{obj.name}' takes {obj.params_type.__name__}, got {type(params).__name__}")
    return obj


def psi(law: str | Law, params: Any, F: npt.ArrayLike) -> Any:
    """Strain energy per unit reference volume (scalar, or shape ``(...)`` for a stack of F)."""
    return _law(law, params).psi(F, params)


def piola(law: str | Law, params: Any, F: npt.ArrayLike) -> Array:
    """Hand-derived first Piola–Kirchhoff stress P = ∂ψ/∂F, same shape as F."""
    return _law(law, params).piola(F, params)


def cauchy(law: str | Law, params: Any, F: npt.ArrayLike) -> Array:
    """Cauchy stress σ = P Fᵀ / J.

    For ``linear`` the small-strain theory does not distinguish stress measures and σ = P
    (= 2με + λ tr ε I) is returned unchanged.
    """
    obj = _law(law, params)
    F = _as_F(F)
    P = obj.piola(F, params)
    if obj.name == "linear":
        return P
    return _scalar_times(1.0 / np.linalg.det(F), P @ _T(F))


def lame_of(law: str | Law, params: Any) -> tuple[float, float]:
    """(μ, λ) of the linearisation of the law at F = I."""
    return _law(law, params).lame(params)


@dataclass(frozen=True)
class Material:
    """A law bound to its parameters: ``m.psi(F)``, ``m.piola(F)``, ``m.cauchy(F)``, ``m.lame``."""

    law: Law
    params: Any

    def psi(self, F: npt.ArrayLike) -> Any:
        return psi(self.law, self.params, F)

    def piola(self, F: npt.ArrayLike) -> Array:
        return piola(self.law, self.params, F)

    def cauchy(self, F: npt.ArrayLike) -> Array:
        return cauchy(self.law, self.params, F)

    @property
    def lame(self) -> tuple[float, float]:
        return lame_of(self.law, self.params)


def material(law: str | Law, params: Any) -> Material:
    """Bind ``params`` to ``law`` (checks the parameter type)."""
    return Material(_law(law, params), params)


def principal_piola(law: str | Law, params: Any, stretches: npt.ArrayLike) -> Array:
    """Principal first Piola stresses ∂ψ̂/∂λᵢ for F = diag(λ1, λ2, λ3).

    For an isotropic law P(diag λ) is diagonal and its diagonal is the gradient of the energy
    written in principal stretches, ψ̂(λ1, λ2, λ3) = ψ(diag λ). ``stretches`` has shape (..., 3);
    the result has the same shape. Complex input is allowed (complex-step tangents).
    """
    lam = np.asarray(stretches)
    F = np.zeros(lam.shape + (3,), dtype=np.result_type(lam, float))
    for i in range(3):
        F[..., i, i] = lam[..., i]
    P = piola(law, params, F)
    return np.einsum("...ii->...i", P)


# ============================================================================================
# Homogeneous deformations
# ============================================================================================


def simple_shear_neo_hookean(g: float, mu: float) -> Array:
    """Cauchy stress of compressible neo-Hookean in simple shear F = I + g e1⊗e2.

    J = 1 so ln J = 0 and σ = μ(F Fᵀ − I) = μ(B − I): σ12 = μg, σ11 = μg², all other
    components zero, independent of λ.
    """
    s = np.zeros((3, 3))
    s[0, 1] = s[1, 0] = mu * g
    s[0, 0] = mu * g**2
    return s


def incompressible_neo_hookean_uniaxial(stretch: npt.ArrayLike, mu: float) -> Any:
    """σ11 = μ(l² − 1/l) for W = μ/2(I1 − 3), F = diag(l, l^-½, l^-½), lateral faces free."""
    l = np.asarray(stretch, dtype=float)
    return _unwrap(mu * (l**2 - 1.0 / l))


def incompressible_neo_hookean_equibiaxial(stretch: npt.ArrayLike, mu: float) -> Any:
    """σ11 = σ22 = μ(l² − l⁻⁴) for W = μ/2(I1 − 3), F = diag(l, l, l⁻²), σ33 = 0."""
    l = np.asarray(stretch, dtype=float)
    return _unwrap(mu * (l**2 - l**-4))


def incompressible_mooney_rivlin_uniaxial(stretch: npt.ArrayLike, c1: float, c2: float) -> Any:
    """σ11 = 2(l² − 1/l)(C1 + C2/l) for W = C1(I1 − 3) + C2(I2 − 3), lateral faces free."""
    l = np.asarray(stretch, dtype=float)
    return _unwrap(2.0 * (l**2 - 1.0 / l) * (c1 + c2 / l))


def uniaxial(law: str | Law, params: Any, stretch: float) -> tuple[float, float]:
    """Uniaxial tension/compression with free lateral faces: ``(lateral_stretch t, σ11)``.

    F = diag(l, t, t); t > 0 solves σ22(t) = 0 by Brent's method on a bracket grown
    geometrically from the incompressible guess l^-½ (σ22 is increasing in t for all laws here).
    σ11 is the Cauchy (true) stress.

    Notes:
    * ``exponential_cg`` has no shear stiffness: σ22 = 0 forces J = 1, i.e. t = l^-½, and then
      σ11 = 0 too (a purely volumetric law carries no uniaxial load). That is what is returned.
    * ``svk`` has the closed form t² = 1 − ν(l² − 1) and no solution for l² ≥ 1 + 1/ν
      (ValueError); likewise ``linear`` (t = 1 − ν(l − 1)) for l ≥ 1 + 1/ν.
    """
    obj = _law(law, params)
    l = float(stretch)
    if not l > 0:
        raise ValueError(f"stretch must be > 0, got {stretch}")

    def s22(t: float) -> float:
        with np.errstate(over="ignore", invalid="ignore"):
            return float(cauchy(obj, params, np.diag([l, t, t]))[1, 1])

    t0 = l**-0.5
    f0 = s22(t0)
    if f0 == 0.0:
        t = t0
    else:
        factor = 0.5 if f0 > 0 else 2.0  # σ22 too large -> shrink t, too small -> grow t
        a, b = t0, t0 * factor
        fb = s22(b)
        while not (np.isfinite(fb) and fb * f0 < 0):
            if not 1e-12 < b < 1e12:
                raise ValueError(f"uniaxial: no lateral stretch with sigma22 = 0 for law '{obj.name}' at l = {l}")
            if np.isfinite(fb):  # keep the bracket end finite (exp overflow far out)
                a = b
            b *= factor
            fb = s22(b)
        t = brentq(s22, min(a, b), max(a, b), xtol=1e-300, rtol=4 * np.finfo(float).eps, maxiter=500)
    sigma11 = float(cauchy(obj, params, np.diag([l, t, t]))[0, 0])
    return t, sigma11


def uniaxial_incompressible_limit(law: str | Law, params: Any, stretch: npt.ArrayLike) -> Any:
    """Uniaxial Cauchy stress of the incompressible limit (λ, κ → ∞) of a compressible law.

    The limit material keeps the isochoric part of ψ and replaces the volumetric one by a
    Lagrange multiplier, so with F = diag(l, l^-½, l^-½) (J = 1) and σ̂ = P Fᵀ the stress of the
    compressible law there, σ = σ̂ − p I with p fixed by σ22 = 0:  σ11 = σ̂11 − σ̂22.
    (Valid for laws whose volumetric terms give an isotropic Cauchy stress at J = 1: the
    ln J and (J − a)² terms here do.) For ``neo_hookean`` this is μ(l² − 1/l), for
    ``mooney_rivlin`` and ``ciarlet_geymonat`` 2(l² − 1/l)(c1 + c2/l), for
    ``stable_neo_hookean`` μ'(l² − 1/l)(1 − 1/(l² + 2/l + 1)).  This is the reference the
    mixed displacement–pressure formulation must reproduce.
    """
    obj = _law(law, params)
    if obj.name in ("linear", "svk", "exponential_cg"):
        raise ValueError(f"no meaningful incompressible limit for law '{obj.name}'")
    l = np.asarray(stretch, dtype=float)
    F = np.zeros(l.shape + (3, 3))
    F[..., 0, 0] = l
    F[..., 1, 1] = F[..., 2, 2] = l**-0.5
    s = obj.piola(F, params) @ _T(F)
    return _unwrap(s[..., 0, 0] - s[..., 1, 1])


# ============================================================================================
# Thick-walled sphere
# ============================================================================================


def _lambda_b(lambda_a: npt.ArrayLike, A: float, B: float) -> Array:
    """Outer hoop stretch of the incompressible sphere: λ_b³ = 1 + (λ_a³ − 1)A³/B³."""
    la = np.asarray(lambda_a, dtype=float)
    return np.cbrt(1.0 + (la**3 - 1.0) * (A / B) ** 3)


def thick_sphere_pressure(lambda_a: npt.ArrayLike, A: float, B: float, mu: float) -> Any:
    """Internal pressure of an incompressible neo-Hookean sphere A ≤ R ≤ B at inner stretch λ_a.

    Incompressibility gives r³ − a³ = R³ − A³; with Ŵ(λ) = W(λ⁻², λ, λ) = μ/2(λ⁻⁴ + 2λ² − 3),
    P = ∫_{λ_b}^{λ_a} Ŵ'(λ)/(λ³ − 1) dλ = ∫ 2μ(λ⁻² + λ⁻⁵) dλ, i.e.

        P = μ [2/λ_b + 1/(2λ_b⁴) − 2/λ_a − 1/(2λ_a⁴)],   λ_b³ = 1 + (λ_a³ − 1) A³/B³.
    """
    la = np.asarray(lambda_a, dtype=float)
    lb = _lambda_b(la, A, B)
    return _unwrap(mu * (2.0 / lb + 0.5 / lb**4 - 2.0 / la - 0.5 / la**4))


def _thick_sphere_dP(lambda_a: float, A: float, B: float, mu: float) -> float:
    """dP/dλ_a = g(λ_a) − g(λ_b) dλ_b/dλ_a, g(λ) = 2μ(λ⁻² + λ⁻⁵), dλ_b/dλ_a = ρ λ_a²/λ_b²."""
    rho = (A / B) ** 3
    lb = float(_lambda_b(lambda_a, A, B))

    def g(x: float) -> float:
        return 2.0 * mu * (x**-2 + x**-5)

    return g(lambda_a) - g(lb) * rho * lambda_a**2 / lb**2


def thick_sphere_limit_point(A: float, B: float, mu: float) -> tuple[float, float]:
    """``(λ_a*, P_max)`` where dP/dλ_a = 0 (≈ (1.8281, 0.81642 μ) for A = 1, B = 2)."""
    hi = 2.0
    while _thick_sphere_dP(hi, A, B, mu) > 0:
        hi *= 2.0
    la = brentq(_thick_sphere_dP, 1.0 + 1e-12, hi, args=(A, B, mu), xtol=1e-15, rtol=4 * np.finfo(float).eps)
    return la, float(thick_sphere_pressure(la, A, B, mu))


def thick_sphere_inner_stretch(P: float, A: float, B: float, mu: float) -> float:
    """Inner hoop stretch λ_a = a/A for pressure P on the rising branch 1 ≤ λ_a ≤ λ_a*.

    Raises ValueError if P exceeds the limit-point pressure (see :func:`thick_sphere_limit_point`).
    """
    la_max, p_max = thick_sphere_limit_point(A, B, mu)
    if P < 0:
        raise ValueError("thick_sphere_inner_stretch: only P >= 0 is supported")
    if P > p_max:
        raise ValueError(f"P = {P} exceeds the limit-point pressure {p_max} (at lambda_a = {la_max})")
    if P == 0:
        return 1.0
    return brentq(
        lambda la: float(thick_sphere_pressure(la, A, B, mu)) - P,
        1.0,
        la_max,
        xtol=1e-15,
        rtol=4 * np.finfo(float).eps,
    )


def thick_sphere_incompressible_displacement(R: npt.ArrayLike, lambda_a: float, A: float) -> Any:
    """Radial displacement u(R) = r − R of the incompressible sphere, r³ = R³ + A³(λ_a³ − 1)."""
    R = np.asarray(R, dtype=float)
    return _unwrap(np.cbrt(R**3 + A**3 * (lambda_a**3 - 1.0)) - R)


@dataclass(frozen=True)
class LameSphere:
    """Linear-elastic (Lamé) pressurised sphere: u(R) = c1 R + c2/R².

    From σ_rr = (λ + 2μ)u' + 2λ u/R = (3λ + 2μ)c1 − 4μ c2/R³ with σ_rr(A) = −P, σ_rr(B) = 0:
    c1 = P A³ / ((3λ + 2μ)(B³ − A³)),  c2 = P A³ B³ / (4μ (B³ − A³)).
    """

    c1: float
    c2: float
    mu: float
    lmbda: float

    def u(self, R: npt.ArrayLike) -> Any:
        R = np.asarray(R, dtype=float)
        return _unwrap(self.c1 * R + self.c2 / R**2)

    def sigma_rr(self, R: npt.ArrayLike) -> Any:
        R = np.asarray(R, dtype=float)
        return _unwrap((3 * self.lmbda + 2 * self.mu) * self.c1 - 4 * self.mu * self.c2 / R**3)

    def sigma_tt(self, R: npt.ArrayLike) -> Any:
        R = np.asarray(R, dtype=float)
        return _unwrap((3 * self.lmbda + 2 * self.mu) * self.c1 + 2 * self.mu * self.c2 / R**3)


def thick_sphere_lame(P: float, A: float, B: float, mu: float, lmbda: float) -> LameSphere:
    """Lamé solution of the pressurised thick sphere (see :class:`LameSphere`)."""
    d = B**3 - A**3
    return LameSphere(c1=P * A**3 / ((3 * lmbda + 2 * mu) * d), c2=P * A**3 * B**3 / (4 * mu * d), mu=mu, lmbda=lmbda)


@dataclass(frozen=True)
class SphereSolution:
    """Result of :func:`thick_sphere_compressible` (all functions of the reference radius R).

    ``u(R)`` radial displacement r − R, ``du(R)`` = du/dR, ``u_inner`` = u(A), ``u_outer`` = u(B),
    ``sigma_rr(R)`` / ``sigma_tt(R)`` Cauchy stresses, ``n_nodes`` final collocation mesh size.
    """

    u: Callable[[npt.ArrayLike], Array]
    du: Callable[[npt.ArrayLike], Array]
    sigma_rr: Callable[[npt.ArrayLike], Array]
    sigma_tt: Callable[[npt.ArrayLike], Array]
    u_inner: float
    u_outer: float
    n_nodes: int


def thick_sphere_compressible(
    law: str | Law,
    params: Any,
    P: float,
    A: float,
    B: float,
    *,
    tol: float = 1e-10,
    max_nodes: int = 50_000,
) -> SphereSolution:
    """Pressurised thick sphere A ≤ R ≤ B of any isotropic law, by ``scipy.integrate.solve_bvp``.

    Unknown r(R) = R + u(R), principal stretches λ_r = dr/dR = 1 + u', λ_θ = r/R = 1 + u/R, and
    principal first Piola stresses P_RR = ∂ψ̂/∂λ_r, P_ΘΘ = ∂ψ̂/∂λ_θ taken from the hand-derived
    3×3 piola at F = diag(λ_r, λ_θ, λ_θ) (:func:`principal_piola`). Reference equilibrium

        d P_RR/dR + 2 (P_RR − P_ΘΘ)/R = 0,

    expanded with dλ_θ/dR = (λ_r − λ_θ)/R into u'' = −[2(P_RR − P_ΘΘ) + ∂P_RR/∂λ_θ (λ_r − λ_θ)]
    / (R ∂P_RR/∂λ_r); the two tangents are complex-step derivatives of the hand-derived piola
    (exact to rounding). Boundary conditions (Cauchy σ_rr = P_RR/λ_θ²):
    P_RR(A) = −P λ_θ(A)² (pressure on the deformed inner surface), P_RR(B) = 0. For ``linear``
    the small-strain BC P_RR(A) = −P is used instead, so it reproduces the Lamé solution.

    Numerics: the ODE is solved in the scaled variables x = R/B, w = u/s (s = Lamé estimate of
    u(A)), first to 1e-4 on a coarse mesh (with load continuation if the linear guess is too far
    off), then to the relative collocation tolerance ``tol``; the boundary Jacobian is exact
    (complex step). ``tol`` is floored at the rounding level (≈100 eps B/s for the ODE,
    10 eps (λ + 2μ)/P for the tractions), otherwise a tiny load or a huge λ would refine the
    mesh forever. Observed displacement errors with the default tol = 1e-10: ~1e-13 relative
    for compressible laws (``linear`` vs Lamé: ~1e-14), ~4e-9 for λ/μ = 5·10⁴ at P = 0.6 μ.

    Requires shear stiffness (ValueError for ``exponential_cg``). Raises RuntimeError when no
    solution is found, typically because P exceeds the law's limit-point pressure (compressible
    neo-Hookean, μ = 1, λ = 3, A = 1, B = 2: between 0.75 and 0.8).
    """
    obj = _law(law, params)
    mu_l, lam_l = obj.lame(params)
    if not mu_l > 0:
        raise ValueError(f"thick_sphere_compressible needs a law with shear stiffness ('{obj.name}' has mu = 0)")
    if not 0 < A < B:
        raise ValueError("need 0 < A < B")
    small_strain = obj.name == "linear"

    if P == 0:
        zero = lambda R: np.zeros_like(np.asarray(R, dtype=float))  # noqa: E731
        return SphereSolution(zero, zero, zero, zero, 0.0, 0.0, 0)

    lame = thick_sphere_lame(P, A, B, mu_l, lam_l)
    s = abs(float(lame.u(A)))  # displacement scale
    xa = A / B
    h = 1e-30  # complex step (stretches are O(1))

    def stretches(x: Array, y: Array) -> tuple[Array, Array]:
        lr = 1.0 + (s / B) * y[1]
        lt = 1.0 + s * y[0] / (B * x)
        return lr, lt

    def p_rr_tt(lr: Array, lt: Array) -> tuple[Array, Array]:
        Pd = principal_piola(obj, params, np.stack([lr, lt, lt], axis=-1))
        return Pd[..., 0], Pd[..., 1]

    def rhs(x: Array, y: Array) -> Array:
        lr, lt = stretches(x, y)
        R = B * x
        Pr_c = principal_piola(obj, params, np.stack([lr + 1j * h, lt + 0j, lt + 0j], axis=-1))[..., 0]
        Pt_c = principal_piola(obj, params, np.stack([lr + 0j, lt + 1j * h, lt + 1j * h], axis=-1))
        P_rr, P_tt = Pt_c[..., 0].real, Pt_c[..., 1].real
        dPrr_dlr = Pr_c.imag / h
        dPrr_dlt = Pt_c[..., 0].imag / h
        upp = -(2.0 * (P_rr - P_tt) + dPrr_dlt * (lr - lt)) / (R * dPrr_dlr)
        return np.vstack([y[1], (B**2 / s) * upp])

    def make_bc(p_load: float) -> tuple[Callable[..., Array], Callable[..., tuple[Array, Array]]]:
        """Scaled traction residuals and their exact (complex-step) Jacobian."""

        def bc(ya: Array, yb: Array) -> Array:
            lr_a, lt_a = stretches(np.array([xa]), ya[:, None])
            lr_b, lt_b = stretches(np.array([1.0]), yb[:, None])
            pa = p_rr_tt(lr_a, lt_a)[0][0]
            pb = p_rr_tt(lr_b, lt_b)[0][0]
            load = p_load if small_strain else p_load * lt_a[0] ** 2
            return np.array([(pa + load) / P, pb / P])

        def bc_jac(ya: Array, yb: Array) -> tuple[Array, Array]:
            d_a = np.array([bc(ya + 1j * h * e, yb + 0j).imag / h for e in np.eye(2)]).T
            d_b = np.array([bc(ya + 0j, yb + 1j * h * e).imag / h for e in np.eye(2)]).T
            return d_a, d_b

        return bc, bc_jac

    # Initial guess: the linear solution (scaled), then load continuation if needed.
    x0 = np.linspace(xa, 1.0, 41)
    y_guess = np.vstack([lame.u(B * x0) / s, B * (lame.c1 - 2 * lame.c2 / (B * x0) ** 3) / s])

    # Rounding: stretches 1 + O(s/B) carry strains with relative error ~eps B/s, and solve_bvp's
    # residual estimate divides by the mesh size, so a tolerance below that noise floor only
    # refines the mesh forever. Hence the floor on the requested tolerance.
    # Likewise the boundary tractions carry rounding ~eps·M (M = ∂P_RR/∂λ_r at F = I, the
    # P-wave modulus λ + 2μ), which is large relative to P for nearly incompressible laws.
    eps = np.finfo(float).eps
    tol_eff = max(tol, 100 * eps * B / s)
    M = float(principal_piola(obj, params, np.array([1.0 + 1j * h, 1.0, 1.0]))[0].imag / h)
    bc_tol_eff = max(tol_eff, 10 * eps * M / abs(P))

    def solve(p_load: float, x: Array, y: Array, tol_: float, nodes: int = max_nodes) -> Any:
        with np.errstate(all="ignore"):
            bc, bc_jac = make_bc(p_load)
            return solve_bvp(rhs, bc, x, y, bc_jac=bc_jac, tol=tol_, bc_tol=max(tol_, bc_tol_eff), max_nodes=nodes)

    # Stage 1: converge the nonlinear problem on a coarse mesh, with load continuation if the
    # linear guess is too far off. Stage 2: refine to the requested tolerance from there.
    coarse_tol, coarse_nodes = max(tol_eff, 1e-4), min(max_nodes, 2000)
    sol = solve(P, x0, y_guess, coarse_tol, coarse_nodes)
    if not sol.success:
        done, frac, x_cur, y_cur = 0.0, 0.25, x0, 0.0 * y_guess
        while done < 1.0:
            trial = min(1.0, done + frac)
            res = solve(trial * P, x_cur, y_cur, coarse_tol, coarse_nodes)
            if res.success:
                done, x_cur, y_cur, sol = trial, res.x, res.y, res
                frac = min(2 * frac, 1.0)
            else:
                frac /= 2
                if frac < 1e-3:
                    raise RuntimeError(
                        f"thick_sphere_compressible: no solution for law '{obj.name}' at P = {P} "
                        f"(reached {done * P}; beyond the limit point?): {res.message}"
                    )
    sol = solve(P, sol.x, sol.y, tol_eff)
    if not sol.success:
        raise RuntimeError(f"thick_sphere_compressible: refinement to tol = {tol_eff:g} failed: {sol.message}")
    spline = sol.sol

    def u(R: npt.ArrayLike) -> Any:
        return _unwrap(s * spline(np.asarray(R, dtype=float) / B)[0])

    def du(R: npt.ArrayLike) -> Any:
        return _unwrap((s / B) * spline(np.asarray(R, dtype=float) / B)[1])

    def _cauchy(R: npt.ArrayLike) -> tuple[Array, Array]:
        R = np.asarray(R, dtype=float)
        y = spline(R / B)
        lr, lt = stretches(R / B, y)
        P_rr, P_tt = p_rr_tt(lr, lt)
        if small_strain:
            return P_rr, P_tt
        return P_rr / lt**2, P_tt / (lr * lt)  # σ = P Fᵀ/J with J = λ_r λ_θ²

    return SphereSolution(
        u=u,
        du=du,
        sigma_rr=lambda R: _unwrap(_cauchy(R)[0]),
        sigma_tt=lambda R: _unwrap(_cauchy(R)[1]),
        u_inner=float(u(A)),
        u_outer=float(u(B)),
        n_nodes=int(sol.x.size),
    )


# ============================================================================================
# Euler–Bernoulli beams
# ============================================================================================

#: Roots βₙL of 1 + cos(βL) cosh(βL) = 0 (clamped–free beam), first three modes.
CANTILEVER_BETA_L: tuple[float, float, float] = (1.8751040687, 4.6940911330, 7.8547574382)


def cantilever_tip_deflection(P: float, L: float, E: float, I: float) -> float:
    """Tip deflection δ = P L³ / (3 E I) of a cantilever under a tip force P."""
    return P * L**3 / (3.0 * E * I)


def cantilever_beta_l(n: int) -> float:
    """n-th root (n ≥ 1) of 1 + cos x cosh x = 0, i.e. of cos x + 1/cosh x = 0, to machine precision."""
    if n < 1:
        raise ValueError("n >= 1")
    c = (n - 0.5) * math.pi
    return brentq(
        lambda x: math.cos(x) + 1.0 / math.cosh(x), c - 0.5, c + 0.5, xtol=1e-15, rtol=4 * np.finfo(float).eps
    )


def cantilever_frequencies(E: float, I: float, rho: float, A: float, L: float, n_modes: int = 3) -> Array:
    """Angular natural frequencies ωₙ = (βₙL)² √(EI/(ρ A L⁴)) [rad/s] of a clamped–free beam."""
    beta_l = np.array([cantilever_beta_l(n) for n in range(1, n_modes + 1)])
    return beta_l**2 * math.sqrt(E * I / (rho * A * L**4))


def cantilever_mode_shape(x: npt.ArrayLike, n: int, L: float) -> Array:
    """Mode shape φₙ(x) = cosh βx − cos βx − k(sinh βx − sin βx), k = (cosh βL + cos βL)/(sinh βL + sin βL).

    Clamped at x = 0 (φ = φ' = 0), free at x = L (φ'' = φ''' = 0); normalised so φₙ(L) = 2·(−1)^(n+1)
    in the classical convention (not unit-normalised).
    """
    bl = cantilever_beta_l(n)
    b = bl / L
    k = (math.cosh(bl) + math.cos(bl)) / (math.sinh(bl) + math.sin(bl))
    x = np.asarray(x, dtype=float)
    return np.cosh(b * x) - np.cos(b * x) - k * (np.sinh(b * x) - np.sin(b * x))


# ============================================================================================
# Lung poromechanics (Patte, Genet & Chapelle 2022): homogeneous inflation
# ============================================================================================


@dataclass(frozen=True)
class LungParams:
    """Skeleton α(e^{γ(J²−1−2lnJ)} − 1) + c1(I1−3−2lnJ) + c2(I2−3−4lnJ); bulk κ(Φs/Φs0 − 1 − ln(Φs/Φs0))."""

    alpha: float = 0.16
    gamma: float = 0.5
    c1: float = 0.2
    c2: float = 0.4
    kappa: float = 100.0
    phi_s0: float = 0.5


def lung_skeleton_principal_stress(stretches: tuple[float, float, float], p: LungParams) -> float:
    """Cauchy stress σ_11 of the skeleton at principal stretches (λ1, λ2, λ3), J = λ1 λ2 λ3:

    σ_11 = (λ1/J) ∂W/∂λ1 = (λ1/J)[2c1 λ1 + 2c2 λ1 (λ2² + λ3²)] + ∂W/∂J,
    ∂W/∂J = αγ e^{γ(J²−1−2lnJ)} (2J − 2/J) − (2c1 + 4c2)/J,

    from W = α(e^{γ(J²−1−2lnJ)} − 1) + c1(I1 − 3 − 2lnJ) + c2(I2 − 3 − 4lnJ), I1 = Σλi², I2 = Σ_{i<j} λi²λj².
    """
    l1, l2, l3 = stretches
    J = l1 * l2 * l3
    volumetric = p.alpha * p.gamma * math.exp(p.gamma * (J**2 - 1.0 - 2.0 * math.log(J))) * (2.0 * J - 2.0 / J)
    return l1 / J * (2.0 * p.c1 * l1 + 2.0 * p.c2 * l1 * (l2**2 + l3**2)) + volumetric - (2.0 * p.c1 + 4.0 * p.c2) / J


def lung_skeleton_stress(J: float, p: LungParams, plane: bool = False) -> float:
    """In-plane Cauchy stress σ_skel of the skeleton under a homogeneous dilation of volume ratio J:
    isotropic, λ = J^(1/3) (VERIFICATION.md: σ_skel(J) = (2/J)(c1 λ² + 2 c2 λ⁴) − (2c1 + 4c2)/J +
    αγ e^{γ(J²−1−2lnJ)} (2J − 2/J)), or in plane strain (``plane``), λ1 = λ2 = √J, λ3 = 1."""
    stretches = (math.sqrt(J), math.sqrt(J), 1.0) if plane else (J ** (1.0 / 3.0),) * 3
    return lung_skeleton_principal_stress(stretches, p)


def lung_scalings(p: LungParams, scaling: str) -> tuple[float, float]:
    """(s_skel, s_bulk): which energies Φs0 multiplies — "none", "skeleton" or "linear" (all)."""
    return (p.phi_s0 if scaling in ("skeleton", "linear") else 1.0), (p.phi_s0 if scaling == "linear" else 1.0)


def lung_inflation(p_f: float, p: LungParams, scaling: str = "none", plane: bool = False) -> dict[str, float]:
    """Homogeneous free inflation of a lung sample by the alveolar (fluid) pressure p_f, in 3-D or
    in plane strain (``plane``: the sample held in z, free in x and y).

    The skeleton balances the fluid pressure in the free directions, s_skel σ_skel(J) = p_f; the
    solid fraction solves s_bulk ∂W_bulk/∂Φs + p_f = 0, i.e. Φs = 1/(1/Φs0 + p_f/(s_bulk κ)).
    Returns the volume ratio J, the Green–Lagrange strain E of a free direction ((J^(2/3) − 1)/2,
    or (J − 1)/2 in plane strain), Φs, Φf = J − Φs and φs = Φs/J.
    """
    s_skel, s_bulk = lung_scalings(p, scaling)
    J = 1.0
    if p_f != 0.0:
        # σ_skel increases with J: grow a bracket from J = 1 towards the root (no overflow).
        factor = 1.25 if p_f > 0 else 0.8
        end = factor
        while (s_skel * lung_skeleton_stress(end, p, plane) - p_f) * (0.0 - p_f) > 0:
            end *= factor
        J = brentq(
            lambda j: s_skel * lung_skeleton_stress(j, p, plane) - p_f,
            min(1.0, end),
            max(1.0, end),
            xtol=1e-15,
            rtol=4 * np.finfo(float).eps,
        )
    phi_s = 1.0 / (1.0 / p.phi_s0 + p_f / (s_bulk * p.kappa))
    strain = 0.5 * (J - 1.0) if plane else 0.5 * (J ** (2.0 / 3.0) - 1.0)
    return {"J": J, "E": strain, "phi_s": phi_s, "phi_f": J - phi_s, "phi_s_current": phi_s / J}


def pore_barrier_derivative(
    phi_f: float, phi_s0: float, eta: float, lower: float, upper: float, exponent: float = 2.0
) -> float:
    """dW_pore/dΦf of W_pore = η(lower/r − 1)^m (r < lower), η(r/upper − 1)^m (r > upper), else 0;
    r = Φf/(1 − Φs0)."""
    phi_f0 = 1.0 - phi_s0
    r, m = phi_f / phi_f0, exponent
    if r < lower:
        return m * eta * (lower / r - 1.0) ** (m - 1) * (-lower / r**2) / phi_f0
    if r > upper:
        return m * eta * (r / upper - 1.0) ** (m - 1) / upper / phi_f0
    return 0.0


def lung_inflation_with_pore_barrier(
    p_f: float,
    p: LungParams,
    eta: float,
    lower: float,
    upper: float,
    exponent: float = 2.0,
    scaling: str = "none",
    plane: bool = False,
) -> dict[str, float]:
    """Homogeneous inflation with the porosity barrier: two scalar equations for (J, Φs).

    u-equation: s_skel σ_skel(J) + s_bulk W_pore'(J − Φs) − p_f = 0;
    Φs-equation: s_bulk [κ(1/Φs0 − 1/Φs) − W_pore'(J − Φs)] + p_f = 0.
    """
    from scipy.optimize import fsolve

    s_skel, s_bulk = lung_scalings(p, scaling)

    def equations(z):
        J, phi_s = z
        w = pore_barrier_derivative(J - phi_s, p.phi_s0, eta, lower, upper, exponent)
        return [
            s_skel * lung_skeleton_stress(J, p, plane) + s_bulk * w - p_f,
            s_bulk * (p.kappa * (1.0 / p.phi_s0 - 1.0 / phi_s) - w) + p_f,
        ]

    start = lung_inflation(p_f, p, scaling, plane)
    (J, phi_s), info, ok, message = fsolve(equations, [start["J"], start["phi_s"]], xtol=1e-14, full_output=True)
    if np.abs(equations((J, phi_s))).max() > 1e-13 * max(1.0, abs(p_f)):  # fsolve may stop at round-off
        raise RuntimeError(message)
    return {"J": J, "phi_s": phi_s, "phi_f": J - phi_s}
