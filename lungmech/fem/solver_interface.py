"""What the load stepping needs of a nonlinear solver (:class:`Solver`), what one Newton solve
returns (:class:`NewtonResult`), and the part shared by the solvers that iterate on the model's own
state array (:class:`StepsModelState`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from lungmech.fem import limits
from lungmech.fem.solver_options import NewtonOptions

__all__ = ["NewtonResult", "Solver", "StepsModelState", "steps_model_state"]


@dataclass(frozen=True)
class NewtonResult:
    """What a Newton solve did."""

    converged: bool
    iterations: int
    residuals: tuple[float, ...]  # the norm of the whole residual at each iteration
    reason: str  # PETSc's converged reason, and what failed when it did not converge


class Solver(Protocol):
    """What the load stepping (:func:`solve`) and the outputs need of a nonlinear solver: the
    full-order :class:`NewtonSolver` and the reduced :class:`lungmech.rom.galerkin.ReducedSolver`."""

    model: Any
    description: str  # for summaries, e.g. "full order"
    options: NewtonOptions  # tolerances and iteration limits (a reduced model is trained with its full solver's)

    def solve(self, start: np.ndarray | None = None) -> NewtonResult:
        """One Newton solve at the model's current loads, from its :attr:`state` or ``start``
        (a prediction; the current state is the last equilibrium). A failed solve leaves its
        last iterate there (the load stepping restores the last equilibrium)."""
        ...

    @property
    def state(self) -> np.ndarray:
        """The unknowns it iterates on: the load stepping keeps, extrapolates and restores these.
        The full and Galerkin solvers' is the model's state array; a hyper-reduced solver's is q,
        and it reads or writes the model's state only on request (``project()``,
        :meth:`update_model`): code that moves the model's state must move q too."""
        ...

    def set_state(self, state: np.ndarray) -> None: ...

    def update_model(self) -> None:
        """Write the solver's state into the model's (a reduced solver need not keep it there)."""
        ...

    def deformation_gradient(self) -> np.ndarray:
        """F at the quadrature points where the solver evaluates the model, (cells, points, d, d)."""
        ...

    def start_path(self) -> None:
        """A load path begins (the solver may rescale its convergence test)."""
        ...

    def linear_step(self) -> None:
        """One Newton step from the model's current state at its current loads (no line search)."""
        ...

    @property
    def residual_form(self) -> Any: ...

    @property
    def jacobian_form(self) -> Any: ...

    def destroy(self) -> None: ...


class StepsModelState:
    """The :class:`Solver` part of a solver that iterates on the model's own state array (the
    full and the Galerkin solvers): the load stepping keeps, extrapolates and restores it."""

    model: Any

    @property
    def state(self) -> np.ndarray:
        """The model's state array (owned and ghost entries)."""
        return self.model.state.x.array

    def set_state(self, state: np.ndarray) -> None:
        """Set the model's state (owned and ghost entries)."""
        self.model.state.x.array[:] = state
        self.model.state.x.scatter_forward()

    def update_model(self) -> None:
        """Nothing to do: the model's state is this solver's."""

    def deformation_gradient(self) -> np.ndarray:
        """F = I + ∇u at the quadrature points of this rank's cells, (cells, points, d, d)."""
        return limits.displacement_gradient(self.model)()


def steps_model_state(solver: Solver) -> bool:
    """Whether ``solver`` iterates on the model's own state array (not on reduced coordinates)."""
    return np.shares_memory(solver.state, solver.model.state.x.array)
