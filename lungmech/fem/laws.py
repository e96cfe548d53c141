"""The hyperelastic strain-energy laws, each a small frozen dataclass with its formula.

See :mod:`lungmech.fem.materials` for the notation and for how laws are used (stresses by UFL
differentiation, parameters as Constants); the checks and bases they share are
:mod:`lungmech.fem.law_base`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import ufl
from ufl.core.expr import Expr

from lungmech.errors import ParameterError
from lungmech.fem.kinematics import green_lagrange, invariants, small_strain
from lungmech.fem.law_base import (
    LameLaw,
    LameSplitLaw,
    Material,
    Param,
    SplitLaw,
    lame_from_young,
    nonpolynomial_degree,
    plain_numbers,
    require,
)


@dataclass(frozen=True, slots=True)
class LinearElastic(LameLaw):
    """Linear (small-strain) isotropic elasticity, Hooke's law.

    .. math:: ψ(F) = μ ε:ε + λ/2 (tr ε)²,   ε = sym(F − I) = sym(∇u)

    Its stress ∂ψ/∂F = 2με + λ (tr ε) I is the Cauchy stress of the linear theory.

    Parameters
    ----------
    mu : float or UFL expression
        Shear modulus μ (Pa), > 0.
    lmbda : float or UFL expression
        Lamé's first parameter λ (Pa), finite, with a positive bulk modulus λ + 2μ/3 > 0.

    Notes
    -----
    Valid for small displacement gradients only. It is not frame-indifferent: a rigid rotation
    by θ gives a stress of order μθ² (a test checks that it does). Scene name ``linear``;
    ``from_young(E, nu)`` builds it from Young's modulus and Poisson's ratio.
    """

    mu: Param
    lmbda: Param
    name: ClassVar[str] = "linear"
    small_strain: ClassVar[bool] = True  # its stress ∂ψ/∂F is σ itself: no finite-strain push-forward

    def psi(self, F: Expr) -> Expr:
        """μ ε:ε + λ/2 (tr ε)² (Pa)."""
        eps = small_strain(F)
        return self.mu * ufl.inner(eps, eps) + self.lmbda / 2 * ufl.tr(eps) ** 2

    def quadrature_degree(self, gradient_degree: int) -> int:
        """2·deg(∇u): ψ is quadratic in ∇u, so this is exact."""
        return 2 * gradient_degree


@dataclass(frozen=True, slots=True)
class SaintVenantKirchhoff(LameLaw):
    """Saint Venant–Kirchhoff: Hooke's law written in the Green–Lagrange strain.

    .. math:: ψ(F) = μ E:E + λ/2 (tr E)²,   E = ½(C − I)

    Parameters
    ----------
    mu : float or UFL expression
        Shear modulus μ (Pa), > 0.
    lmbda : float or UFL expression
        Lamé's first parameter λ (Pa), finite, with λ + 2μ/3 > 0.

    Notes
    -----
    Small-strain limit: the linear law with the same μ, λ. Frame-indifferent, so it handles
    large rotations, but only moderate strains: it softens under compression (for ν = 0 the
    uniaxial nominal stress E λ(λ² − 1)/2 peaks at the stretch λ = 1/√3) and ψ stays finite as J → 0, so nothing
    stops a cell from inverting. Lungmech cuts back any step whose solution has J ≤ 0. Scene name
    ``saint_venant_kirchhoff``; ``from_young(E, nu)`` builds it from (E, ν).
    """

    mu: Param
    lmbda: Param
    name: ClassVar[str] = "saint_venant_kirchhoff"

    def psi(self, F: Expr) -> Expr:
        """μ E:E + λ/2 (tr E)² (Pa)."""
        E = green_lagrange(F)
        return self.mu * ufl.inner(E, E) + self.lmbda / 2 * ufl.tr(E) ** 2

    def quadrature_degree(self, gradient_degree: int) -> int:
        """4·deg(∇u): ψ is quartic in ∇u, so this is exact."""
        return 4 * gradient_degree


@dataclass(frozen=True, slots=True)
class NeoHookean(LameSplitLaw):
    """Compressible neo-Hookean law.

    .. math:: ψ(F) = μ/2 (I1 − 3) − μ ln J + λ/2 (ln J)²

    Volumetric split: ψ_iso = μ/2 (I1 − 3) − μ ln J, g(J) = ln J, bulk = λ.

    Parameters
    ----------
    mu : float or UFL expression
        Shear modulus μ (Pa), > 0.
    lmbda : float or UFL expression
        Lamé's first parameter λ (Pa), with λ + 2μ/3 > 0; ``inf`` (``incompressible(mu)``) is
        the incompressible law ψ = μ/2 (I1 − 3) with J = 1, for the mixed formulation only.

    Notes
    -----
    Small-strain limit: the linear law with the same μ, λ. Valid at large strains of rubber-like
    materials; ψ → ∞ as J → 0, so the energy itself keeps cells from inverting. Scene name
    ``neo_hookean``; ``from_young(E, nu)`` builds it from (E, ν).
    """

    mu: Param
    lmbda: Param
    name: ClassVar[str] = "neo_hookean"

    @property
    def bulk(self) -> Param:
        """The modulus of the volumetric split, λ (Pa)."""
        return self.lmbda

    def psi_iso(self, F: Expr) -> Expr:
        """μ/2 (I1 − 3) − μ ln J (Pa)."""
        I1, _, J = invariants(F)
        return self.mu / 2 * (I1 - 3) - self.mu * ufl.ln(J)

    def volumetric(self, J: Expr) -> Expr:
        """g(J) = ln J."""
        return ufl.ln(J)


@dataclass(frozen=True, slots=True)
class StableNeoHookean(LameSplitLaw):
    """Stable neo-Hookean law of Smith, de Goes & Kim (2018).

    .. math:: ψ(F) = μ'/2 (I1 − 3) + λ'/2 (J − a)² − μ'/2 ln(I1 + 1),
              μ' = 4μ/3,  λ' = λ + 5μ/6,  a = 1 + 3μ'/(4λ')

    Volumetric split: ψ_iso = μ'/2 (I1 − 3) − μ'/2 ln(I1 + 1), g(J) = J − a, bulk = λ'.

    Parameters
    ----------
    mu : float or UFL expression
        Shear modulus μ (Pa) of the small-strain limit, > 0.
    lmbda : float or UFL expression
        Lamé's first parameter λ (Pa) of the small-strain limit, with λ + 2μ/3 > 0; ``inf``
        (``incompressible(mu)``) gives g(J) = J − 1 = 0, for the mixed formulation only.

    Notes
    -----
    Small-strain limit: the linear law with μ, λ (μ', λ' and a are chosen for that, and make the
    stress vanish at F = I). ψ(I) = 9μ'²/(32λ') − μ' ln 2 is a constant, not zero. ψ has no
    ln J, so it is defined for every F, inverted ones included (an iterate that inverts a cell
    leaves ψ finite), but it has no barrier at J = 0 either. Scene name ``stable_neo_hookean``; ``from_young(E, nu)`` builds it
    from (E, ν).
    """

    mu: Param
    lmbda: Param
    name: ClassVar[str] = "stable_neo_hookean"

    @property
    def bulk(self) -> Param:
        """The modulus of the volumetric split, λ' = λ + 5μ/6 (Pa)."""
        return self.lmbda + 5 * self.mu / 6

    def psi_iso(self, F: Expr) -> Expr:
        """μ'/2 (I1 − 3) − μ'/2 ln(I1 + 1) with μ' = 4μ/3 (Pa)."""
        I1, _, _ = invariants(F)
        mu_s = 4 * self.mu / 3
        return mu_s / 2 * (I1 - 3) - mu_s / 2 * ufl.ln(I1 + 1)

    def volumetric(self, J: Expr) -> Expr:
        """g(J) = J − a, a = 1 + 3μ'/(4λ')."""
        return J - (1 + 3 * (4 * self.mu / 3) / (4 * self.bulk))


