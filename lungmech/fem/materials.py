"""Hyperelastic strain-energy laws.

A law is a small frozen dataclass with one method, ``psi(F) -> ufl.Expr``: the strain energy per
unit reference volume. Stresses are never written by hand; they come from UFL differentiation
(see :func:`first_piola`). Parameters are plain floats (validated on construction) or UFL
expressions such as ``dolfinx.fem.Constant`` (see :func:`with_constants`), so one compiled form
serves every parameter value.

Laws with a volumetric split (``psi = psi_iso + bulk/2 · g(J)²``, see :class:`VolumetricSplit`)
also run in the mixed displacement–pressure formulation, which stays accurate as ν → 0.5 and is
exactly incompressible when ``bulk = inf``.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar, Protocol, Self, runtime_checkable

import ufl

from lungmech import checks
from lungmech.errors import ParameterError
from lungmech.fem.kinematics import green_lagrange, invariants, small_strain

Param = float | ufl.core.expr.Expr


@runtime_checkable
class Material(Protocol):
    """What every law provides."""

    def psi(self, F: ufl.core.expr.Expr) -> ufl.core.expr.Expr: ...

    def quadrature_degree(self, gradient_degree: int) -> int: ...


@runtime_checkable
class VolumetricSplit(Protocol):
    """A law written ψ(F) = ψ_iso(F) + bulk/2 · g(J)² with g(1) = 0.

    The mixed formulation replaces the last term by −p g(J) − p²/(2 bulk): eliminating p gives
    back ψ exactly, and bulk = inf turns it into the constraint g(J) = 0, i.e. J = 1.
    """

    bulk: Param

    def psi_iso(self, F: ufl.core.expr.Expr) -> ufl.core.expr.Expr: ...

    def volumetric(self, J: ufl.core.expr.Expr) -> ufl.core.expr.Expr: ...


# --- parameters ------------------------------------------------------------------------------


def lame_from_young(E: float, nu: float) -> tuple[float, float]:
    """(μ, λ) from Young's modulus and Poisson's ratio of a compressible material.

    ν = 0.5 is refused: an incompressible law is built with ``incompressible(...)`` and the
    mixed formulation instead of an infinite λ.
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
        return Sum(tuple(with_values(term, part) for term, part in zip(law.terms, parts)))
    return dataclasses.replace(law, **values) if values else law


def with_constants(law: Material, mesh) -> Material:
    """A copy of ``law`` whose finite parameters are ``fem.Constant``s on ``mesh``.

    Forms built from it compile once; changing a parameter is then ``law.mu.value = ...``.
    Infinite parameters (incompressible limits) stay floats: they change the form's structure.
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
        return cls(*lame_from_young(E, nu))


class _Split:
    """ψ = ψ_iso + bulk/2 g(J)² for laws that define psi_iso, volumetric and bulk."""

    def psi(self, F):
        if isinstance(self.bulk, numbers.Real) and math.isinf(self.bulk):
            raise ParameterError(
                f"{type(self).__name__} is incompressible (bulk = inf): it needs the mixed formulation"
            )
        return self.psi_iso(F) + self.bulk / 2 * self.volumetric(ufl.det(F)) ** 2

    def quadrature_degree(self, gradient_degree: int) -> int:
        return _nonpolynomial_degree(gradient_degree)


class _LameSplit(_Lame, _Split):
    """A Lamé-parametrised law with a volumetric split: λ = inf is its incompressible limit."""

    @classmethod
    def incompressible(cls, mu: float) -> Self:
        return cls(mu, math.inf)


@dataclass(frozen=True, slots=True)
class LinearElastic(_Lame):
    """ψ = μ ε:ε + λ/2 (tr ε)², ε = sym(∇u): small-strain elasticity (not frame-indifferent)."""

    mu: Param
    lmbda: Param
    name: ClassVar[str] = "linear"
    small_strain: ClassVar[bool] = True  # its stress ∂ψ/∂F is σ itself: no finite-strain push-forward

    def psi(self, F):
        eps = small_strain(F)
        return self.mu * ufl.inner(eps, eps) + self.lmbda / 2 * ufl.tr(eps) ** 2

    def quadrature_degree(self, gradient_degree: int) -> int:
        return 2 * gradient_degree


@dataclass(frozen=True, slots=True)
class SaintVenantKirchhoff(_Lame):
    """ψ = μ E:E + λ/2 (tr E)², E = ½(C − I). Softens and fails under strong compression."""

    mu: Param
    lmbda: Param
    name: ClassVar[str] = "saint_venant_kirchhoff"

    def psi(self, F):
        E = green_lagrange(F)
        return self.mu * ufl.inner(E, E) + self.lmbda / 2 * ufl.tr(E) ** 2

    def quadrature_degree(self, gradient_degree: int) -> int:
        return 4 * gradient_degree


@dataclass(frozen=True, slots=True)
class NeoHookean(_LameSplit):
    """ψ = μ/2 (I1 − 3) − μ ln J + λ/2 (ln J)²  (compressible; λ = inf: incompressible)."""

    mu: Param
    lmbda: Param
    name: ClassVar[str] = "neo_hookean"

    @property
    def bulk(self) -> Param:
        return self.lmbda

    def psi_iso(self, F):
        I1, _, J = invariants(F)
        return self.mu / 2 * (I1 - 3) - self.mu * ufl.ln(J)

    def volumetric(self, J):
        return ufl.ln(J)


@dataclass(frozen=True, slots=True)
class StableNeoHookean(_LameSplit):
    """Smith, de Goes & Kim (2018): ψ = μ'/2 (I1 − 3) + λ'/2 (J − a)² − μ'/2 ln(I1 + 1).

    Built from the Lamé parameters (μ, λ) it matches in the small-strain limit:
    μ' = 4μ/3, λ' = λ + 5μ/6, a = 1 + 3μ'/(4λ'). Defined for every F (no ln J), so it survives
    inverted elements. ψ(I) is a constant 9μ'²/(32λ'); the stress at rest is zero.
    """

    mu: Param
    lmbda: Param
    name: ClassVar[str] = "stable_neo_hookean"

    @property
    def bulk(self) -> Param:
        return self.lmbda + 5 * self.mu / 6

    def psi_iso(self, F):
        I1, _, _ = invariants(F)
        mu_s = 4 * self.mu / 3
        return mu_s / 2 * (I1 - 3) - mu_s / 2 * ufl.ln(I1 + 1)

    def volumetric(self, J):
        return J - (1 + 3 * (4 * self.mu / 3) / (4 * self.bulk))


@dataclass(frozen=True, slots=True)
class MooneyRivlin(_Split):
    """ψ = c1 (I1 − 3 − 2 ln J) + c2 (I2 − 3 − 4 ln J) + bulk/2 (ln J)²  (bulk = inf: incompressible).

    Small-strain limit: μ = 2(c1 + c2), λ = bulk + 4 c2.
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
        """c2 carries ``c2_share`` of the shear modulus; λ is matched through the bulk term."""
        mu, lmbda = lame_from_young(E, nu)
        c2 = c2_share * mu / 2
        return cls(mu / 2 - c2, c2, lmbda - 4 * c2)

    @classmethod
    def incompressible(cls, c1: float, c2: float) -> MooneyRivlin:
        return cls(c1, c2, math.inf)

    def psi_iso(self, F):
        I1, I2, J = invariants(F)
        return self.c1 * (I1 - 3 - 2 * ufl.ln(J)) + self.c2 * (I2 - 3 - 4 * ufl.ln(J))

    def volumetric(self, J):
        return ufl.ln(J)


