"""One problem, several models of it: every model answers ``solve(μ)`` with the same outputs.

In the manner of pyMOR (model → reductor → reduced model), a *parametric model* has named
``parameters`` and a ``solve(mu)`` that returns a :class:`Solution`: the outputs at the output
times of the load path, the states (full state vectors, or reduced coordinates) and, on request,
the derivatives of the outputs with respect to μ. :class:`FullOrderModel` is the finite-element
model driven along its load path by Newton's method; :class:`lungmech.rom.reduced.ReducedModel`
answers the same calls from a reduced basis. They can be swapped, compared and chained.

The outputs are the same functionals of the state for every model (:class:`Outputs`): the
deformed volume ∫ J dX (m³), the strain energy ∫ ψ dX (J), the displacement at probe points (m),
the value of every scalar load as applied (Pa, for pressure–volume curves) and the formulation's
own averages (a lung's fractions and mean stresses), where the model has the full field. They
are recorded at the *output times*: the stepping's ``times``, every ramp breakpoint and the end,
which every model hits exactly, so two models' answers are compared point by point; or at the
times asked for (``solve(mu, times=[T])``: the equilibrium at T, a static answer).

Where the path starts is the problem's (:mod:`lungmech.fem.start`): every solution says which
start it used (:attr:`Solution.start`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Protocol, cast

import numpy as np

from lungmech.errors import ParameterError
from lungmech.fem.averages import means
from lungmech.fem.parameters import Parameters
from lungmech.fem.quantities import Probe, deformed_volume, strain_energy
from lungmech.fem.sensitivity import output_derivatives, value_derivatives
from lungmech.fem.solver import (
    NewtonOptions,
    NewtonSolver,
    Solver,
    Stepping,
    StepReport,
    solve,
    steps_model_state,
)
from lungmech.fem.start import Equilibrium, Rest, Start, StartReport, approach
from lungmech.parallel.owned import owned_size

if TYPE_CHECKING:
    from lungmech.fem.model import Model

__all__ = [
    "FullOrderModel",
    "Outputs",
    "ParametricModel",
    "Solution",
    "Step",
    "approach",
    "checked_times",
    "output_times",
    "trajectory",
]

UNITS = {"time": "s", "volume": "m^3", "strain_energy": "J", "probes": "m", "loads": "Pa"}


@dataclass(frozen=True)
class Solution:
    """What ``solve(mu)`` returns.

    ``times`` (s) are the output times; ``outputs[name]`` has one row per output time (volume
    in m³, strain_energy in J, probes in m with shape (times, points, 3), loads in Pa by label).
    ``states`` has one row per output time: the owned entries of the full state vector, or the
    reduced coordinates q. ``sensitivities[name]`` (when asked) holds ∂output/∂μ with the
    parameters on the last axis, in ``parameter_names`` order, for every output but the
    formulation's averages. ``indicator``: a reduced
    model's estimate of its relative energy-norm error along this path (None: the full model,
    or a reduced model without an enrichment), see :mod:`lungmech.rom.indicator`. ``start``:
    what the start state at μ is (its ``details`` hold its volume, m³); ``scale``: the factor(s)
    on the loads' change from the start.
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
    start: StartReport | None = None
    scale: float | list[float] = 1.0


class ParametricModel(Protocol):
    """What every model of a problem provides, full order or reduced: ``solve(mu)`` with the
    keywords below, its fem ``model`` (for fields and pictures), its ``parameters`` and
    ``stepping``, :meth:`fields` and :meth:`describe`. The application talks to nothing else."""

    model: Model
    parameters: Parameters
    stepping: Stepping

    def solve(
        self,
        mu: Mapping[str, float] | None = None,
        *,
        sensitivities: bool = False,
        on_step: Callable[[Step], None] | None = None,
        scale: float | Sequence[float] = 1.0,
        times: Sequence[float] | None = None,
        progress: Callable[[float, str], None] | None = None,
    ) -> Solution: ...

    def fields(self, state: np.ndarray, time: float) -> None:
        """The fem model's state the full field of ``state`` (a :class:`Step`'s or a
        solution's row) at ``time``, for writing fields or pictures. Collective."""

    def describe(self) -> dict[str, object]:
        """What solves it, for summaries: the solver and the linear solver, by name (merged into
        a run's summary)."""


