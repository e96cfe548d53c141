"""Hyperelastic strain-energy laws.

A law is a small frozen dataclass with one method, ``psi(F) -> ufl.Expr``: the strain energy per
unit reference volume (Pa = J/m³). Stresses are never written by hand; they come from UFL
differentiation (see :func:`first_piola`). Parameters are plain floats (validated on
construction) or UFL expressions such as ``dolfinx.fem.Constant`` (see :func:`with_constants`),
so one compiled form serves every parameter value.

Notation, used in every docstring below: F the deformation gradient, C = FᵀF, I1 = tr C,
I2 = ½(I1² − tr C²), J = det F, E = ½(C − I) (Green–Lagrange), ε = sym(F − I) (linearised
strain). Moduli are in Pa, ratios and exponents are dimensionless (unit 1). "Small-strain limit"
names the Lamé parameters (μ, λ) of the linear law that ψ agrees with to second order in ∇u;
the small-strain bulk modulus is then K = λ + 2μ/3.

Laws with a volumetric split (``psi = psi_iso + bulk/2 · g(J)²``, see :class:`VolumetricSplit`)
also run in the mixed displacement–pressure formulation, which stays accurate as ν → 0.5 and is
exactly incompressible when ``bulk = inf``.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import ClassVar, Protocol, Self, runtime_checkable

import ufl

from lungmech import checks
from lungmech.errors import ParameterError
from lungmech.fem.kinematics import green_lagrange, invariants, small_strain

Param = float | ufl.core.expr.Expr  # a number, or a UFL expression such as a fem.Constant


@runtime_checkable
class Material(Protocol):
    """What every law provides: its energy and how exactly to integrate it.

    A law is also expected to carry a class attribute ``name`` (its scene name, e.g.
    ``"neo_hookean"``) and its parameters as dataclass fields.
    """

    def psi(self, F: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
        """The strain energy density ψ(F) in Pa (J per m³ of reference volume)."""
        ...

    def quadrature_degree(self, gradient_degree: int) -> int:
        """The quadrature degree for ψ when ∇u is a polynomial of degree ``gradient_degree``."""
        ...


@runtime_checkable
class VolumetricSplit(Protocol):
    """A law written ψ(F) = ψ_iso(F) + bulk/2 · g(J)² with g(1) = 0.

    The mixed formulation replaces the last term by −p g(J) − p²/(2 bulk): eliminating p gives
    back ψ exactly, and bulk = inf turns it into the constraint g(J) = 0, i.e. J = 1.
    ``psi_iso`` need not be isochoric: it is whatever the law keeps outside the bulk term.

    Attributes
    ----------
    bulk : float or UFL expression
        The modulus (Pa) in front of g(J)²/2; ``inf`` for an incompressible material.
    """

    bulk: Param

    def psi_iso(self, F: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
        """ψ without the bulk term (Pa)."""
        ...

    def volumetric(self, J: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
        """g(J), dimensionless, with g(1) = 0."""
        ...


# --- parameters ------------------------------------------------------------------------------


def lame_from_young(E: float, nu: float) -> tuple[float, float]:
    """(μ, λ) from Young's modulus and Poisson's ratio of a compressible material.

    μ = E / (2(1 + ν)) and λ = E ν / ((1 + ν)(1 − 2ν)).

    Parameters
    ----------
    E : float
        Young's modulus (Pa), > 0.
    nu : float
        Poisson's ratio (1), −1 < ν < 0.5. ν = 0.5 is refused: an incompressible law is built
        with ``incompressible(...)`` and the mixed formulation instead of an infinite λ.

    Returns
    -------
    (mu, lmbda) : tuple of float
        The shear modulus μ and Lamé's first parameter λ (Pa).
    """
    _check_real("E", E)
    _check_real("nu", nu)
    if not E > 0:
        raise ParameterError(f"Young's modulus E must be > 0 (got E = {E})")
    if not -1.0 < nu < 0.5:
        raise ParameterError(
            f"Poisson's ratio must satisfy -1 < nu < 0.5 for a compressible law (got nu = {nu}); "
            "for an incompressible material use the mixed formulation with an incompressible law"
        )
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


def _check_real(name: str, value: object) -> None:
    """A finite real number; only a bulk modulus may be +inf (the incompressible limit)."""
    checks.real(f"parameter '{name}'", value, infinite=name in ("bulk", "lmbda"))
    if math.isinf(value) and value < 0:
        raise ParameterError(f"parameter '{name}' must be a finite number or +inf (got {value})")


def _require(law: object, condition: bool, message: str) -> None:
    if not condition:
        raise ParameterError(f"{type(law).__name__}: {message}")


def _numbers(law: object) -> dict[str, float] | None:
    """The law's parameters when all are plain numbers (validation is skipped for UFL values)."""
    values = {f.name: getattr(law, f.name) for f in dataclasses.fields(law)}
    for name, v in values.items():
        if isinstance(v, bool) or not isinstance(v, numbers.Real | ufl.core.expr.Expr):
            raise ParameterError(f"parameter '{name}' must be a number (got {v!r})")
    if not all(isinstance(v, numbers.Real) for v in values.values()):
        return None
    for name, v in values.items():
        _check_real(name, v)
    return values


