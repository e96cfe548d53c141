"""Where a load path starts at μ: the equilibrium at ``stepping.start`` a model steps from.

Every parametric model answers ``solve(μ)`` from a start state that is an equilibrium at μ at
the start time. What that state is belongs to the problem, not to the model that solves it, and
every model says which one it uses (:class:`StartReport`, in the solution, the console and the
summaries):

* :class:`Rest`: the unloaded state; the mesh is the reference configuration;
* :class:`Equilibrium`: a given equilibrium at the *default* parameters (a lung imaged at
  end-expiration, unloaded once at the defaults), moved to μ by a continuation in μ
  (:func:`approach`): at another stiffness its deformed state is not the image;
* :class:`lungmech.lung.inverse.Imaged`: the mesh is the loaded state at the start *for every
  μ*; the unloaded reference is found at μ (the problem of a scene with [inverse]).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Protocol

import numpy as np

from lungmech.errors import ParameterError
from lungmech.fem.solver import Solver, Stepping, StepReport, solve

if TYPE_CHECKING:
    from lungmech.fem.model import Model
    from lungmech.fem.sensitivity import Moved

__all__ = ["Equilibrium", "Rest", "Start", "StartReport", "approach", "one_state"]

Progress = Callable[[float, str], None]  # (fraction done, what is being done)


@dataclass(frozen=True)
class StartReport:
    """What a start did at μ: its ``kind`` ("rest", "equilibrium", "imaged"), one line saying
    what the start state is, the Newton iterations it took and its own numbers (``details``,
    SI units: an inverse problem's iterations and volumes, say)."""

    kind: str
    description: str
    newton_iterations: int = 0
    details: dict = field(default_factory=dict)

    def measured(self, volume: float) -> StartReport:
        """This report with the start state's deformed volume (m³) in its details, and, where the
        details hold the image's volume, how far the start lies from it (m³)."""
        details = self.details | {"volume": float(volume)}
        if "imaged_volume" in details:
            details["from_image"] = float(volume) - details["imaged_volume"]
        return replace(self, details=details)


class Start(Protocol):
    """How a model's load path starts (collective methods)."""

    kind: str
    refuses_sensitivities: str | None  # why its answers have no sensitivities (one line), or None

    def reset(self, model: Model) -> None:
        """The model at the start state at the default parameters (nothing solved)."""

    def place(
        self,
        model: Model,
        solver: Solver,
        values: Mapping[str, float],
        time: float,
        progress: Progress | None = None,
        on_step: Callable[[StepReport], None] | None = None,
    ) -> StartReport:
        """The model's state an equilibrium at ``values`` at ``time``; what was done.
        ``progress(fraction, text)`` follows long work; ``on_step(report)`` sees every accepted
        continuation step."""

    def moved(self, model: Model) -> Moved | None:
        """What the last placement set beyond the parameters' values, with its derivatives with
        respect to μ (:class:`lungmech.fem.sensitivity.Moved`); None for a start whose states are
        all solved on the model's own forms."""


def approach(
    model: Model,
    solver: Solver,
    values: Mapping[str, float],
    start: Mapping[str, float],
    time: float,
    on_step: Callable[[StepReport], None] | None = None,
    first_step: float = 0.25,
) -> int:
    """Move the model's state, an equilibrium at the parameters ``start`` and time ``time``, to
    the equilibrium at ``values``: a continuation along the straight line between them in the unit
    box (log parameters in log μ), with the load stepping's adaptive steps from ``first_step`` (a
    fraction of the way; 1: straight there, continuing only when Newton fails). A start state under
    load is an equilibrium for its own parameters only; other parameters reach it this way rather
    than in one Newton solve. Returns the Newton iterations (0 when the parameters are the
    start's). Collective."""
    if all(values[name] == start[name] for name in values):
        model.set_parameters(values)
        model.set_time(time)
        return 0
    box = model.parameters
    a, b = box.to_unit(start), box.to_unit(values)

    def drive(s: float) -> None:
        model.set_parameters(values if s == 1.0 else box.from_unit(a + s * (b - a)))  # the end exactly
        model.set_time(time)

    report = solve(
        model, Stepping(initial_step=first_step), solver=solver, drive=drive, on_step=on_step, monitor=lambda step: None
    )
    if model.parameter_values != values:  # the path ended short of s = 1 by rounding
        model.set_parameters(values)
    return report.newton_iterations


class Rest:
    """The unloaded state (u = 0, every other field at its initial value) on the reference mesh,
    an equilibrium when the loads at the start vanish; moved to μ by :func:`approach`."""

    kind = "rest"
    refuses_sensitivities: str | None = None
    description = "the unloaded state"
    details: dict = {}

    def reset(self, model: Model) -> None:
        model.set_parameters(model.parameters.defaults)
        model.reset()

    def state(self, model: Model) -> np.ndarray:
        """The start state at the default parameters (a full local array)."""
        with model.kept_state():
            model.reset()
            return model.state.x.array.copy()

    def place(
        self,
        model: Model,
        solver: Solver,
        values: Mapping[str, float],
        time: float,
        progress: Progress | None = None,
        on_step: Callable[[StepReport], None] | None = None,
    ) -> StartReport:
        self.reset(model)
        iterations = approach(model, solver, values, model.parameters.defaults, time, on_step)
        return StartReport("rest", self.description, iterations)

    def moved(self, model: Model) -> Moved | None:
        """Nothing: the path's every state is solved on the model's own forms."""
        return None


class Equilibrium:
    """A given equilibrium at the default parameters at the start time — ``state``, a full
    local state array (owned and ghost entries) — moved to μ by :func:`approach`.
    ``description`` says what it is ("the imaged lung unloaded at the default parameters, moved
    to μ", say); ``details`` are its numbers for the summaries."""

    kind = "equilibrium"
    refuses_sensitivities: str | None = None

    def __init__(
        self,
        state: np.ndarray,
        description: str = "an equilibrium at the default parameters, moved to μ",
        details: Mapping[str, object] | None = None,
    ) -> None:
        self._state = np.array(state, dtype=float)
        self.description = description
        self.details = dict(details or {})

    def reset(self, model: Model) -> None:
        model.set_parameters(model.parameters.defaults)
        model.state.x.array[:] = self._state
        model.state.x.scatter_forward()

    def state(self, model: Model) -> np.ndarray:
        """The start state at the default parameters (a copy)."""
        return self._state.copy()

    def place(
        self,
        model: Model,
        solver: Solver,
        values: Mapping[str, float],
        time: float,
        progress: Progress | None = None,
        on_step: Callable[[StepReport], None] | None = None,
    ) -> StartReport:
        self.reset(model)
        iterations = approach(model, solver, values, model.parameters.defaults, time, on_step)
        return StartReport("equilibrium", self.description, iterations, dict(self.details))

    def moved(self, model: Model) -> Moved | None:
        """Nothing: the path's every state is solved on the model's own forms."""
        return None


def one_state(start: Start, model: Model) -> np.ndarray:
    """The one start state a reduced basis is relative to: ``start``'s at the default parameters
    (a full local array). A start found anew at every μ (an imaged body's) has none: refused."""
    if not isinstance(start, Rest | Equilibrium):
        raise ParameterError(
            f"a reduced basis is relative to one start state, and this full model's start ({start.kind}) is found "
            "anew at every μ: give it an Equilibrium start (the unloaded reference found at the defaults)"
        )
    return start.state(model)