@dataclass(frozen=True)
class Step:
    """One state of a solve, as ``solve(mu, on_step=...)`` shows it.

    ``phase``: "start" (the start state at μ; ``start`` says what it is), "approach" (an
    accepted continuation step in μ towards it), "path" (an accepted step of the load path) or
    "cut" (a load step Newton did not converge on, cut back: its ``report``; the state is the
    last accepted one). ``time`` (s); ``report``: the Newton solve (None for the start). On
    request: the model's ``outputs()`` (as :class:`Outputs` gives them), its ``state()`` (a copy:
    the full owned entries, or reduced coordinates q; the model's ``fields(state, time)`` makes
    it a full field) and ``indicator()`` (a reduced model's error estimate of the path so far,
    relative, energy norm; None for a model without one)."""

    phase: str
    time: float
    report: StepReport | None
    outputs: Callable[[], dict[str, object]]
    state: Callable[[], np.ndarray]
    indicator: Callable[[], float | None] = lambda: None
    start: StartReport | None = None


class Recorder(Protocol):
    """What a model records at the output times (:class:`Outputs`, or a reduced model's): its
    outputs now, and their units by name."""

    @property
    def units(self) -> dict[str, str]: ...

    def __call__(self) -> dict[str, object]: ...


class Driven(Protocol):
    """What :func:`trajectory` drives along the load path: a full or reduced model, with its fem
    ``model``, ``solver``, ``stepping``, ``outputs``, output ``times`` and ``parameters``."""

    @property
    def model(self) -> Model: ...

    @property
    def solver(self) -> Solver: ...

    @property
    def stepping(self) -> Stepping: ...

    @property
    def outputs(self) -> Recorder: ...

    @property
    def times(self) -> np.ndarray: ...

    @property
    def parameters(self) -> Parameters: ...


def trajectory(
    owner: Driven,
    values: dict[str, float],
    start: Callable[[Callable | None], StartReport],
    state: Callable[[], np.ndarray],
    derivatives: Callable[[], dict] | None = None,
    on_step: Callable[[Step], None] | None = None,
    scale: float | Sequence[float] = 1.0,
    times: Sequence[float] | None = None,
    observe: Callable[[], None] | None = None,
    indicator: Callable[[], float | None] = lambda: None,
) -> Solution:
    """The load path of ``owner`` (a full or reduced model: its ``model``, ``solver``,
    ``stepping``, ``outputs``, ``times``, ``parameters``) at ``values``: ``start(on_approach)``
    places the start state at μ (returning its :class:`StartReport`), then the load stepping
    records ``outputs()``, ``state()`` and ``derivatives()`` at the output times — ``times``
    (each in [start, end] of the stepping; the path then ends at the last) or the owner's.
    ``scale`` multiplies the loads' change from the start (one factor or one per load).
    ``observe()`` is called at every output time, after its outputs (a reduced model's error
    estimate); ``on_step`` sees every state (:class:`Step`, with ``indicator``). Collective."""
    model, stepping = owner.model, owner.stepping
    wanted = owner.times if times is None else checked_times(times, stepping)
    tic = time.perf_counter()
    rows, states, derived = [], [], []

    def show(phase: str, report: StepReport | None, started: StartReport | None = None) -> None:
        if on_step is not None:
            on_step(Step(phase, model.time, report, owner.outputs, state, indicator, started))

    placed = start(None if on_step is None else lambda report: show("approach", report))
    factor = np.asarray(scale, dtype=float)
    if np.all(factor == 1.0):  # bit for bit the scene's loads
        drive: Callable[[float], None] = model.set_time
    else:
        drive = lambda t: model.set_time(t, load_factor=scale, about=stepping.start)  # noqa: E731
    drive(stepping.start)  # the start's own work may have left another time (or none) set
    span = stepping.end - stepping.start

    def record(report: StepReport | None) -> None:
        if np.min(np.abs(wanted - model.time)) <= 1e-9 * span:
            rows.append(owner.outputs())
            states.append(state())
            if derivatives is not None:
                derived.append(derivatives())
            if observe is not None:
                observe()
        if report is not None:
            show("path", report)

    record(None)
    placed = placed.measured(cast(float, rows[0]["volume"] if rows else owner.outputs()["volume"]))  # m³
    show("start", None, placed)
    iterations = placed.newton_iterations
    last = float(wanted[-1])
    if last > stepping.start + 1e-9 * span:
        path = replace(stepping, end=last, times=tuple(float(t) for t in wanted if stepping.start < t < last))

        def cut(report: StepReport) -> None:
            if not report.converged:
                show("cut", report)

        report = solve(
            model, path, solver=owner.solver, on_step=record, monitor=cut, drive=drive, breakpoints=model.breakpoints
        )
        iterations += report.newton_iterations
    return Solution(
        parameters=values,
        times=np.array(wanted, dtype=float),
        outputs=stack(rows),
        states=np.array(states),
        newton_iterations=iterations,
        seconds=time.perf_counter() - tic,
        sensitivities=stack(derived) if derivatives is not None else None,
        parameter_names=owner.parameters.names,
        units=dict(owner.outputs.units),
        start=placed,
        scale=factor.tolist(),
    )


