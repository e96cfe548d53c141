"""A PGD model answers ``solve(μ)`` like every other model of the problem, by evaluation alone.

Its state at μ and time t is u = Q z, with z = ρ(t) R q(μ) (:class:`~lungmech.pgd.decomposition.Decomposition`):
the decomposition is the equilibrium at the path's end T, and a linear model started at rest
whose loads all follow one ramp r(t), with r(t₀) = 0 at the path's start, is at
ρ(t) = s r(t) / r(T) of it at t (s the load factor). Its outputs are exact functions of z, computed once offline (:class:`~lungmech.pgd.online.Online`):

* the volume ∫ det F dX, a cubic of z (:func:`lungmech.rom.exact.cubic`);
* the probes' displacements, linear in z;
* the strain energy ½ zᵀ (A₀ + Σₑ cₑ(μ) Aₑ) z, Aₑ = Qᵀ Kₑ Q the terms' operators projected and
  cₑ(μ) the values the model's parameters set (a linear law's energy is a quadratic form of u
  whose Hessian is its Jacobian; checked at a random point);
* the scalar loads as the model applies them.

Derivatives in μ are exact through the splines: dz/dμ = ρ(t) ∂(R q)/∂μ, with the energy's
explicit part ½ zᵀ (Σₑ ∂cₑ/∂μ Aₑ) z from the model's own value derivatives
(:func:`lungmech.fem.sensitivity.value_derivatives`).
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict
from typing import Any

import numpy as np

from lungmech.errors import ParameterError
from lungmech.fem.loads import is_pressure
from lungmech.fem.model import Model
from lungmech.fem.parametric import UNITS, Solution, Step, checked_times, output_times, stack
from lungmech.fem.quantities import Probe
from lungmech.fem.sensitivity import value_derivatives
from lungmech.fem.solver import Stepping, StepReport
from lungmech.fem.start import StartReport
from lungmech.parallel.owned import owned_size
from lungmech.pgd import terms as separated
from lungmech.pgd.axes import Axis
from lungmech.pgd.decomposition import Decomposition
from lungmech.pgd.greedy import Options, Round, pgd
from lungmech.pgd.imaged import Reference
from lungmech.pgd.indicator import indicator
from lungmech.pgd.online import Online, online
from lungmech.pgd.point import Point
from lungmech.pgd.terms import separated_terms
from lungmech.pgd.timeline import RampTimeline, SampledTimeline
from lungmech.pgd.values import closed_form, joined
from lungmech.rom.basis import inner_product

__all__ = ["ESTIMATE", "PGDModel", "build", "load_fractions", "ramp_of"]

ESTIMATE = 16  # the Sobol' points where an a priori PGD's indicator is evaluated, its estimate their largest


def ramp_of(model: Model, stepping: Stepping) -> Callable[[float], float]:
    """r(t), the one ramp every load of ``model`` follows over ``stepping``, refused in one line
    where two loads follow different ramps, or the loads do not vanish at the path's start (the
    rest state is then no equilibrium) or vanish at its end."""
    if not model.loads:
        raise ParameterError("PGD: the model has no load, so its answer is the rest state")
    first = model.loads[0].ramp
    probe = np.unique(np.concatenate([np.linspace(stepping.start, stepping.end, 65), model.breakpoints]))
    shape = np.array([first(t) for t in probe])
    for load in model.loads[1:]:
        if not np.allclose([load.ramp(t) for t in probe], shape, rtol=1e-12, atol=0.0):
            label = getattr(load, "label", type(load).__name__)
            raise ParameterError(
                f"PGD: load '{label}' follows another ramp than the first load's: a PGD answers along one ramp"
            )
    if first(stepping.start) != 0.0:
        raise ParameterError(
            f"PGD: the loads' ramp is {first(stepping.start):g}, not 0, at the path's start (t = {stepping.start:g} s): "
            "a PGD's path starts at rest"
        )
    if first(stepping.end) == 0.0:
        raise ParameterError(f"PGD: the loads' ramp is 0 at the path's end (t = {stepping.end:g} s)")
    return first


def load_fractions(model: Model, stepping: Stepping) -> Callable[[float], np.ndarray]:
    """t ↦ r(t)/r(T) of each scalar load (a pressure, in the order of ``model.scalar_loads()``),
    its value at t that fraction of its value at the path's end T; refused in one line where a
    scalar load is 0 at T."""
    pressures = [load for load in model.loads if is_pressure(load)]
    ends = [load.ramp(stepping.end) for load in pressures]  # r(T), once: an answer asks at every output time
    for load, end in zip(pressures, ends):
        if end == 0.0:
            raise ParameterError(
                f"PGD: load '{load.label}' is 0 at the path's end (t = {stepping.end:g} s): a PGD reads its loads there"
            )
    return lambda t: np.array([load.ramp(t) / end for load, end in zip(pressures, ends)])


class PGDModel:
    """The model whose answers are ``decomposition`` evaluated (module docstring): the fem
    ``model`` (for fields, and the values its parameters set), the load path ``stepping``,
    the ``online`` outputs and ``built``, how it was built (for its record). Its terms move
    along the path as ``timeline`` says (default: the loads' one ramp,
    :class:`~lungmech.pgd.timeline.RampTimeline`); a PGD fitted to full solves gives its own
    (:class:`~lungmech.pgd.timeline.SampledTimeline`) and its strain energy's fit ``energy`` (a
    one-row decomposition and its timeline), and answers at the loads' own scale only; on an
    imaged body, its fit of the body's reference ξ(μ) is ``reference``
    (:mod:`lungmech.pgd.imaged`: its timeline then starts at t₀, where the image's fields move
    with μ). Every answer carries the model's estimate of its relative energy-norm error: an
    a priori PGD's indicator at μ, from its residual's factor (:mod:`lungmech.pgd.online`),
    or where none is kept its indicator at a sample of the box, the largest,
    ``built["estimate"]`` (:mod:`lungmech.pgd.indicator`); a fitted one's held-out error.
    Collective for :meth:`fields` only; a solve is evaluation on every rank."""

    def __init__(
        self,
        model: Model,
        decomposition: Decomposition,
        online: Online,
        stepping: Stepping,
        probe_points: Sequence[Sequence[float]] = (),
        built: dict | None = None,
        timeline: SampledTimeline | None = None,
        energy: tuple[Decomposition, SampledTimeline] | None = None,
        reference: Reference | None = None,
    ) -> None:
        if (timeline is None) != (energy is None) or (reference is not None and timeline is None):
            raise ParameterError("PGD: a fitted PGD has both a timeline and its strain energy's fit, or neither")
        self.model = model
        self.parameters = model.parameters
        self.stepping = stepping
        self.decomposition = decomposition
        self.online = online
        self.timeline: RampTimeline | SampledTimeline = (
            timeline if timeline is not None else RampTimeline(ramp_of(model, stepping), stepping.end)
        )
        self.fractions = load_fractions(model, stepping)
        self.energy, self.reference = energy, reference
        self.times = output_times(model, stepping)
        self.probe_points = tuple(tuple(float(c) for c in p) for p in probe_points)
        self.built = dict(built or {})
        self._owned = owned_size(model.space)
        if model.reference_map is not None:  # an image's motion rests on its reference: w = 0 at ξ = 0
            model.set_reference_map(np.zeros(owned_size(model.reference_map.function_space)))
        with model.kept_state():
            model.reset()
            self._rest = model.state.x.array[: self._owned].copy()  # what the modes add to
        self._start = StartReport("rest", "the unloaded state")
        self._values = _Entries(model, online.entries)
        # the values the strain energy's operators take (the others only the indicator's loads)
        self._operated = np.abs(online.energy[:, 1:]).max(axis=(0, 2, 3), initial=0.0) > 0
        self._last = dict(model.parameter_values), 1.0  # the parameters and load factor of the last answer
        operated = self._operated
        with model.kept_state():
            model.set_time(stepping.end)  # the scalar loads at the path's end, the load factor 1
            self._labels = tuple(model.scalar_loads())
            reads = (
                lambda: self._values.read()[operated],
                lambda: np.array(list(model.scalar_loads().values())),
                self._shape_values,
                lambda: self._values.read()[~operated],  # the loads' own values: the indicator's alone
            )
            forms = [closed_form(model, decomposition.axes, read) for read in reads]
        # an answer without setting the fem model needs the first three; the fourth gives its
        # indicator (without it, the build's estimate answers for it)
        self._closed = None if None in forms[:3] else joined([form for form in forms if form is not None])

    @property
    def size(self) -> int:
        """The number of space modes m."""
        return self.decomposition.size

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
        """The outputs at the output times — or at ``times`` (s) — for ``mu`` (the others at
        their defaults), the loads' change from the start scaled by ``scale`` (one factor for
        every load). ``on_step`` sees the start and each output time's state."""
        tic = time.perf_counter()
        values = self.parameters.values(mu)
        factor = _one_factor(scale, len(self.model.loads))
        if self.energy is not None and factor != 1.0:
            raise ParameterError(
                f"a PGD fitted, or of a nonlinear model, answers the loads at the scene's own scale (got a load factor {factor:g}): "
                "put the loads' amplitude in [parameters] to vary it"
            )
        wanted = self.times if times is None else self._times(tuple(times))
        model, stepping, start = self.model, self.stepping, self._start
        self._last = values, factor
        if self._closed is not None and not sensitivities:  # the fem model is not set
            form, ends = self._closed
            found = form(values)
            parts = [found[a:b] for a, b in zip([0, *ends[:-1]], ends)]
            c = np.zeros(len(self._operated))
            c[self._operated] = parts[0]
            loads = dict(zip(self._labels, factor * parts[1]))
            indicated = None
            if len(parts) > 3:
                c[~self._operated] = parts[3]
                indicated = c
            point = Point(self, values, c, loads, parts[2], None, indicated)
        else:
            indicated = None
            if factor != 1.0:  # the indicator's values at the loads' own scale (η is the same at any)
                model.set_time(stepping.end)
                model.set_parameters(values)
                indicated = self._values.read()
            if model.time != stepping.end or model.scaling != (factor, None):
                model.set_time(stepping.end, load_factor=factor)  # the loads at t are r(t)/r(T) of these
            model.set_parameters(values)  # (at that time)
            derivatives = value_derivatives(model) if sensitivities else None
            c = self._values.read()
            point = Point(
                self,
                values,
                c,
                model.scalar_loads(),
                self._shape_values(),
                derivatives,
                c if factor == 1.0 else indicated,
            )
        if self.reference is not None:  # the image on its reference at μ, and its volume there
            imaged = self.online.volume_at(point.state(float(stepping.start), factor), point.a)
            start = self.reference.start(values, point.a).measured(imaged)
        elif self.online.shape:  # the body at rest: of the shape at μ over a shape map
            start = start.measured(self.online.rest_volume(point.a))
        else:  # (the same at every μ)
            start = self._rest_report
        if on_step is not None:  # the start, as every model shows it first
            at_start = float(stepping.start)
            on_step(
                Step(
                    "start",
                    stepping.start,
                    None,
                    lambda: point.outputs(at_start, point.state(at_start, factor), factor),
                    lambda: point.state(at_start, factor),
                    start=start,
                )
            )
        rows, states, derived = [], [], []
        previous = stepping.start
        for t in wanted:
            states.append(point.state(float(t), factor))
            rows.append(point.outputs(float(t), states[-1], factor))
            if sensitivities:
                derived.append(point.derivatives(float(t), factor))
            if on_step is not None and t > stepping.start:
                report = StepReport(float(t), float(t - previous), 0, (), "evaluated", 0.0, True)
                on_step(Step("path", float(t), report, _returning(rows[-1]), _returning(states[-1].copy())))
            previous = float(t)
        return Solution(
            parameters=values,
            times=np.array(wanted, dtype=float),
            outputs=stack(rows),
            states=np.array(states),
            newton_iterations=0,
            seconds=time.perf_counter() - tic,
            sensitivities=stack(derived) if sensitivities else None,
            parameter_names=self.parameters.names,
            units=dict(UNITS),
            start=start,
            scale=factor if isinstance(scale, int | float) else np.asarray(scale, dtype=float).tolist(),
            indicator=point.indicator if point.indicator is not None else self.built.get("estimate"),
        )

    @functools.lru_cache(maxsize=8)  # noqa: B019  (the model lives as long as its answers are asked for)
    def _times(self, times: tuple[float, ...]) -> np.ndarray:
        """The output times asked for, checked (:func:`~lungmech.fem.parametric.checked_times`)."""
        return checked_times(times, self.stepping)

    @functools.cached_property
    def _rest_report(self) -> StartReport:
        """The start's report of a body at rest with no shape map: its volume, at every μ."""
        return self._start.measured(self.online.rest_volume(np.zeros(0)))

    def _shape_values(self) -> np.ndarray:
        """The shape coefficients a the fem model's parameters set now (none: no shape map)."""
        return np.zeros(0) if self.model.shape is None else self.model.shape.values()

    def fields(self, state: np.ndarray, time: float) -> None:
        """The fem model's state Q ``state`` at ``time``, its parameters and load factor the last
        answer's (collective)."""
        model, (values, factor) = self.model, self._last
        model.set_time(time, load_factor=factor)
        if model.parameter_values != values:
            model.set_parameters(values)
        if self.reference is not None:
            self.reference.hand_over(model, values)
        model.state.x.array[: self._owned] = self._rest + self.decomposition.modes @ state
        model.state.x.scatter_forward()

    def reconstruct(self, solution: Solution, index: int) -> np.ndarray:
        """The full state u_rest + Q z of output ``index`` of ``solution`` (owned entries), as
        :meth:`lungmech.rom.reduced.ReducedModel.reconstruct` gives a reduced one's (the rest
        state holds a poromechanical model's porosity, say)."""
        return self._rest + self.decomposition.modes @ solution.states[index]

    def describe(self) -> dict[str, object]:
        """What answers: the decomposition's size; no solver."""
        d = self.decomposition
        how = self.built.get("method", "fitted to full solves" if self.energy is not None else "a priori")
        return {
            "solver": f"PGD evaluation ({d.size} space modes, {d.terms} separated terms, {how})",
            "linear_solver": None,
        }