@dataclass(frozen=True, slots=True)
class MooneyRivlin(SplitLaw):
    """Compressible Mooney–Rivlin law.

    .. math:: ψ(F) = c1 (I1 − 3 − 2 ln J) + c2 (I2 − 3 − 4 ln J) + bulk/2 (ln J)²

    The −2 ln J and −4 ln J make the stress vanish at F = I. Volumetric split:
    ψ_iso = the first two terms, g(J) = ln J.

    Parameters
    ----------
    c1 : float or UFL expression
        Coefficient of the first invariant (Pa), ≥ 0.
    c2 : float or UFL expression
        Coefficient of the second invariant (Pa), ≥ 0, with c1 + c2 > 0.
    bulk : float or UFL expression
        Modulus of the volumetric term (Pa), > 0; ``inf`` (``incompressible(c1, c2)``) is the
        incompressible law, for the mixed formulation only.

    Notes
    -----
    Small-strain limit: μ = 2(c1 + c2), λ = bulk + 4 c2. c2 = 0 is a neo-Hookean law (with
    μ = 2 c1, λ = bulk). Valid at large strains of rubber-like materials; ψ → ∞ as J → 0. Scene
    name ``mooney_rivlin``; ``from_young(E, nu, c2_share)`` builds it from (E, ν).
    """

    c1: Param
    c2: Param
    bulk: Param
    name: ClassVar[str] = "mooney_rivlin"

    def __post_init__(self) -> None:
        if (p := plain_numbers(self)) is not None:
            require(self, p["c1"] >= 0 and p["c2"] >= 0 and p["c1"] + p["c2"] > 0, "need c1, c2 >= 0, c1 + c2 > 0")
            require(self, p["bulk"] > 0, f"bulk must be > 0 (got {p['bulk']})")

    @classmethod
    def from_young(cls, E: float, nu: float, c2_share: float = 0.5) -> MooneyRivlin:
        """The law matching Young's modulus ``E`` (Pa) and Poisson's ratio ``nu`` (1) at small
        strain: c2 carries the fraction ``c2_share`` (1, default 0.5) of the shear modulus, and λ
        is matched through the bulk term (bulk = λ − 4 c2)."""
        mu, lmbda = lame_from_young(E, nu)
        c2 = c2_share * mu / 2
        return cls(mu / 2 - c2, c2, lmbda - 4 * c2)

    @classmethod
    def incompressible(cls, c1: float, c2: float) -> MooneyRivlin:
        """The incompressible law (bulk = inf) with ``c1``, ``c2`` (Pa); it needs the mixed
        formulation."""
        return cls(c1, c2, math.inf)

    def psi_iso(self, F: Expr) -> Expr:
        """c1 (I1 − 3 − 2 ln J) + c2 (I2 − 3 − 4 ln J) (Pa)."""
        I1, I2, J = invariants(F)
        return self.c1 * (I1 - 3 - 2 * ufl.ln(J)) + self.c2 * (I2 - 3 - 4 * ufl.ln(J))

    def volumetric(self, J: Expr) -> Expr:
        """g(J) = ln J."""
        return ufl.ln(J)


