"""Gravity, optionally balanced by a heterogeneous pleural pressure (after Peyraut & Genet 2024).

The weight of the lung, ∫ ρ0 g dX, is carried in vivo by the pleural pressure, which is higher
(less negative) at the bottom than at the top. With ``balanced_on`` boundaries, this load adds
to the dead weight a follower pressure on those boundaries,

    q(x) = b · y + y · B y,   y = (x − x_G) / L,

with x the current position, x_G the current centre of mass and L a fixed length. Its gradient
b (the hydrostatic part) and the symmetric B (the least correction, smallest |B|) are chosen at
every residual evaluation so that the pressure's resultant force and moment cancel those of the
weight exactly: the held region (hilum) then carries no weight. On a closed surface with
x_G at the volume centroid, B = 0 and b = L M g/|ω|: the hydrostatic pressure of a fluid of the
lung's mean density. The moment condition needs the quadratic term otherwise, since a
pressure linear in x has the moment of a buoyant body about the volume centroid.

The coefficients are global functionals of the state. The solver freezes them for a Newton
solve (exact, quadratic: it differentiates q through x and the surface) and updates them
between solves until they settle, so the converged state is balanced exactly.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import ufl
from dolfinx import fem
from ufl.core.expr import Expr

from lungmech import checks
from lungmech.errors import ParameterError
from lungmech.fem.loads import Named, StateDependentWork
from lungmech.fem.quantities import vector_integral
from lungmech.fem.ramp import Ramp


def _quadratic_basis(y: Expr) -> list[Expr]:
    """b·y + y·B y as a linear combination: (y1, y2, y3, y1², y2², y3², 2y1y2, 2y1y3, 2y2y3)."""
    return [y[0], y[1], y[2], y[0] ** 2, y[1] ** 2, y[2] ** 2, 2 * y[0] * y[1], 2 * y[0] * y[2], 2 * y[1] * y[2]]


# Weights of the nine coefficients in |B|² (b is free): off-diagonal entries count twice.
_NORM = np.diag([0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 2.0, 2.0, 2.0])


@dataclass(frozen=True)
class Gravity(Named):
    """The weight ρ0 g per unit reference volume, optionally balanced by pleural pressure.

    Args:
        density: mass per unit reference volume ρ0 (for the lung, the solid density times Φs0;
            the air weighs nothing).
        acceleration: the gravity vector g, e.g. (0, 0, −9.81) for an upright patient.
        balanced_on: boundaries carrying the balancing pressure (e.g. pleura, diaphragm,
            mediastinum); empty: the held region carries the weight.
        ramp: time profile of g.
    """

    density: float
    acceleration: Sequence[float]
    balanced_on: tuple[str, ...] = ()
    ramp: Ramp = field(default_factory=Ramp)
    name: str = ""
    kind: ClassVar[str] = "gravity"

    def __post_init__(self):
        checks.real("gravity: density", self.density, positive=True)
        try:
            object.__setattr__(self, "acceleration", checks.vector("acceleration", self.acceleration))
        except ParameterError:
            raise ParameterError(f"gravity: acceleration needs 3 components (got {self.acceleration!r})") from None
        balanced_on = (self.balanced_on,) if isinstance(self.balanced_on, str) else self.balanced_on
        if (
            isinstance(balanced_on, bytes)
            or not isinstance(balanced_on, Sequence)
            or not all(isinstance(b, str) and b for b in balanced_on)
        ):
            raise ParameterError(f"gravity: balanced_on must be a list of boundary names (got {self.balanced_on!r})")
        object.__setattr__(self, "balanced_on", tuple(balanced_on))
        if not isinstance(self.ramp, Ramp) or not isinstance(self.name, str):
            raise ParameterError("gravity: ramp must be a Ramp and name a string")

    @property
    def value(self) -> Sequence[float]:
        return self.acceleration

    def potential(self, model, value: Expr) -> ufl.Form:
        return -self.density * ufl.dot(value, model.u) * model.dx

    def virtual_work(self, model, v: Expr, value: Expr) -> StateDependentWork | None:
        if not self.balanced_on:
            return None
        geometry = model.geometry
        mesh = geometry.mesh
        length = geometry.size
        X = ufl.SpatialCoordinate(mesh)
        x = X + model.u
        centre = fem.Constant(mesh, np.zeros(3))
        coefficients = fem.Constant(mesh, np.zeros(9))
        basis = _quadratic_basis((x - centre) / length)
        q = sum(coefficients[k] * phi for k, phi in enumerate(basis))
        F = model.F
        n_da = ufl.det(F) * ufl.inv(F).T * ufl.FacetNormal(mesh)  # Nanson: current n da on the reference
        surface = geometry.ds(self.balanced_on)
        y = x - centre
        # Resultant force and moment (about x_G) of −φ_k n da for each basis pressure φ_k.
        response = vector_integral(
            ufl.as_matrix(
                [[-phi * n_da[i] for phi in basis] for i in range(3)]
                + [[-phi * ufl.cross(y, n_da)[i] for phi in basis] for i in range(3)]
            ),
            surface,
            mesh,
        )
        # [mass, first moment]: recomputed with the rest, as the reference itself may move (inverse problem)
        moments = vector_integral(self.density * ufl.as_vector([1, *x]), model.dx, mesh)

        def evaluate() -> np.ndarray:
            """(x_G / L, coefficients) of the current state."""
            mass, first_moment = np.split(moments(), [1])
            previous = centre.value.copy()
            centre.value = first_moment / mass  # the response is measured about the new centre
            weight = mass * np.asarray(value.value, dtype=float)
            # The pressure's force cancels the weight; its moment about x_G is zero, like the weight's.
            balanced = _least_correction(response(), np.concatenate([-weight, np.zeros(3)]))
            centre.value = previous
            return np.concatenate([first_moment / mass / length, balanced])

        def assign(theta: np.ndarray) -> None:
            centre.value = theta[:3] * length
            coefficients.value = theta[3:]

        # Can these boundaries balance a weight along g at all? Checked once, on the reference.
        mass, first_moment = np.split(moments(), [1])
        centre.value = first_moment / mass
        direction = np.asarray(self.acceleration, dtype=float)
        A = response()
        target = np.concatenate([-mass * direction, np.zeros(3)])
        if np.linalg.norm(A @ _least_correction(A, target) - target) > 1e-8 * np.linalg.norm(target):
            raise ParameterError(
                f"gravity: no pressure on {', '.join(self.balanced_on)} can balance the weight's force "
                "and moment; name the boundaries that surround the body (e.g. pleura, diaphragm, mediastinum)"
            )
        return StateDependentWork(-q * ufl.dot(n_da, v) * surface, evaluate, assign)


def _least_correction(A: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Coefficients c of A c = target with the smallest |B| (a KKT solve; b is left free)."""
    kkt = np.block([[_NORM, A.T], [A, np.zeros((6, 6))]])
    rhs = np.concatenate([np.zeros(9), target])
    return np.linalg.lstsq(kkt, rhs, rcond=None)[0][:9]
