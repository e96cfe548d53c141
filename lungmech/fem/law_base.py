"""What every strain-energy law shares: the protocols, the checks of its parameters, the bases.

:class:`Material` is what a law provides (ψ(F) and its quadrature degree), :class:`VolumetricSplit`
what a law with a bulk term adds; :class:`LameLaw` and :class:`SplitLaw` are the bases of laws in
the Lamé parameters and of laws ψ = ψ_iso + bulk/2 g(J)². The laws themselves are
:mod:`lungmech.fem.laws`; :mod:`lungmech.fem.materials` is where they are used from.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, Self, runtime_checkable

import ufl

from lungmech import checks
from lungmech.errors import ParameterError

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

Param = float | ufl.core.expr.Expr  # a number, or a UFL expression such as a fem.Constant


@runtime_checkable
class Material(Protocol):
    """What every law provides: its energy and how exactly to integrate it.

    A law is also expected to carry a class attribute ``name`` (its scene name, e.g.
    ``"neo_hookean"``) and its parameters as dataclass fields.
    """

    name: ClassVar[str]
    __dataclass_fields__: ClassVar[dict[str, dataclasses.Field[Any]]]  # a dataclass: its parameters are its fields

    def psi(self, F: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
        """The strain energy density ψ(F) in Pa (J per m³ of reference volume)."""
        ...

    def quadrature_degree(self, gradient_degree: int) -> int:
        """The quadrature degree for ψ when ∇u is a polynomial of degree ``gradient_degree``."""
        ...


@runtime_checkable
class VolumetricSplit(Material, Protocol):
    """A law written ψ(F) = ψ_iso(F) + bulk/2 · g(J)² with g(1) = 0.

    The mixed formulation replaces the last term by −p g(J) − p²/(2 bulk): eliminating p gives
    back ψ exactly, and bulk = inf turns it into the constraint g(J) = 0, i.e. J = 1.
    ``psi_iso`` need not be isochoric: it is whatever the law keeps outside the bulk term.

    Attributes
    ----------
    bulk : float or UFL expression
        The modulus (Pa) in front of g(J)²/2; ``inf`` for an incompressible material.
    """

    @property
    def bulk(self) -> Param: ...

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
    check_real("E", E)
    check_real("nu", nu)
    if not E > 0:
        raise ParameterError(f"Young's modulus E must be > 0 (got E = {E})")
    if not -1.0 < nu < 0.5:
        raise ParameterError(
            f"Poisson's ratio must satisfy -1 < nu < 0.5 for a compressible law (got nu = {nu}); "
            "for an incompressible material use the mixed formulation with an incompressible law"
        )
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


def check_real(name: str, value: object) -> None:
    """A finite real number; only a bulk modulus may be +inf (the incompressible limit)."""
    number = checks.real(f"parameter '{name}'", value, infinite=name in ("bulk", "lmbda"))
    if math.isinf(number) and number < 0:
        raise ParameterError(f"parameter '{name}' must be a finite number or +inf (got {value})")


def require(law: object, condition: bool, message: str) -> None:
    if not condition:
        raise ParameterError(f"{type(law).__name__}: {message}")


def plain_numbers(law: DataclassInstance) -> dict[str, float] | None:
    """The law's parameters when all are plain numbers (validation is skipped for UFL values)."""
    values = {f.name: getattr(law, f.name) for f in dataclasses.fields(law)}
    for name, v in values.items():
        if isinstance(v, bool) or not isinstance(v, numbers.Real | ufl.core.expr.Expr):
            raise ParameterError(f"parameter '{name}' must be a number (got {v!r})")
    if not all(isinstance(v, numbers.Real) for v in values.values()):
        return None
    for name, v in values.items():
        check_real(name, v)
    return values


def nonpolynomial_degree(gradient_degree: int) -> int:
    """Quadrature degree for a law with logarithms/exponentials: exact when ∇u is constant."""
    return 2 * gradient_degree + 2 if gradient_degree > 0 else 0


# --- bases ------------------------------------------------------------------------------------


class LameLaw:
    """Laws parametrised by the Lamé constants (mu, lmbda): validation and (E, ν) constructor."""

    mu: Param
    lmbda: Param

    if TYPE_CHECKING:  # each law is a dataclass of (mu, lmbda), with their __init__

        def __init__(self, mu: Param, lmbda: Param) -> None: ...

    def __post_init__(self: DataclassInstance) -> None:
        check_lame(self)

    @classmethod
    def from_young(cls, E: float, nu: float) -> Self:
        """The law with the Lamé parameters of Young's modulus ``E`` (Pa) and Poisson's ratio
        ``nu`` (1, −1 < ν < 0.5), see :func:`lame_from_young`."""
        return cls(*lame_from_young(E, nu))


class SplitLaw:
    """ψ = ψ_iso + bulk/2 g(J)² for laws that define psi_iso, volumetric and bulk."""

    def psi(self: VolumetricSplit, F: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
        """ψ_iso(F) + bulk/2 g(J)² (Pa). Refused for bulk = inf: only the mixed formulation can
        impose J = 1."""
        if isinstance(self.bulk, numbers.Real) and math.isinf(self.bulk):
            raise ParameterError(
                f"{type(self).__name__} is incompressible (bulk = inf): it needs the mixed formulation"
            )
        return self.psi_iso(F) + self.bulk / 2 * self.volumetric(ufl.det(F)) ** 2

    def quadrature_degree(self, gradient_degree: int) -> int:
        """Exact for constant ∇u, 2·deg(∇u) + 2 otherwise: ψ has a logarithm (see
        :func:`nonpolynomial_degree`)."""
        return nonpolynomial_degree(gradient_degree)


class LameSplitLaw(LameLaw, SplitLaw):
    """A Lamé-parametrised law with a volumetric split: λ = inf is its incompressible limit."""

    @classmethod
    def incompressible(cls, mu: float) -> Self:
        """The incompressible law (λ = inf) of shear modulus ``mu`` (Pa); it needs the mixed
        formulation."""
        return cls(mu, math.inf)


def check_lame(law: DataclassInstance) -> None:
    if (p := plain_numbers(law)) is None:
        return
    mu, lmbda = p["mu"], p["lmbda"]
    require(law, mu > 0, f"shear modulus mu must be > 0 (got {mu})")
    require(
        law,
        math.isfinite(lmbda) or isinstance(law, SplitLaw),
        "lmbda must be finite (this law has no incompressible limit)",
    )
    require(law, 3 * lmbda + 2 * mu > 0, f"bulk modulus lmbda + 2 mu/3 must be > 0 (got lmbda = {lmbda})")