@dataclass(frozen=True, slots=True)
class CiarletGeymonat:
    """Ciarlet–Geymonat law, with optional neo-Hookean and Mooney–Rivlin terms.

    .. math:: ψ(F) = c0 (J² − 1 − 2 ln J) + c1 (I1 − 3 − 2 ln J) + c2 (I2 − 3 − 4 ln J)

    c1 = c2 = 0 is the pure Ciarlet–Geymonat bulk term (CG), c2 = 0 its neo-Hookean sum (CGNH),
    all three the CGNHMR law; the lung skeleton uses its shear part (c0 = 0), see
    :func:`lungmech.lung.skeleton`.

    Parameters
    ----------
    c0 : float or UFL expression
        Coefficient of the volumetric term J² − 1 − 2 ln J (Pa), ≥ 0.
    c1 : float or UFL expression
        Coefficient of the first invariant (Pa), ≥ 0; default 0.
    c2 : float or UFL expression
        Coefficient of the second invariant (Pa), ≥ 0; default 0. Not all three are zero.

    Notes
    -----
    Small-strain limit: μ = 2(c1 + c2), λ = 4(c0 + c2). J² − 1 − 2 ln J grows as J² in
    expansion and as −2 ln J → ∞ as J → 0, so it is a barrier against inversion. With c1 = c2 = 0
    the law has no shear stiffness. No volumetric split, so no mixed formulation. Scene name
    ``ciarlet_geymonat``; ``from_young(E, nu, c2_share)`` builds it from (E, ν).
    """

    c0: Param
    c1: Param = 0.0
    c2: Param = 0.0
    name: ClassVar[str] = "ciarlet_geymonat"

    def __post_init__(self) -> None:
        if (p := plain_numbers(self)) is not None:
            require(self, min(p.values()) >= 0 and max(p.values()) > 0, "need c0, c1, c2 >= 0, not all zero")

    @classmethod
    def from_young(cls, E: float, nu: float, c2_share: float = 0.0) -> CiarletGeymonat:
        """The law matching Young's modulus ``E`` (Pa) and Poisson's ratio ``nu`` (1) at small
        strain: c2 carries the fraction ``c2_share`` (1, default 0) of the shear modulus, and
        c0 = λ/4 − c2, c1 = μ/2 − c2. Refused where c0 would be negative (low ν)."""
        mu, lmbda = lame_from_young(E, nu)
        c2 = c2_share * mu / 2
        if lmbda / 4 - c2 < 0:
            raise ParameterError(
                f"CiarletGeymonat: nu = {nu} is too low for c2_share = {c2_share} (c0 would be negative)"
            )
        return cls(lmbda / 4 - c2, mu / 2 - c2, c2)

    def psi(self, F: Expr) -> Expr:
        """c0 (J² − 1 − 2 ln J) + c1 (I1 − 3 − 2 ln J) + c2 (I2 − 3 − 4 ln J) (Pa)."""
        I1, I2, J = invariants(F)
        lnJ = ufl.ln(J)
        return self.c0 * (J**2 - 1 - 2 * lnJ) + self.c1 * (I1 - 3 - 2 * lnJ) + self.c2 * (I2 - 3 - 4 * lnJ)

    def quadrature_degree(self, gradient_degree: int) -> int:
        """Exact for constant ∇u, 2·deg(∇u) + 2 otherwise (ψ has a logarithm)."""
        return nonpolynomial_degree(gradient_degree)


