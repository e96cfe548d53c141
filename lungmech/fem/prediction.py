"""The next load step's state, predicted from the converged ones of a smooth stretch of the path."""

from __future__ import annotations

import math
from typing import cast

from petsc4py import PETSc

import numpy as np

from lungmech.errors import Interrupted
from lungmech.fem.solver_interface import Solver

__all__ = ["Path"]


class Path:
    """The converged states of one smooth stretch of a load path (from its start or its last
    ramp breakpoint), kept to predict the next step's state (the last three at most)."""

    def __init__(self, t: float, state: np.ndarray) -> None:
        self.times, self.states = [t], [state.copy()]

    @property
    def last(self) -> np.ndarray:
        return self.states[-1]

    def append(self, t: float, state: np.ndarray) -> None:
        self.times, self.states = [*self.times[-2:], t], [*self.states[-2:], state.copy()]

    def predict(self, t: float, solver: Solver, rate: np.ndarray | None) -> tuple[np.ndarray | None, int]:
        """A prediction of the state at t (the loads already at t), and how many linear solves it
        cost. With two or three converged states: their Lagrange extrapolation,
        x(t) ≈ Σ_i x_i Π_{j≠i} (t − t_j)/(t_i − t_j), exact for a path of that degree in t. With
        one: the tangent's response x_0 + K⁻¹(load increment), taken in full. Newton's first step
        from an equilibrium is that same response, but a line search judging it by the energy may
        crawl along it where the path curves (a nearly incompressible solid: a tangential step
        leaves the isochoric manifold to second order, at a bulk modulus' cost), while from the
        prediction Newton corrects back onto the path. None: no prediction (a singular tangent)."""
        if len(self.times) > 1:
            extrapolated = sum(
                x_i * math.prod((t - t_j) / (t_i - t_j) for j, t_j in enumerate(self.times) if j != i)
                for i, (t_i, x_i) in enumerate(zip(self.times, self.states))
            )
            return cast(np.ndarray, extrapolated), 0  # a sum of two or three arrays
        if rate is not None:
            return self.last + (t - self.times[0]) * rate, 0
        try:
            solver.linear_step()
        except PETSc.Error:  # a singular tangent: Newton starts from the last state
            Interrupted.raise_pending()
            return None, 1
        finally:
            predicted = solver.state.copy()
            solver.set_state(self.last)
        return predicted, 1