@dataclass(frozen=True, slots=True)
class CiarletGeymonat:
    """ψ = c0 (J² − 1 − 2 ln J) + c1 (I1 − 3 − 2 ln J) + c2 (I2 − 3 − 4 ln J).

    c1 = c2 = 0 is the pure Ciarlet–Geymonat bulk term (CG), c2 = 0 its neo-Hookean sum (CGNH),
    all three the CGNHMR law. Small-strain limit: μ = 2(c1 + c2), λ = 4(c0 + c2).
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
        """Matches (E, ν) at small strain; c2 carries ``c2_share`` of the shear modulus."""
        mu, lmbda = lame_from_young(E, nu)
        c2 = c2_share * mu / 2
        if lmbda / 4 - c2 < 0:
            raise ParameterError(
                f"CiarletGeymonat: nu = {nu} is too low for c2_share = {c2_share} (c0 would be negative)"
            )
        return cls(lmbda / 4 - c2, mu / 2 - c2, c2)

    def psi(self, F):
        I1, I2, J = invariants(F)
        lnJ = ufl.ln(J)
        return self.c0 * (J**2 - 1 - 2 * lnJ) + self.c1 * (I1 - 3 - 2 * lnJ) + self.c2 * (I2 - 3 - 4 * lnJ)

    def quadrature_degree(self, gradient_degree: int) -> int:
        return _nonpolynomial_degree(gradient_degree)


@dataclass(frozen=True, slots=True)
class ExponentialCiarletGeymonat:
    """ψ = α (exp(γ (J² − 1 − 2 ln J)) − 1): the stiffening volumetric part of the lung skeleton."""

    alpha: Param
    gamma: Param
    name: ClassVar[str] = "exponential_ciarlet_geymonat"

    def __post_init__(self):
        if (p := _numbers(self)) is not None:
            _require(self, p["alpha"] > 0 and p["gamma"] > 0, "need alpha > 0 and gamma > 0")

    def psi(self, F):
        J = ufl.det(F)
        return self.alpha * (ufl.exp(self.gamma * (J**2 - 1 - 2 * ufl.ln(J))) - 1)

    def quadrature_degree(self, gradient_degree: int) -> int:
        return _nonpolynomial_degree(gradient_degree)


@dataclass(frozen=True, slots=True)
class Sum:
    """ψ = Σ ψ_i: e.g. the lung skeleton, exponential CG + CGNHMR."""

    terms: tuple[Material, ...]
    name: ClassVar[str] = "sum"

    def __post_init__(self):
        if not self.terms:
            raise ParameterError("Sum: needs at least one law")

    def psi(self, F):
        return sum((t.psi(F) for t in self.terms[1:]), self.terms[0].psi(F))

    def quadrature_degree(self, gradient_degree: int) -> int:
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
    """P = ∂ψ/∂F by UFL differentiation (``F`` must be a ``ufl.variable``)."""
    return ufl.diff(law.psi(F), F)


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