def numbers_of(law: Material) -> dict[str, float]:
    """The law's numeric parameters by path: ``"mu"``, or ``"terms[1].c1"`` inside a :class:`Sum`.

    Parameters already given as UFL expressions are left out.
    """
    if isinstance(law, Sum):
        return {f"terms[{i}].{path}": v for i, term in enumerate(law.terms) for path, v in numbers_of(term).items()}
    values = {f.name: getattr(law, f.name) for f in dataclasses.fields(law)}
    return {name: float(v) for name, v in values.items() if isinstance(v, numbers.Real) and not isinstance(v, bool)}


def with_values(law: Material, values: Mapping[str, Param]) -> Material:
    """A copy of ``law`` with the parameters at the paths of :func:`numbers_of` replaced."""
    if isinstance(law, Sum):
        parts = [{} for _ in law.terms]
        for path, v in values.items():
            index, _, rest = path.removeprefix("terms[").partition("].")
            parts[int(index)][rest] = v
        return dataclasses.replace(law, terms=tuple(with_values(term, part) for term, part in zip(law.terms, parts)))
    return dataclasses.replace(law, **values) if values else law


def with_constants(law: Material, mesh) -> Material:
    """A copy of ``law`` whose finite parameters are ``fem.Constant``s on ``mesh``.

    Forms built from it compile once; changing a parameter is then ``law.mu.value = ...``.
    Infinite parameters (incompressible limits) stay floats: they change the form's structure.
    A :class:`Sum` is converted term by term. Values and units are unchanged.
    """
    from dolfinx import fem

    finite = {path: v for path, v in numbers_of(law).items() if math.isfinite(v)}
    return with_values(law, {path: fem.Constant(mesh, v) for path, v in finite.items()})


def _nonpolynomial_degree(gradient_degree: int) -> int:
    """Quadrature degree for a law with logarithms/exponentials: exact when ∇u is constant."""
    return 2 * gradient_degree + 2 if gradient_degree > 0 else 0


# --- laws --------------------------------------------------------------------------------------


class _Lame:
    """Laws parametrised by the Lamé constants (mu, lmbda): validation and (E, ν) constructor."""

    def __post_init__(self):
        _check_lame(self)

    @classmethod
    def from_young(cls, E: float, nu: float) -> Self:
        """The law with the Lamé parameters of Young's modulus ``E`` (Pa) and Poisson's ratio
        ``nu`` (1, −1 < ν < 0.5), see :func:`lame_from_young`."""
        return cls(*lame_from_young(E, nu))