@dataclass(frozen=True, slots=True)
class ExponentialCiarletGeymonat:
    """Exponential Ciarlet–Geymonat law: the stiffening volumetric part of the lung skeleton.

    .. math:: ψ(F) = α (exp(γ (J² − 1 − 2 ln J)) − 1)

    Parameters
    ----------
    alpha : float or UFL expression
        Stiffness α (Pa), > 0.
    gamma : float or UFL expression
        Exponential rate γ (1), > 0.

    Notes
    -----
    Depends on J alone: no shear stiffness (add a shear law with :class:`Sum`). Small-strain
    limit: μ = 0, λ = 4αγ. The volume stiffness grows exponentially in both compression and
    expansion, and ψ → ∞ as J → 0. No volumetric split, so no mixed formulation. Scene name
    ``exponential_ciarlet_geymonat``; with CGNHMR shear terms it is the lung skeleton W_skel of
    Patte, Genet & Chapelle (2022), see :func:`lungmech.lung.skeleton`.
    """

    alpha: Param
    gamma: Param
    name: ClassVar[str] = "exponential_ciarlet_geymonat"

    def __post_init__(self) -> None:
        if (p := plain_numbers(self)) is not None:
            require(self, p["alpha"] > 0 and p["gamma"] > 0, "need alpha > 0 and gamma > 0")

    def psi(self, F: Expr) -> Expr:
        """α (exp(γ (J² − 1 − 2 ln J)) − 1) (Pa)."""
        J = ufl.det(F)
        return self.alpha * (ufl.exp(self.gamma * (J**2 - 1 - 2 * ufl.ln(J))) - 1)

    def quadrature_degree(self, gradient_degree: int) -> int:
        """Exact for constant ∇u, 2·deg(∇u) + 2 otherwise (ψ has an exponential)."""
        return nonpolynomial_degree(gradient_degree)


@dataclass(frozen=True, slots=True)
class Sum:
    """The sum of laws, e.g. the lung skeleton: exponential CG + CGNHMR.

    .. math:: ψ(F) = Σᵢ ψᵢ(F)

    Parameters
    ----------
    terms : tuple of laws
        At least one law; their parameters keep their own units.

    Notes
    -----
    Small-strain limit: the sums of the terms' μ and λ. No volumetric split, so no mixed
    formulation. Scene name ``sum``, with ``terms = [{law = ...}, ...]``.
    """

    terms: tuple[Material, ...]
    label: str = field(default="", compare=False)  # the named law it is, if any (e.g. "lung_skeleton")
    name: ClassVar[str] = "sum"

    def __post_init__(self) -> None:
        if not self.terms:
            raise ParameterError("Sum: needs at least one law")

    def psi(self, F: Expr) -> Expr:
        """Σᵢ ψᵢ(F) (Pa)."""
        return sum((t.psi(F) for t in self.terms[1:]), self.terms[0].psi(F))

    def quadrature_degree(self, gradient_degree: int) -> int:
        """The largest of the terms' degrees."""
        return max(t.quadrature_degree(gradient_degree) for t in self.terms)
