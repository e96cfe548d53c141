"""A PGD model answers ``solve(μ)`` like every other model of the problem, by evaluation alone.

Its state at μ and time t is u = Q z, with z = ρ(t) R q(μ) (:class:`~lungmech.pgd.decomposition.Decomposition`):
the decomposition is the equilibrium at the path's end T, and a linear model started at rest
whose loads all follow one ramp r(t), with r(t₀) = 0 at the path's start, is at
ρ(t) = s r(t) / r(T) of it at t (s the load factor). Its outputs are exact functions of z, computed once offline (:class:`Online`):

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

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np
import ufl

from lungmech.errors import ParameterError
from lungmech.fem.model import Model
from lungmech.fem.parametric import UNITS, Solution, Step, checked_times, output_times, stack
from lungmech.fem.quantities import Probe, strain_energy
from lungmech.fem.sensitivity import value_derivatives
from lungmech.fem.solver import Stepping, StepReport
from lungmech.fem.start import StartReport
from lungmech.parallel.linalg import apply, gram
from lungmech.parallel.owned import owned_size
from lungmech.pgd import terms as separated
from lungmech.pgd.axes import Axis
from lungmech.pgd.decomposition import Decomposition
from lungmech.pgd.greedy import Options, Round, pgd
from lungmech.pgd.terms import separated_terms
from lungmech.rom.basis import inner_product
from lungmech.rom.exact import Cubic, affine, cubic

__all__ = ["Online", "PGDModel", "build", "online", "ramp_of"]

ENERGY_CHECK = 1e-9  # the quadratic form's strain energy against the model's own, relative


@dataclass(frozen=True)
class Online:
    """The outputs of u = Q z as functions of z: ``volume`` (m³), ``probes`` (m: 3 rows per
    point, x y z, × m), ``energy`` (J: A₀ then each entry's Aₑ, (1 + entries) × m × m) for
    the values ``entries`` (indices into :func:`lungmech.pgd.terms.values`)."""

    volume: Cubic
    probes: np.ndarray
    energy: np.ndarray
    entries: np.ndarray

    def arrays(self) -> dict[str, np.ndarray]:
        """Its arrays by name, for a model file."""
        c0, c1, c2, c3 = self.volume.arrays()
        return {"volume/c0": c0, "volume/c1": c1, "volume/c2": c2, "volume/c3": c3} | {
            "probes": self.probes,
            "energy": self.energy,
            "entries": self.entries,
        }

    @classmethod
    def of(cls, arrays: Mapping[str, np.ndarray]) -> Online:
        """The :class:`Online` of its :meth:`arrays`."""
        volume = Cubic.of(tuple(arrays[f"volume/{name}"] for name in ("c0", "c1", "c2", "c3")))
        return cls(volume, arrays["probes"], arrays["energy"], arrays["entries"].astype(int))

    def operator(self, c: np.ndarray) -> np.ndarray:
        """A(c) = A₀ + Σₑ cₑ Aₑ (m × m)."""
        return self.energy[0] + np.tensordot(c[self.entries], self.energy[1:], axes=1)


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


def online(model: Model, problem: separated.Terms, modes: np.ndarray, probe: Probe | None) -> Online:
    """The :class:`Online` outputs of ``model``'s states Q z (``modes`` Q, owned rows) from the
    rest state, with the terms' operators of ``problem``; the strain energy's form checked
    against the model's own at a random point. Collective; the model's state and parameters are
    kept."""
    comm = model.geometry.mesh.comm
    m = modes.shape[1]
    with model.kept_state():
        model.reset()
        rest = model.state.x.array.copy()
    volume = cubic(model, ufl.det(model.F) * model.dx, rest, modes)
    if probe is not None:
        _, probes = affine(model, lambda: probe(model.displacement()), rest, modes)
    else:
        probes = np.zeros((0, m))
    fixed = [t for t in problem.operator if t.entry is None]
    by_entry = {t.entry: t.matrix for t in problem.operator if t.entry is not None}
    entries = np.array(sorted(by_entry), dtype=int)
    matrices = [fixed[0].matrix, *(by_entry[e] for e in entries)]
    energy = np.array([gram(modes, apply(K, modes, comm), comm) for K in matrices])
    found = Online(volume, probes, energy, entries)
    _check_energy(model, found, modes)
    return found


def _check_energy(model: Model, found: Online, modes: np.ndarray) -> None:
    """½ zᵀ A(c) z against the model's own ∫ψ dX at a random point of the box and a random z."""
    values = dict(model.parameter_values)
    rng = np.random.default_rng(13)
    z = rng.uniform(-1.0, 1.0, modes.shape[1])
    z = model.geometry.mesh.comm.bcast(z)
    try:
        with model.kept_state():
            model.set_parameters(model.parameters.sample(1, seed=17)[0])
            model.reset()
            model.state.x.array[: modes.shape[0]] += modes @ z
            model.state.x.scatter_forward()
            exact = strain_energy(model)()
            reduced = 0.5 * z @ found.operator(separated.values(model)) @ z
    finally:
        model.set_parameters(values)
    if not abs(reduced - exact) <= ENERGY_CHECK * max(abs(exact), np.finfo(float).tiny):
        raise ParameterError(
            f"PGD: the strain energy is not the quadratic form of the model's Jacobian (off by "
            f"{abs(reduced - exact) / max(abs(exact), np.finfo(float).tiny):.1e}, relative): a load depends on the state"
        )


class PGDModel:
    """The model whose answers are ``decomposition`` evaluated (module docstring): the fem
    ``model`` (for fields, and the values its parameters set), the load path ``stepping``,
    the ``online`` outputs and ``built``, how it was built (for its record). Collective for
    :meth:`fields` only; a solve is evaluation on every rank."""

    def __init__(
        self,
        model: Model,
        decomposition: Decomposition,
        online: Online,
        stepping: Stepping,
        probe_points: Sequence[Sequence[float]] = (),
        built: dict | None = None,
    ) -> None:
        self.model = model
        self.parameters = model.parameters
        self.stepping = stepping
        self.decomposition = decomposition
        self.online = online
        self.ramp = ramp_of(model, stepping)
        self.times = output_times(model, stepping)
        self.probe_points = tuple(tuple(float(c) for c in p) for p in probe_points)
        self.built = dict(built or {})
        self._owned = owned_size(model.space)

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
        wanted = self.times if times is None else checked_times(times, self.stepping)
        model, stepping = self.model, self.stepping
        model.set_parameters(values)
        base = self.decomposition.factors(values)
        slopes = self.decomposition.factor_derivatives(values) if sensitivities else None
        c = separated.values(model)
        start = StartReport("rest", "the unloaded state")
        if on_step is not None:  # the start, as every model shows it first
            model.set_time(stepping.start, load_factor=factor)
            self._show(on_step, "start", stepping.start, np.zeros(self.size), c, None, start)
        rows, states, derived = [], [], []
        previous = stepping.start
        for t in wanted:
            z = self._rho(t, factor) * base
            model.set_time(float(t), load_factor=factor)
            rows.append(self._outputs(z, c))
            states.append(z)
            if slopes is not None:
                derived.append(self._derivatives(z, self._rho(t, factor) * slopes, c))
            if on_step is not None and t > stepping.start:
                report = StepReport(float(t), float(t - previous), 0, (), "evaluated", 0.0, True)
                self._show(on_step, "path", float(t), z, c, report, None)
            previous = float(t)
        return Solution(
            parameters=values,
            times=np.array(wanted, dtype=float),
            outputs=stack(rows),
            states=np.array(states),
            newton_iterations=0,
            seconds=time.perf_counter() - tic,
            sensitivities=stack(derived) if slopes is not None else None,
            parameter_names=self.parameters.names,
            units=dict(UNITS),
            start=start.measured(self.online.volume.c0),  # the rest state's volume
            scale=np.asarray(scale, dtype=float).tolist(),
        )

    def _show(
        self,
        on_step: Callable[[Step], None],
        phase: str,
        t: float,
        z: np.ndarray,
        c: np.ndarray,
        report: StepReport | None,
        start: StartReport | None,
    ) -> None:
        """``on_step`` of the state Q z at ``t`` (the model's loads set at t)."""
        shown = self._outputs(z, c)
        on_step(Step(phase, t, report, lambda: shown, lambda: z.copy(), start=start))

    def _rho(self, t: float, factor: float) -> float:
        """ρ(t) = s r(t) / r(T): the state at t over the decomposition's."""
        return factor * self.ramp(t) / self.ramp(self.stepping.end)

    def _outputs(self, z: np.ndarray, c: np.ndarray) -> dict[str, object]:
        """The outputs of the state Q z, the values c (module docstring)."""
        found: dict[str, object] = {
            "volume": self.online.volume(z),
            "strain_energy": 0.5 * float(z @ self.online.operator(c) @ z),
        }
        if self.probe_points:
            found["probes"] = (self.online.probes @ z).reshape(-1, 3)
        found["loads"] = self.model.scalar_loads()
        return found

    def _derivatives(self, z: np.ndarray, dz: np.ndarray, c: np.ndarray) -> dict[str, object]:
        """d(outputs)/dμ at Q z, dz/dμ = ``dz`` (m × parameters)."""
        derivatives = value_derivatives(self.model)
        dc = np.concatenate(
            [np.reshape(derivatives.constants[k], (-1, dz.shape[1])) for k in separated.constants(self.model)]
        )
        A = self.online.operator(c)
        explicit = [
            0.5 * z @ np.tensordot(dc[self.online.entries, i], self.online.energy[1:], axes=1) @ z
            for i in range(dz.shape[1])
        ]
        found: dict[str, object] = {
            "volume": self.online.volume.gradient(z) @ dz,
            "strain_energy": z @ A @ dz + np.array(explicit),
        }
        if self.probe_points:
            found["probes"] = (self.online.probes @ dz).reshape(-1, 3, dz.shape[1])
        found["loads"] = {label: d.copy() for label, d in derivatives.loads.items()}
        return found

    def fields(self, state: np.ndarray, time: float) -> None:
        """The fem model's state Q ``state`` at ``time`` (collective)."""
        model = self.model
        model.set_time(time, *model.scaling)
        model.reset()
        model.state.x.array[: self._owned] += self.decomposition.modes @ state
        model.state.x.scatter_forward()

    def describe(self) -> dict[str, object]:
        """What answers: the decomposition's size; no solver."""
        d = self.decomposition
        return {"solver": f"PGD evaluation ({d.size} space modes, {d.terms} separated terms)", "linear_solver": None}


def _one_factor(scale: float | Sequence[float], loads: int) -> float:
    """The one load factor a PGD model takes (the same for every load)."""
    factors = np.broadcast_to(np.asarray(scale, dtype=float), (max(loads, 1),))
    if not (np.all(factors == factors[0]) and np.isfinite(factors[0])):
        raise ParameterError(
            f"a PGD model takes one finite load factor for every load (got {np.asarray(scale).tolist()})"
        )
    return float(factors[0])


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
    if not model.parameters.names:
        raise ParameterError("PGD: the model has no parameters to separate: give the scene [parameters]")
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
        probe = Probe(model.geometry.mesh, probe_points) if len(probe_points) else None
        outputs = online(model, problem, decomposition.modes, probe)
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
        "seconds": seconds,
    }
    return PGDModel(model, decomposition, outputs, stepping, probe_points, built), rounds
