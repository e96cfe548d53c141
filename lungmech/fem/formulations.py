"""How a model's unknowns are discretised: the displacement alone, or with extra fields.

A formulation names the fields it adds to the displacement u, gives their finite elements, and
writes the energy density from the law, F and those fields. The model stays the same for all:
its total potential is Π = ∫ energy_density dX + (load potentials), the residual is δΠ and the
tangent its derivative, all by UFL differentiation.

Three formulations exist: :class:`PureDisplacement` (u only), :class:`TaylorHood` (u and a
pressure p, for nearly or exactly incompressible laws) and the lung's
:class:`lungmech.lung.poromechanics.Poromechanics` (u and the solid fraction Φs). Energy
densities are per unit reference volume, in Pa (J/m³).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from dataclasses import Field, dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, cast

import basix.ufl
import ufl
from ufl.core.expr import Expr

from lungmech.errors import ParameterError
from lungmech.fem.materials import Material, VolumetricSplit

if TYPE_CHECKING:
    import dolfinx.fem
    import dolfinx.mesh

    from lungmech.fem.model import Model


class Formulation(Protocol):
    """What a formulation provides to :class:`lungmech.fem.model.Model`.

    A formulation may also name the unit of each extra field's residual in a class attribute
    ``residual_units`` (e.g. ``{"p": "m^3"}``), which the convergence test and its messages use.
    """

    fields: ClassVar[tuple[str, ...]]  # the unknowns after u, in order
    # a dataclass: a parameter on one of its constants is checked by rebuilding it (dataclasses.replace)
    __dataclass_fields__: ClassVar[dict[str, Field[Any]]]

    def bind(self, mesh: dolfinx.mesh.Mesh) -> Formulation:
        """The formulation with its data (e.g. fields given per cell) placed on ``mesh``."""
        ...

    def check(self, material: Material, degree: int) -> None:
        """Raise :class:`ParameterError` if ``material`` with u of Lagrange ``degree`` cannot
        be used in this formulation."""
        ...

    def elements(self, cell: basix.CellType, degree: int, quadrature_degree: int) -> list:
        """The finite elements of the extra fields, in the order of ``fields``."""
        ...

    def energy_density(self, material: Material, F: Expr, fields: dict[str, Expr]) -> Expr:
        """The energy per unit reference volume (Pa) from the law, F and the extra fields."""
        ...

    def initial_values(self) -> Mapping[str, float | dolfinx.fem.Function]:
        """Starting values of the extra fields at rest (fields not named start at 0)."""
        ...


def incompressible(material: Material) -> bool:
    """Whether the law is the incompressible limit of a volumetric split (bulk = inf)."""
    bulk = getattr(material, "bulk", None)
    return isinstance(bulk, numbers.Real) and math.isinf(bulk)


@dataclass(frozen=True)
class PureDisplacement:
    """The displacement formulation: u is the only unknown, in Lagrange P_k (scene
    ``type = "displacement"``, the default).

    .. math:: Π(u) = ∫ ψ(F) dX + (load potentials),   F = I + ∇u

    Every law works, except an incompressible one (bulk = inf). With P1 and a nearly
    incompressible law (ν → 0.5) the elements lock: use P2, or :class:`TaylorHood`.
    No parameters.
    """

    fields: ClassVar[tuple[str, ...]] = ()

    def bind(self, mesh: dolfinx.mesh.Mesh) -> PureDisplacement:
        """Itself: there are no data to place."""
        return self

    def check(self, material: Material, degree: int) -> None:
        """Refuse an incompressible law: J = 1 needs the mixed formulation."""
        if incompressible(material):
            raise ParameterError(f"the incompressible law '{material.name}' needs the mixed formulation")

    def elements(self, cell: basix.CellType, degree: int, quadrature_degree: int) -> list:
        """No extra fields."""
        return []

    def energy_density(self, material: Material, F: Expr, fields: dict[str, Expr]) -> Expr:
        """ψ(F) (Pa)."""
        return material.psi(F)

    def initial_values(self) -> dict[str, float]:
        """No extra fields."""
        return {}


@dataclass(frozen=True)
class TaylorHood:
    """The mixed displacement–pressure formulation (scene ``type = "mixed"``): u in P_k and a
    pressure p in P_{k−1}, k ≥ 2 (Taylor–Hood, inf-sup stable).

    For a law split as ψ = ψ_iso + bulk/2 · g(J)² (:class:`lungmech.fem.materials.VolumetricSplit`):

    .. math:: Π(u, p) = ∫ [ψ_iso(F) − p g(J) − p²/(2 bulk)] dX + (load potentials)

    The last term vanishes for bulk = inf. Stationarity in p gives p = −bulk · g(J); putting it
    back gives ψ exactly, so this is the displacement model without its locking. With bulk = inf
    it imposes g(J) = 0, i.e. J = 1 (weakly, in P_{k−1}): exact incompressibility.

    The field p (Pa) is the pressure the bulk term carries, positive in compression: for the
    neo-Hookean law p = −λ ln J. Its residual ∫ (g(J) + p/bulk) q dX is a volume (m³). No
    parameters; the law provides ``bulk``.
    """

    fields: ClassVar[tuple[str, ...]] = ("p",)
    residual_units: ClassVar[dict[str, str]] = {"p": "m^3"}  # ∫ (g(J) + p/bulk) q dX

    def bind(self, mesh: dolfinx.mesh.Mesh) -> TaylorHood:
        """Itself: there are no data to place."""
        return self

    def check(self, material: Material, degree: int) -> None:
        """Refuse degree < 2 (Taylor–Hood needs P_k–P_{k−1} with k ≥ 2) and a law without a
        volumetric split."""
        if degree < 2:
            raise ParameterError("the mixed formulation is Taylor–Hood: it needs degree >= 2")
        if not isinstance(material, VolumetricSplit):
            raise ParameterError(
                f"law '{getattr(material, 'label', '') or material.name}' has no volumetric split, so no mixed "
                "formulation; "
                "use neo_hookean, stable_neo_hookean or mooney_rivlin"
            )

    def elements(self, cell: basix.CellType, degree: int, quadrature_degree: int) -> list:
        """p in continuous Lagrange P_{k−1}."""
        return [basix.ufl.element("Lagrange", cell, degree - 1)]

    def energy_density(self, material: Material, F: Expr, fields: dict[str, Expr]) -> Expr:
        """ψ_iso(F) − p g(J) − p²/(2 bulk) (Pa); without the last term for bulk = inf."""
        p = fields["p"]
        material = cast(VolumetricSplit, material)  # check() refused a law without the split
        density = material.psi_iso(F) - p * material.volumetric(ufl.det(F))
        if not incompressible(material):
            density -= p**2 / (2 * material.bulk)
        return density

    def initial_values(self) -> dict[str, float]:
        """p starts at 0 (the stress-free state)."""
        return {}

    def point_fields(self, model: Model) -> dict[str, Expr]:
        """The pressure p (Pa) for outputs at the displacement's nodes (P_{k−1} ⊂ P_k: exact)."""
        return {"pressure": model.fields["p"]}