class _Split:
    """ψ = ψ_iso + bulk/2 g(J)² for laws that define psi_iso, volumetric and bulk."""

    def psi(self, F):
        """ψ_iso(F) + bulk/2 g(J)² (Pa). Refused for bulk = inf: only the mixed formulation can
        impose J = 1."""
        if isinstance(self.bulk, numbers.Real) and math.isinf(self.bulk):
            raise ParameterError(
                f"{type(self).__name__} is incompressible (bulk = inf): it needs the mixed formulation"
            )
        return self.psi_iso(F) + self.bulk / 2 * self.volumetric(ufl.det(F)) ** 2

    def quadrature_degree(self, gradient_degree: int) -> int:
        """Exact for constant ∇u, 2·deg(∇u) + 2 otherwise: ψ has a logarithm (see
        :func:`_nonpolynomial_degree`)."""
        return _nonpolynomial_degree(gradient_degree)


class _LameSplit(_Lame, _Split):
    """A Lamé-parametrised law with a volumetric split: λ = inf is its incompressible limit."""

    @classmethod
    def incompressible(cls, mu: float) -> Self:
        """The incompressible law (λ = inf) of shear modulus ``mu`` (Pa); it needs the mixed
        formulation."""
        return cls(mu, math.inf)


@dataclass(frozen=True, slots=True)
class LinearElastic(_Lame):
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

    def psi(self, F):
        """μ ε:ε + λ/2 (tr ε)² (Pa)."""
        eps = small_strain(F)
        return self.mu * ufl.inner(eps, eps) + self.lmbda / 2 * ufl.tr(eps) ** 2

    def quadrature_degree(self, gradient_degree: int) -> int:
        """2·deg(∇u): ψ is quadratic in ∇u, so this is exact."""
        return 2 * gradient_degree


@dataclass(frozen=True, slots=True)
class SaintVenantKirchhoff(_Lame):
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

    def psi(self, F):
        """μ E:E + λ/2 (tr E)² (Pa)."""
        E = green_lagrange(F)
        return self.mu * ufl.inner(E, E) + self.lmbda / 2 * ufl.tr(E) ** 2

    def quadrature_degree(self, gradient_degree: int) -> int:
        """4·deg(∇u): ψ is quartic in ∇u, so this is exact."""
        return 4 * gradient_degree


@dataclass(frozen=True, slots=True)
class NeoHookean(_LameSplit):
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

    def psi_iso(self, F):
        """μ/2 (I1 − 3) − μ ln J (Pa)."""
        I1, _, J = invariants(F)
        return self.mu / 2 * (I1 - 3) - self.mu * ufl.ln(J)

    def volumetric(self, J):
        """g(J) = ln J."""
        return ufl.ln(J)


@dataclass(frozen=True, slots=True)
class StableNeoHookean(_LameSplit):
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

    def psi_iso(self, F):
        """μ'/2 (I1 − 3) − μ'/2 ln(I1 + 1) with μ' = 4μ/3 (Pa)."""
        I1, _, _ = invariants(F)
        mu_s = 4 * self.mu / 3
        return mu_s / 2 * (I1 - 3) - mu_s / 2 * ufl.ln(I1 + 1)

    def volumetric(self, J):
        """g(J) = J − a, a = 1 + 3μ'/(4λ')."""
        return J - (1 + 3 * (4 * self.mu / 3) / (4 * self.bulk))