class _Entries:
    """Reads the values c_e of ``entries`` (indices into :func:`lungmech.pgd.terms.values`)
    from the few Constants that hold them, as the model's parameters set them now."""

    def __init__(self, model: Model, entries: np.ndarray) -> None:
        constants = separated.constants(model)
        starts = np.cumsum([0] + [np.size(c.value) for c in constants])
        holder = np.searchsorted(starts, entries, side="right") - 1  # the constant holding each entry
        self._picks = [(constants[h], int(e - starts[h])) for e, h in zip(entries, holder)]

    def read(self) -> np.ndarray:
        """c_e for each entry, now."""
        return np.array([np.ravel(c.value)[i] for c, i in self._picks], dtype=float)


def _returning(value: object) -> Callable[[], Any]:
    """A function that returns ``value`` (a step's outputs or state, already evaluated)."""
    return lambda: value


def _one_factor(scale: float | Sequence[float], loads: int) -> float:
    """The one load factor a PGD model takes (the same for every load)."""
    if isinstance(scale, int | float) and math.isfinite(scale):
        return float(scale)
    factors = np.broadcast_to(np.asarray(scale, dtype=float), (max(loads, 1),))
    if not (np.all(factors == factors[0]) and np.isfinite(factors[0])):
        raise ParameterError(
            f"a PGD model takes one finite load factor for every load (got {np.asarray(scale).tolist()})"
        )
    return float(factors[0])


