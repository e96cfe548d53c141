"""One problem, several models of it: every model answers ``solve(μ)`` with the same outputs.

In the manner of pyMOR (model → reductor → reduced model), a *parametric model* has named
``parameters`` and a ``solve(mu)`` that returns a :class:`Solution`: the outputs at the output
times of the load path, the states (full state vectors, or reduced coordinates) and, on request,
the derivatives of the outputs with respect to μ. :class:`FullOrderModel` is the finite-element
model driven along its load path by Newton's method; :class:`lungmech.rom.reduced.ReducedModel`
answers the same calls from a reduced basis. They can be swapped, compared and chained.

The outputs are the same functionals of the state for every model (:class:`Outputs`): the
deformed volume ∫ J dX (m³), the strain energy ∫ ψ dX (J), the displacement at probe points (m)
and the value of every scalar load (Pa, for pressure–volume curves). They are recorded at the
*output times*: the stepping's ``times``, every ramp breakpoint and the end, which every model
hits exactly, so two models' answers are compared point by point.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from lungmech.errors import ParameterError
from lungmech.fem.parameters import Parameters
from lungmech.fem.quantities import Probe, deformed_volume, strain_energy
from lungmech.fem.sensitivity import check_differentiable, output_derivatives
from lungmech.fem.solver import NewtonOptions, NewtonSolver, Solver, Stepping, solve, steps_model_state

__all__ = ["FullOrderModel", "Outputs", "ParametricModel", "Solution", "approach", "output_times", "trajectory"]

UNITS = {"time": "s", "volume": "m^3", "strain_energy": "J", "probes": "m", "loads": "Pa"}


@dataclass(frozen=True)
class Solution:
    """What ``solve(mu)`` returns.

    ``times`` (s) are the output times; ``outputs[name]`` has one row per output time (volume
    in m³, strain_energy in J, probes in m with shape (times, points, 3), loads in Pa by label).
    ``states`` has one row per output time: the owned entries of the full state vector, or the
    reduced coordinates q. ``sensitivities[name]`` (when asked) holds ∂output/∂μ with the
    parameters on the last axis, in ``parameter_names`` order. ``indicator``: a reduced
    model's estimate of its relative energy-norm error along this path (None: the full model,
    or a reduced model without an enrichment), see :mod:`lungmech.rom.indicator`.
    """

    parameters: dict[str, float]
    times: np.ndarray
    outputs: dict[str, np.ndarray]
    states: np.ndarray
    newton_iterations: int
    seconds: float
    sensitivities: dict[str, np.ndarray] | None = None
    parameter_names: tuple[str, ...] = ()
    units: dict[str, str] = field(default_factory=lambda: dict(UNITS))
    indicator: float | None = None


class ParametricModel(Protocol):
    """What every model of a problem provides, full order or reduced."""

    parameters: Parameters

    def solve(self, mu: Mapping[str, float] | None = None, *, sensitivities: bool = False) -> Solution: ...


def approach(
    model,
    solver: Solver,
    values: Mapping[str, float],
    start: Mapping[str, float],
    time: float,
    on_step: Callable | None = None,
    first_step: float = 0.25,
) -> int:
    """Move the model's state, an equilibrium at the parameters ``start`` and time ``time``, to
    the equilibrium at ``values``: a continuation along the straight line between them in the unit
    box (log parameters in log μ), with the load stepping's adaptive steps from ``first_step`` (a
    fraction of the way; 1: straight there, continuing only when Newton fails). A start state under
    load (a lung imaged at end-expiration) is an equilibrium for its own parameters only; other
    parameters reach it this way rather than in one Newton solve. Returns the Newton iterations
    (0 when the parameters are the start's). Collective."""
    if all(values[name] == start[name] for name in values):
        model.set_parameters(values)
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


def trajectory(
    owner,
    values: dict[str, float],
    state: Callable[[], np.ndarray],
    derivatives: Callable[[], dict] | None = None,
    on_step: Callable | None = None,
    first_step: float = 0.25,
) -> Solution:
    """The load path of ``owner`` (a full or reduced model: its ``model``, ``solver``,
    ``stepping``, ``outputs``, ``times``, ``parameters``) at ``values``, from the state the model
    holds (an equilibrium at the default parameters at ``stepping.start``): :func:`approach`, then
    the load stepping, recording ``outputs()``, ``state()`` and ``derivatives()`` at every output
    time. ``on_step(step)`` is called after every accepted step of both (a snapshot); ``first_step``
    is the approach's. Collective."""
    model, stepping = owner.model, owner.stepping
    if derivatives is not None:
        check_differentiable(model)  # before the solve, not after it
    tic = time.perf_counter()
    iterations = approach(model, owner.solver, values, owner.parameters.defaults, stepping.start, on_step, first_step)
    rows, states, derived = [], [], []

    def record(step) -> None:
        if on_step is not None:
            on_step(step)
        if np.min(np.abs(owner.times - model.time)) <= 1e-9 * (stepping.end - stepping.start):
            rows.append(owner.outputs())
            states.append(state())
            if derivatives is not None:
                derived.append(derivatives())

    model.set_time(stepping.start)
    report = solve(model, stepping, solver=owner.solver, on_step=record, monitor=lambda step: None)
    return Solution(
        parameters=values,
        times=owner.times.copy(),
        outputs=stack(rows),
        states=np.array(states),
        newton_iterations=iterations + report.newton_iterations,
        seconds=time.perf_counter() - tic,
        sensitivities=stack(derived) if derivatives is not None else None,
        parameter_names=owner.parameters.names,
    )


def output_times(model, stepping: Stepping) -> np.ndarray:
    """The times a load path reports: the stepping's ``times``, the ramp breakpoints and the end."""
    inside = [t for t in (*stepping.times, *model.breakpoints) if stepping.start < t < stepping.end]
    return np.array(sorted({*inside, stepping.end}))


class Outputs:
    """The outputs of a model's current state, compiled once (collective)."""

    def __init__(self, model, probes: Sequence[Sequence[float]] = ()):
        self.model = model
        self.probe_points = tuple(tuple(float(c) for c in point) for point in probes)
        self._volume, self._energy = deformed_volume(model), strain_energy(model)
        self._probe = Probe(model.geometry.mesh, probes) if len(probes) else None

    @property
    def probe(self) -> Probe | None:
        """The probe of the displacement at the points, if any were given."""
        return self._probe

    def __call__(self) -> dict[str, object]:
        values: dict[str, object] = {"volume": self._volume(), "strain_energy": self._energy()}
        if self._probe is not None:
            values["probes"] = self._probe(self.model.displacement())
        values["loads"] = self.model.scalar_loads()
        return values


def stack(rows: list[dict[str, object]]) -> dict[str, np.ndarray]:
    """Rows of outputs (one per time) as arrays with the time first; loads by label."""
    stacked = {name: np.array([row[name] for row in rows]) for name in rows[0] if name != "loads"}
    for label in rows[0]["loads"]:
        stacked[f"loads/{label}"] = np.array([row["loads"][label] for row in rows])
    return stacked


class FullOrderModel:
    """The finite-element model driven along its load path: ``solve(mu)`` from the start state.

    ``model`` is a :class:`~lungmech.fem.model.Model` with parameters; each solve resets it to
    ``start`` (default: the unloaded state; a lung imaged under load starts from the state the
    inverse problem found), an equilibrium at the default parameters at ``stepping.start``,
    moves it to the asked parameters (:func:`approach`) and steps it from ``stepping.start`` to
    ``stepping.end``.
    Collective. The model's compiled forms serve every μ: nothing is recompiled.
    """

    def __init__(
        self,
        model,
        stepping: Stepping | None = None,
        newton: NewtonOptions | None = None,
        probes: Sequence[Sequence[float]] = (),
        start: np.ndarray | None = None,
        solver: Solver | None = None,
    ):
        self.model = model
        self.parameters = model.parameters
        self.stepping = stepping or Stepping()
        self.solver = solver or NewtonSolver(model, newton)
        if not steps_model_state(self.solver):
            raise ParameterError(
                f"FullOrderModel steps the model's state; this solver ({self.solver.description}) iterates on "
                "reduced coordinates: use ReducedModel(..., sample=...) for a hyper-reduced model"
            )
        self.outputs = Outputs(model, probes)
        self.start = start
        self.times = output_times(model, self.stepping)

    def solve(
        self, mu: Mapping[str, float] | None = None, *, sensitivities: bool = False, on_step: Callable | None = None
    ) -> Solution:
        """The outputs (and states) at the output times for the parameters ``mu`` (the others at
        their defaults). ``on_step(step)`` sees every accepted step (e.g. to keep snapshots)."""
        owned = self.model.space.dofmap.index_map.size_local * self.model.space.dofmap.index_map_bs
        self.reset()
        return trajectory(
            self,
            self.parameters.values(mu),
            state=lambda: self.model.state.x.array[:owned].copy(),
            derivatives=self.sensitivities if sensitivities else None,
            on_step=on_step,
        )

    def reset(self) -> None:
        """The model back at the start state, at the default parameters."""
        model = self.model
        model.set_parameters(self.parameters.defaults)
        model.reset()
        if self.start is not None:
            model.state.x.array[:] = self.start
            model.state.x.scatter_forward()

    def sensitivities(self) -> dict[str, object]:
        """∂outputs/∂μ at the current state: direct sensitivities (:mod:`lungmech.fem.sensitivity`)."""
        return output_derivatives(self.model, self.outputs, self.solver)