def checked_times(times: Sequence[float], stepping: Stepping) -> np.ndarray:
    """The output times asked for, sorted, each a number in [start, end] of the load path."""
    try:
        asked = np.unique(np.asarray(times, dtype=float).reshape(-1))
    except (TypeError, ValueError):
        raise ParameterError(f"times must be numbers, in s (got {times!r})") from None
    if not asked.size or not np.all(np.isfinite(asked)):
        raise ParameterError(f"times must be finite numbers, in s, at least one (got {times!r})")
    span = stepping.end - stepping.start
    outside = asked[(asked < stepping.start - 1e-12 * span) | (asked > stepping.end + 1e-12 * span)]
    if outside.size:
        raise ParameterError(
            f"time {outside[0]:g} s lies outside the model's load path [{stepping.start:g}, {stepping.end:g}] s"
        )
    return np.clip(asked, stepping.start, stepping.end)


def output_times(model: Model, stepping: Stepping) -> np.ndarray:
    """The times a load path reports: the stepping's ``times``, the ramp breakpoints and the end."""
    inside = [t for t in (*stepping.times, *model.breakpoints) if stepping.start < t < stepping.end]
    return np.array(sorted({*inside, stepping.end}))


class Outputs:
    """The outputs of a model's current state, compiled once (collective): volume, strain
    energy, probes, the scalar loads as applied and the formulation's averages
    (:mod:`lungmech.fem.averages`), if it has any."""

    def __init__(self, model: Model, probes: Sequence[Sequence[float]] | Probe = ()) -> None:
        self.model = model
        self._probe = (
            probes if isinstance(probes, Probe) else (Probe(model.geometry.mesh, probes) if len(probes) else None)
        )
        self.probe_points = () if self._probe is None else tuple(tuple(float(c) for c in p) for p in self._probe.points)
        self._volume, self._energy = deformed_volume(model), strain_energy(model)
        self._averages = means(model)
        self.units = dict(UNITS) | {f"averages/{name}": unit for name, (_, unit) in self._averages.items()}

    @property
    def probe(self) -> Probe | None:
        """The probe of the displacement at the points, if any were given."""
        return self._probe

    def __call__(self) -> dict[str, object]:
        values: dict[str, object] = {"volume": self._volume(), "strain_energy": self._energy()}
        if self._probe is not None:
            values["probes"] = self._probe(self.model.displacement())
        values["loads"] = self.model.scalar_loads()
        if self._averages:
            values["averages"] = {name: mean() for name, (mean, _) in self._averages.items()}
        return values


def stack(rows: list[dict[str, object]]) -> dict[str, np.ndarray]:
    """Rows of outputs (one per time) as arrays with the time first; loads and averages by name
    ("loads/<label>", "averages/<name>")."""
    grouped = ("loads", "averages")
    stacked = {name: np.array([row[name] for row in rows]) for name in rows[0] if name not in grouped}
    for group in grouped:
        for name in cast(dict[str, float], rows[0].get(group, {})):  # values by name
            stacked[f"{group}/{name}"] = np.array([cast(dict[str, float], row[group])[name] for row in rows])
    return stacked


