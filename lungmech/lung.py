"""The quasi-static poromechanical lung model of Patte, Genet & Chapelle (2022).

Unknowns: the displacement u and Φs, the current solid volume per unit reference volume
(Φf = J − Φs is the fluid, i.e. air, volume). The total potential is

    Π(u, Φs) = ∫ W_skel(F) + W_bulk(Φs) − p_f (J − Φs) dX  + (pleural loads),

W_skel = α(e^{γ(J²−1−2lnJ)} − 1) + c1(I1−3−2lnJ) + c2(I2−3−4lnJ) and
W_bulk = κ(Φs/Φs0 − 1 − ln(Φs/Φs0)). Its Φs-equation is the reference's ∂W_bulk/∂Φs + p_f = 0,
and at that solution its u-equation is the reference's, so the total Cauchy stress is
σ_skel + (∂W_bulk/∂Φs) I = σ_skel − p_f I.

Φs lives in DG0: its equation holds pointwise (no derivative of Φs appears), and with P1
displacements on affine cells J is constant per cell, so DG0 is exact there.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import basix.ufl
import ufl
from ufl.core.expr import Expr

from lungmech.errors import ParameterError
from lungmech.materials import CiarletGeymonat, ExponentialCiarletGeymonat, Material, Sum
from lungmech.ramp import Ramp


def skeleton(alpha: float, gamma: float, c1: float, c2: float) -> Sum:
    """W_skel: the exponential Ciarlet–Geymonat bulk term plus the CGNHMR shear terms."""
    return Sum((ExponentialCiarletGeymonat(alpha, gamma), CiarletGeymonat(0.0, c1, c2)))


@dataclass(frozen=True)
class Poromechanics:
    """The (u, Φs) formulation: a skeleton law plus the solid bulk energy W_bulk(Φs)."""

    kappa: float
    phi_s0: float
    fields: ClassVar[tuple[str, ...]] = ("phi_s",)

    def __post_init__(self):
        if not self.kappa > 0:
            raise ParameterError(f"lung bulk modulus kappa must be > 0 (got {self.kappa})")
        if not 0 < self.phi_s0 < 1:
            raise ParameterError(f"reference solid fraction phi_s0 must lie in (0, 1) (got {self.phi_s0})")

    def check(self, material: Material, degree: int) -> None:
        pass

    def elements(self, cell: str, degree: int, quadrature_degree: int) -> list:
        return [basix.ufl.element("DG", cell, 0)]

    def bulk_energy(self, phi_s: Expr) -> Expr:
        ratio = phi_s / self.phi_s0
        return self.kappa * (ratio - 1 - ufl.ln(ratio))

    def energy_density(self, material: Material, F: Expr, fields: dict[str, Expr]) -> Expr:
        return material.psi(F) + self.bulk_energy(fields["phi_s"])

    def initial_values(self) -> dict[str, float]:
        return {"phi_s": self.phi_s0}


@dataclass(frozen=True)
class AlveolarPressure:
    """Air pressure p_f in the alveoli ("internal" loading): the potential −p_f Φf = −p_f (J − Φs)."""

    value: float
    ramp: Ramp = field(default_factory=Ramp)

    def potential(self, model, value: Expr) -> ufl.Form:
        return -value * (ufl.det(model.F) - model.fields["phi_s"]) * model.dx


def averages(model) -> dict[str, Callable[[], float]]:
    """Reference-volume averages of the lung's fractions and strain, compiled once.

    Φs (solid), Φf = J − Φs (air) per reference volume, φs = Φs/J (current solid fraction),
    and the mean Green–Lagrange strain tr(E)/3.
    """
    from lungmech.kinematics import green_lagrange
    from lungmech.quantities import integral

    comm = model.geometry.mesh.comm
    volume = model.geometry.volume()
    J, phi_s = ufl.det(model.F), model.fields["phi_s"]
    expressions = {
        "phi_s": phi_s,
        "phi_f": J - phi_s,
        "phi_s_current": phi_s / J,
        "green_lagrange_mean": ufl.tr(green_lagrange(model.F)) / 3,
    }
    means = {name: integral(expr * model.dx, comm) for name, expr in expressions.items()}
    return {name: (lambda f=f: f() / volume) for name, f in means.items()}