@dataclass(frozen=True)
class PlaneStress:
    """The displacement formulation of a thin plate: 2-D, plane stress (``Model(plane="stress")``).
    u lies in the plane, in Lagrange P_k; the thickness stretch λ₃ is an unknown in DG_{k−1}.

    .. math:: Π(u, λ₃) = ∫ ψ(F) dA + (load potentials),   F = [[I + ∇u, 0], [0, λ₃]]

    Stationarity in λ₃ gives ∂ψ/∂λ₃ = S₃₃ λ₃ = 0: the faces of the plate are stress-free. It
    holds at every point for P1 triangles (F is constant per cell, λ₃ too) and in the mean
    against DG_{k−1} otherwise. Every compressible law works; energies and forces are per unit
    reference thickness. No parameters.
    """

    fields: ClassVar[tuple[str, ...]] = ("thickness_stretch",)
    residual_units: ClassVar[dict[str, str]] = {"thickness_stretch": "N/m"}  # ∫ ∂ψ/∂λ₃ μ dA, per unit thickness

    def bind(self, mesh: dolfinx.mesh.Mesh) -> PlaneStress:
        """Itself: there are no data to place."""
        return self

    def check(self, material: Material, degree: int) -> None:
        """Refuse an incompressible law: its energy is not defined off J = 1."""
        if incompressible(material):
            raise ParameterError(
                "an incompressible law (bulk = inf) cannot be used in plane stress here; give it a finite bulk modulus"
            )

    def elements(self, cell: basix.CellType, degree: int, quadrature_degree: int) -> list:
        """λ₃ in discontinuous Lagrange DG_{k−1}."""
        return [basix.ufl.element("DG", cell, degree - 1)]

    def energy_density(self, material: Material, F: Expr, fields: dict[str, Expr]) -> Expr:
        """ψ(F) (Pa), F holding λ₃."""
        return material.psi(F)

    def initial_values(self) -> dict[str, float]:
        """λ₃ starts at 1 (the unstretched plate)."""
        return {"thickness_stretch": 1.0}