@dataclass(frozen=True, slots=True)
class MooneyRivlin(_Split):
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

    def __post_init__(self):
        if (p := _numbers(self)) is not None:
            _require(self, p["c1"] >= 0 and p["c2"] >= 0 and p["c1"] + p["c2"] > 0, "need c1, c2 >= 0, c1 + c2 > 0")
            _require(self, p["bulk"] > 0, f"bulk must be > 0 (got {p['bulk']})")

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

    def psi_iso(self, F):
        """c1 (I1 − 3 − 2 ln J) + c2 (I2 − 3 − 4 ln J) (Pa)."""
        I1, I2, J = invariants(F)
        return self.c1 * (I1 - 3 - 2 * ufl.ln(J)) + self.c2 * (I2 - 3 - 4 * ufl.ln(J))

    def volumetric(self, J):
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

    def __post_init__(self):
        if (p := _numbers(self)) is not None:
            _require(self, min(p.values()) >= 0 and max(p.values()) > 0, "need c0, c1, c2 >= 0, not all zero")

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

    def psi(self, F):
        """c0 (J² − 1 − 2 ln J) + c1 (I1 − 3 − 2 ln J) + c2 (I2 − 3 − 4 ln J) (Pa)."""
        I1, I2, J = invariants(F)
        lnJ = ufl.ln(J)
        return self.c0 * (J**2 - 1 - 2 * lnJ) + self.c1 * (I1 - 3 - 2 * lnJ) + self.c2 * (I2 - 3 - 4 * lnJ)

    def quadrature_degree(self, gradient_degree: int) -> int:
        """Exact for constant ∇u, 2·deg(∇u) + 2 otherwise (ψ has a logarithm)."""
        return _nonpolynomial_degree(gradient_degree)


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

    def __post_init__(self):
        if (p := _numbers(self)) is not None:
            _require(self, p["alpha"] > 0 and p["gamma"] > 0, "need alpha > 0 and gamma > 0")

    def psi(self, F):
        """α (exp(γ (J² − 1 − 2 ln J)) − 1) (Pa)."""
        J = ufl.det(F)
        return self.alpha * (ufl.exp(self.gamma * (J**2 - 1 - 2 * ufl.ln(J))) - 1)

    def quadrature_degree(self, gradient_degree: int) -> int:
        """Exact for constant ∇u, 2·deg(∇u) + 2 otherwise (ψ has an exponential)."""
        return _nonpolynomial_degree(gradient_degree)


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

    def __post_init__(self):
        if not self.terms:
            raise ParameterError("Sum: needs at least one law")

    def psi(self, F):
        """Σᵢ ψᵢ(F) (Pa)."""
        return sum((t.psi(F) for t in self.terms[1:]), self.terms[0].psi(F))

    def quadrature_degree(self, gradient_degree: int) -> int:
        """The largest of the terms' degrees."""
        return max(t.quadrature_degree(gradient_degree) for t in self.terms)


def _check_lame(law) -> None:
    if (p := _numbers(law)) is None:
        return
    mu, lmbda = p["mu"], p["lmbda"]
    _require(law, mu > 0, f"shear modulus mu must be > 0 (got {mu})")
    _require(
        law,
        math.isfinite(lmbda) or isinstance(law, _Split),
        "lmbda must be finite (this law has no incompressible limit)",
    )
    _require(law, 3 * lmbda + 2 * mu > 0, f"bulk modulus lmbda + 2 mu/3 must be > 0 (got lmbda = {lmbda})")


def first_piola(law: Material, F: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """The first Piola–Kirchhoff stress P = ∂ψ/∂F (Pa) by UFL differentiation.

    ``F`` must be a ``ufl.variable``. The Cauchy stress is σ = J⁻¹ P Fᵀ.
    """
    return ufl.diff(law.psi(F), F)


def shear_modulus(law: Material, mesh) -> ufl.core.expr.Expr:
    """The initial shear modulus μ₀ = ∂²ψ/∂γ² at γ = 0 of a simple shear F = I + γ e₁⊗e₂ (Pa; a
    UFL expression, a field where the law's parameters are). J = 1 in simple shear, so a split
    law's bulk term adds nothing and ψ_iso is used (it is defined also for bulk = inf).
    Neo-Hookean: μ; Mooney–Rivlin: 2(c1 + c2)."""
    from dolfinx import fem

    gamma = ufl.variable(fem.Constant(mesh, 0.0))
    F = ufl.variable(ufl.Identity(3) + gamma * ufl.outer(ufl.unit_vector(0, 3), ufl.unit_vector(1, 3)))
    psi = law.psi_iso(F) if isinstance(law, VolumetricSplit) else law.psi(F)
    return ufl.diff(ufl.diff(psi, gamma), gamma)


# The laws a scene names by `law = "..."` (besides the composite `sum` and `lung_skeleton`).
LAWS: dict[str, type] = {
    law.name: law
    for law in (
        LinearElastic,
        SaintVenantKirchhoff,
        NeoHookean,
        StableNeoHookean,
        MooneyRivlin,
        CiarletGeymonat,
        ExponentialCiarletGeymonat,
    )
}