def answerable(model: Model) -> None:
    """Refuse, in one line, a model whose parameters a PGD cannot separate: none. (A shape
    coefficient moves the body, and the operators with it: the a priori PGD takes it as a
    curve, :mod:`lungmech.pgd.terms`; a fitted PGD's volumes are cubics of their coordinates
    and the shape coefficients together.)"""
    if not model.parameters.names:
        raise ParameterError("PGD: the model has no parameters to separate: give the scene [parameters]")


def build(
    model: Model,
    stepping: Stepping,
    probe_points: Sequence[Sequence[float]] = (),
    intervals: int = 32,
    options: Options | None = None,
) -> tuple[PGDModel, list[Round]]:
    """The :class:`PGDModel` of ``model`` over its parameters' box along ``stepping``: its terms
    at the path's end, the greedy (``options``) on ``intervals`` per axis, and the online
    outputs (``probe_points`` located on the mesh as it is); with the greedy's rounds.
    Refused in one line before any work where it cannot answer (no parameter, loads on several
    ramps or not at rest at the start) and as :func:`~lungmech.pgd.terms.separated_terms`
    refuses. Collective."""
    answerable(model)
    ramp_of(model, stepping)
    options = options or Options()
    axes = [Axis(parameter, intervals) for parameter in model.parameters]
    tic = time.perf_counter()
    model.set_time(stepping.end)
    problem = separated_terms(model, axes)
    W = inner_product(model, "energy")
    try:
        seconds = {"terms": time.perf_counter() - tic}
        tic = time.perf_counter()
        decomposition, rounds = pgd(problem, W, options)
        seconds["greedy"] = time.perf_counter() - tic
        tic = time.perf_counter()
        estimates = indicator(model, decomposition, W, model.parameters.sample(ESTIMATE, seed=31))
        seconds["indicator"] = time.perf_counter() - tic
        tic = time.perf_counter()
        probe = Probe(model.geometry.mesh, probe_points) if len(probe_points) else None
        outputs = online(model, problem, decomposition.modes, probe, W)
        seconds["outputs"] = time.perf_counter() - tic
    finally:
        problem.destroy()
        W.destroy()
    built = {
        "intervals": intervals,
        "options": asdict(options),
        "rounds": [asdict(r) for r in rounds],
        "operator_terms": len(problem.operator),
        "load_terms": len(problem.load),
        "curves": [
            {"parameter": axes[curve.axis].parameter.name, "points": curve.points, "degrees": curve.degrees}
            for curve in problem.curves
        ],
        "estimate": float(estimates.max()),  # an answer's indicator where the online one is not kept
        "indicator_points": estimates.tolist(),
        "seconds": seconds,
    }
    return PGDModel(model, decomposition, outputs, stepping, probe_points, built), rounds
