"""How a model's unknowns are discretised: the displacement alone, or with extra fields.

A formulation names the fields it adds to the displacement u, gives their finite elements, and
writes the energy density from the law, F and those fields. The model stays the same for all.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import ClassVar, Protocol

import basix.ufl
import ufl
from ufl.core.expr import Expr

from lungmech.errors import ParameterError
from lungmech.fem.materials import Material, VolumetricSplit


class Formulation(Protocol):
    fields: ClassVar[tuple[str, ...]]  # the unknowns after u, in order

    def bind(self, mesh) -> Formulation:
        """The formulation with its data (e.g. fields given per cell) placed on ``mesh``."""
        ...

    def check(self, material: Material, degree: int) -> None: ...

    def elements(self, cell: str, degree: int, quadrature_degree: int) -> list: ...

    def energy_density(self, material: Material, F: Expr, fields: dict[str, Expr]) -> Expr: ...

    def initial_values(self) -> dict[str, float]: ...


def _incompressible(material: Material) -> bool:
    bulk = getattr(material, "bulk", None)
    return isinstance(bulk, numbers.Real) and math.isinf(bulk)


@dataclass(frozen=True)
class PureDisplacement:
    """u only: ψ(F)."""

    fields: ClassVar[tuple[str, ...]] = ()

    def bind(self, mesh) -> PureDisplacement:
        return self

    def check(self, material: Material, degree: int) -> None:
        if _incompressible(material):
            raise ParameterError(f"the incompressible law '{material.name}' needs the mixed formulation")

    def elements(self, cell: str, degree: int, quadrature_degree: int) -> list:
        return []

    def energy_density(self, material: Material, F: Expr, fields: dict[str, Expr]) -> Expr:
        return material.psi(F)

    def initial_values(self) -> dict[str, float]:
        return {}


@dataclass(frozen=True)
class TaylorHood:
    """u in P_k, pressure p in P_{k−1}: ψ_iso(F) − p g(J) − p²/(2 bulk) (the last term vanishes for bulk = inf)."""

    fields: ClassVar[tuple[str, ...]] = ("p",)
    residual_units: ClassVar[dict[str, str]] = {"p": "m^3"}  # ∫ (g(J) + p/bulk) q dX

    def bind(self, mesh) -> TaylorHood:
        return self

    def check(self, material: Material, degree: int) -> None:
        if degree < 2:
            raise ParameterError("the mixed formulation is Taylor–Hood: it needs degree >= 2")
        if not isinstance(material, VolumetricSplit):
            raise ParameterError(
                f"law '{material.name}' has no volumetric split, so no mixed formulation; "
                "use neo_hookean, stable_neo_hookean or mooney_rivlin"
            )

    def elements(self, cell: str, degree: int, quadrature_degree: int) -> list:
        return [basix.ufl.element("Lagrange", cell, degree - 1)]

    def energy_density(self, material: Material, F: Expr, fields: dict[str, Expr]) -> Expr:
        p = fields["p"]
        density = material.psi_iso(F) - p * material.volumetric(ufl.det(F))
        if not _incompressible(material):
            density -= p**2 / (2 * material.bulk)
        return density

    def initial_values(self) -> dict[str, float]:
        return {}
