"""What a Newton–PGD (:mod:`lungmech.pgd.newton`) assembles at its quadrature's points: the
model's residual, its tangent on the span of the space modes and its strain energy, each at a
point's state u_start(μ_q) + U_q.

The start u_start is the model's rest, or on an imaged body the image on its reference ξ(μ_q)
(:mod:`lungmech.pgd.imaged_newton`): a :data:`Start` sets what the point needs in the model
(its reference map) and gives the state its terms add to. A state-dependent load's
coefficients θ = Θ(u) are set from each point's state before anything is assembled there.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix

from lungmech import jit
from lungmech.fem.model import Model
from lungmech.fem.quantities import assemble_owned, strain_energy
from lungmech.fem.state_dependent import StateDependent
from lungmech.parallel.linalg import apply, gram
from lungmech.parallel.owned import owned_size
from lungmech.pgd.terms import constants, kept

__all__ = ["March", "Start"]

Start = Callable[[Mapping[str, float]], np.ndarray]
"""At a point μ: sets in the model what the point needs besides its parameters, and returns
the state (owned entries) the terms add to there. Collective."""


class March:
    """``model``'s residual, tangent on the modes' span and strain energy at the ``points``,
    its state there ``start``'s (default: the rest) plus a given displacement of the modes'
    space."""

    def __init__(self, model: Model, points: Sequence[Mapping[str, float]], start: Start | None = None) -> None:
        self.model, self.points = model, list(points)
        self.owned = owned_size(model.space)
        self.comm = model.geometry.mesh.comm
        self._imposed = model.constrained_dofs()
        self._residual, self._jacobian = jit.form(model.residual), jit.form(model.jacobian)
        self._coupled = StateDependent(model)
        self._work = fem.Function(model.space).x
        self._held = constants(model)
        with model.kept_state():
            model.reset()
            rest = model.state.x.array[: self.owned].copy()
        self._start = start or (lambda point: rest)

    def _at(self, point: Mapping[str, float], u: np.ndarray) -> None:
        model = self.model
        model.set_parameters(point)
        model.state.x.array[: self.owned] = self._start(point) + u
        model.state.x.scatter_forward()
        self._coupled.update()

    def residuals(self, U: np.ndarray, Q: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """R(u_start + U_q; μ_q) at the model's current loads (owned entries × N, 0 where
        imposed) and, given space modes ``Q``, the tangent there on their span, Qᵀ J_q Q (N × m ×
        m; J_q with a state-dependent load's coupling U Vᵀ, :mod:`lungmech.fem.state_dependent`)."""
        found = np.empty((self.owned, len(self.points)))
        tangents = None if Q is None else np.empty((len(self.points), Q.shape[1], Q.shape[1]))
        with kept(self.model, self._held):
            for q, point in enumerate(self.points):
                self._at(point, U[:, q])
                found[:, q] = assemble_owned(self._residual, self._work, self.owned)
                if Q is not None and tangents is not None:
                    tangents[q] = gram(Q, self._tangent_on(Q), self.comm)
        found[self._imposed] = 0.0
        return found, tangents

    def _tangent_on(self, Q: np.ndarray) -> np.ndarray:
        """J Q at the model's state (owned rows; the imposed rows the modes' zero)."""
        J = assemble_matrix(self._jacobian, bcs=self.model.bcs)
        try:
            J.assemble()
            JQ = apply(J, Q, self.comm)
        finally:
            J.destroy()
        if self._coupled:
            U, V = self._coupled.low_rank()
            JQ += U @ gram(V, Q, self.comm)
        return JQ

    def energies(self, states: Sequence[np.ndarray], times: Sequence[float] | np.ndarray) -> np.ndarray:
        """The strain energy (J) at each point at each of ``times``, the displacement there
        ``states[i]`` (owned entries × N) from the start (N × times)."""
        energy = strain_energy(self.model)
        found = np.empty((len(self.points), len(times)))
        with kept(self.model, self._held):
            for i, (U, t) in enumerate(zip(states, times)):
                self.model.set_time(float(t))
                for q, point in enumerate(self.points):
                    self._at(point, U[:, q])
                    found[q, i] = energy()
        return found