class FullOrderModel:
    """The finite-element model driven along its load path: ``solve(mu)`` from its start.

    ``model`` is a :class:`~lungmech.fem.model.Model` with parameters. ``start`` says where every
    solve begins (:mod:`lungmech.fem.start`): :class:`~lungmech.fem.start.Rest` (the default),
    a state array or :class:`~lungmech.fem.start.Equilibrium` (an equilibrium at the default
    parameters, moved to μ by continuation), or :class:`lungmech.lung.inverse.Imaged` (the mesh
    is the loaded state at the start for every μ: the unloaded reference is found at μ). Then
    the load stepping runs from ``stepping.start`` to ``stepping.end``. Collective. The model's
    compiled forms serve every μ: nothing is recompiled.
    """

    def __init__(
        self,
        model: Model,
        stepping: Stepping | None = None,
        newton: NewtonOptions | None = None,
        probes: Sequence[Sequence[float]] | Probe = (),
        start: Start | np.ndarray | None = None,
        solver: Solver | None = None,
    ) -> None:
        self.model = model
        self.parameters = model.parameters
        self.stepping = stepping or Stepping()
        self.solver = solver or NewtonSolver(model, newton)
        if not steps_model_state(self.solver):
            raise ParameterError(
                f"FullOrderModel steps the model's state; this solver ({self.solver.description}) iterates on "
                "reduced coordinates: use ReducedModel(..., sample=...) for a hyper-reduced model"
            )
        self.outputs = Outputs(model, probes)  # probes located now: on an imaged mesh, in the image
        self.start: Start = Rest() if start is None else Equilibrium(start) if isinstance(start, np.ndarray) else start
        self.times = output_times(model, self.stepping)

    def solve(
        self,
        mu: Mapping[str, float] | None = None,
        *,
        sensitivities: bool = False,
        on_step: Callable[[Step], None] | None = None,
        scale: float | Sequence[float] = 1.0,
        times: Sequence[float] | None = None,
        progress: Callable[[float, str], None] | None = None,
    ) -> Solution:
        """The outputs (and states) at the output times — or at ``times`` (s) — for the
        parameters ``mu`` (the others at their defaults), the loads' change from the start scaled
        by ``scale``. ``on_step`` sees every accepted state (:class:`Step`: e.g. snapshots, a
        history); ``progress(fraction, text)`` the start's own work (an inverse problem's
        iterations)."""
        if sensitivities and self.start.refuses_sensitivities:
            raise ParameterError(self.start.refuses_sensitivities)  # before the work
        owned = owned_size(self.model.space)
        values = self.parameters.values(mu)

        def start(on_approach: Callable[[StepReport], None] | None) -> StartReport:
            return self.start.place(self.model, self.solver, values, self.stepping.start, progress, on_approach)

        return trajectory(
            self,
            values,
            start,
            state=lambda: self.model.state.x.array[:owned].copy(),
            derivatives=self.sensitivities if sensitivities else None,
            on_step=on_step,
            scale=scale,
            times=times,
        )

    def fields(self, state: np.ndarray, time: float) -> None:
        """The model's state ``state`` (owned entries) at ``time`` (collective)."""
        model = self.model
        model.set_time(time, *model.scaling)
        model.state.x.array[: state.size] = state
        model.state.x.scatter_forward()

    def describe(self) -> dict[str, object]:
        """What solves it, for summaries: the solver, and the linear solver "auto" chose."""
        return {"solver": self.solver.description, "linear_solver": getattr(self.solver, "linear_solver", None)}

    def reset(self) -> None:
        """The model back at the start state, at the default parameters."""
        self.start.reset(self.model)

    def sensitivities(self) -> dict[str, object]:
        """∂outputs/∂μ at the current state: direct sensitivities (:mod:`lungmech.fem.sensitivity`),
        with what the start set at μ (an imaged body's reference map: its own sensitivities)."""
        derivatives = value_derivatives(self.model, self.start.moved(self.model))
        return output_derivatives(self.model, self.outputs, self.solver, derivatives=derivatives)
