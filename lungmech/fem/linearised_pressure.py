"""Newton's tangent for a nearly incompressible displacement model: the mixed formulation's path.

For a law split as ψ = ψ_iso(F) + κ/2 · g(J)² (:class:`lungmech.fem.materials.VolumetricSplit`)
the displacement formulation's residual and exact tangent are

.. math::

    R(u)[v] = ∫ ∂ψ_iso(F):∇v + κ g(J) · DG[v] dX + (loads),        G(u) = g(det F(u))

    K(u)[v, w] = ∫ ∂²ψ_iso[∇v, ∇w] + κ DG[v] DG[w] + κ g(J) · D²G[v, w] dX + (loads)

Away from an equilibrium κ g(J) is κ times the error in J: a prediction or an overshooting
iterate that leaves the isochoric manifold to second order gets a bulk stress κ/μ = 5000 times
too large (ν = 0.4999), its geometric term κ g(J) D²G swamps the rest, and Newton's direction
with it (Cook's P2 membrane: steps that stall at λ ≈ 1e-3, 44 iterations where the Taylor–Hood
formulation needs 12). Newton here uses K with κ g(J) in that last term replaced by s, the bulk
stress as a variable at the quadrature points, moved as the Taylor–Hood pressure would be:

.. math::

    s ← κ [g(J) + g'(J) · DJ[Δu]]   (at the previous iterate, Δu the step just taken)

    s = κ g(J)                      (at an equilibrium, where every Newton solve starts)

The residual is not changed, so the solution is the displacement formulation's, to the same
tolerance; as Newton converges s → κ g(J) and the tangent becomes the exact one (quadratic
convergence). The modified term is symmetric, as K is. Cook's P2 membrane then takes 13–14
Newton iterations on every mesh (benchmarks/cook.py); compressible laws see no change.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, cast

import basix.ufl
import numpy as np
import ufl
from dolfinx import fem

from lungmech import jit
from lungmech.fem.formulations import PlaneStress, PureDisplacement, incompressible
from lungmech.fem.materials import VolumetricSplit

if TYPE_CHECKING:
    from lungmech.fem.model import Model

__all__ = ["LinearisedPressure"]


class LinearisedPressure:
    """The bulk stress s of a displacement model's Newton tangent (see the module).

    ``tangent`` is the Newton tangent (a UFL form); :meth:`at_equilibrium` sets s from the
    current state, :meth:`advance` moves it along a step Newton took."""

    def __init__(self, model: Model) -> None:
        material = cast(VolumetricSplit, model.material)  # made for a law with a split only (:meth:`of`)
        state, dx = model.state, model.dx
        mesh = model.geometry.mesh
        element = basix.ufl.quadrature_element(
            mesh.basix_cell(), value_shape=(), degree=dx.metadata()["quadrature_degree"]
        )
        self.stress = fem.Function(fem.functionspace(mesh, element), name="bulk_stress")  # s (Pa)
        G = material.volumetric(ufl.det(model.F))
        test, trial = ufl.TestFunction(model.space), ufl.TrialFunction(model.space)
        second = ufl.derivative(ufl.derivative(G, state, test), state, trial)  # D²G[v, w]
        self.tangent = model.jacobian + (self.stress - material.bulk * G) * second * dx
        # s from an iterate and a step: one compiled expression, for both moves
        self._iterate, self._step = fem.Function(model.space), fem.Function(model.space)
        at_iterate = ufl.replace(G, {state: self._iterate})
        linearised = material.bulk * (at_iterate + ufl.derivative(at_iterate, self._iterate, self._step))
        self._linearised = jit.expression(linearised, element.custom_quadrature()[0])
        self._state = state

    @staticmethod
    def of(model: Model) -> LinearisedPressure | None:
        """For a displacement model (3-D, plane strain or plane stress) whose law has a finite
        volumetric split; None otherwise (the mixed and the lung's formulations have their own
        fields, a law without a split has no bulk stress)."""
        if not isinstance(model.formulation, PureDisplacement | PlaneStress):
            return None
        if not isinstance(model.material, VolumetricSplit) or incompressible(model.material):
            return None
        return LinearisedPressure(model)

    def at_equilibrium(self) -> None:
        """s = κ g(J) at the current state (collective)."""
        self._iterate.x.array[:] = self._state.x.array
        self._step.x.array[:] = 0.0
        self._evaluate()

    def advance(self, iterate: np.ndarray, step: np.ndarray) -> None:
        """s = κ [g(J) + g'(J) DJ[step]] at ``iterate`` (owned entries of the state vector and of
        the step Newton took from it; collective)."""
        for function, values in ((self._iterate, iterate), (self._step, step)):
            function.x.array[: values.size] = values
            function.x.scatter_forward()
        self._evaluate()

    def _evaluate(self) -> None:
        self.stress.interpolate(self._linearised)
        self.stress.x.scatter_forward()
