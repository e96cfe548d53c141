"""The a priori PGD of a nonlinear model — a hyperelastic law, a follower pressure — by Newton
linearisation over the box: residual assemblies at a quadrature's points, no full solve.

Its residual R(u; μ) is known only where it is assembled, so the box's integral of the
Galerkin PGD, ∫_B ⟨R(u(μ); μ), δu(μ)⟩ dμ = 0, is taken by a quadrature μ_q, w_q
(:func:`quadrature`): the tensor product of the axes' Gauss rules — exact for products of the
splines, as the linear greedy's integrals are — or, where it has more points than
``Newton.quadrature``, that many Sobol' points with equal weights. Each iteration assembles the
residual at the current terms' state there, r_q = R(u(μ_q); μ_q), and finds the next terms as
the sampled Galerkin PGD (:mod:`lungmech.pgd.sampled`) of

    K̄(μ) u⁺(μ) = K̄(μ) u(μ) − R(u(μ); μ),

K̄(μ) the residual's tangent at rest — separated from the model's own forms like a linear
model's operator (:func:`~lungmech.pgd.terms.separated_terms`, ``linearised``), one
factorisation a new term's space step: a modified Newton whose fixed point is the sampled
Galerkin PGD of R itself, whatever K̄. The first iteration from rest is the linear PGD of the
tangent problem; each next starts from the last one's terms (updated, then enriched while a new
term matters).

A load that depends on the state (balanced gravity: its coefficients θ = Θ(u), set from each
point's state before its residual) moves the tangent with the state, and no tangent held over
the box converges there (``benchmarks/pgd_tangent.py``). Its iterations assemble, beside each
point's residual, its tangent at that point's state on the span of the space modes Q,
Qᵀ J_q Q (J_q with the load's coupling U Vᵀ, :mod:`lungmech.fem.state_dependent`): the
updates of the terms then take that tangent — a Newton step on the modes' span, its sampled
residual there minimised by alternating least squares (the tangents are not symmetric: the
Galerkin updates diverged) — and only a new term's space part takes K̄
(:class:`~lungmech.pgd.sampled.Operator`'s correction). An
iteration adds at most ``Newton.enrich`` terms, the first one too, as a Krylov method adds one
direction an iteration: the terms are kept for the directions the true problem needs (left
free, the iterations spent all 40 terms of the balanced lung's budget and then diverged; the
first iteration's linear PGD of K̄ alone, left free, took terms that left the imaged lung of
``tests/test_pgd_imaged.py`` at 5e-3 at 20 terms, against 2e-3 capped);
a new term's right-hand side is what the updates left on the modes' span. Such iterations
assemble a Jacobian at every point too: on the breath of ``benchmarks/pgd.py``, which needs
none of this, they made a build several times slower for no accuracy, so a model without
such a load keeps the tangent at rest.

Where the points start elsewhere than at rest (an imaged body's breath: each from the image on
its reference ξ(μ_q), :mod:`lungmech.pgd.imaged_newton`), K̄ is linearised at that start at
the box's centre, its loads 0: the material's tangent at the prestressed image. The rest's —
the image taken as unstressed — left an error of 3 % at the same 20 terms, and capped, its
iterations diverged.

The path is followed output time after output time, each time's iterations
starting from the last time's terms, until the terms change by less than ``tolerance`` of
themselves in the quadrature's mean energy norm. A time whose iterations fail — a residual
not finite, or :data:`STALLED` iterations that stopped coming closer — is approached again
from the last time reached, its step halved, down to :data:`SMALLEST` of the path (a
continuation, as a full solve's cut-back).

The answer at output time tᵢ is its own terms' (Q shared): u(μ, tᵢ) = Q Rᵢ qᵢ(μ), kept as one
decomposition whose terms each belong to one time (their timeline 1 there, 0 at the others;
:class:`~lungmech.pgd.timeline.SampledTimeline`). The strain energy, no quadratic form of a
nonlinear state, is assembled at the sample's states and fitted by separated terms on the
state's own splines (:func:`~lungmech.pgd.fitted.energy_fit`; finer ones would follow the
grid's points and wander between them), as a fitted PGD's is from its full solves.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, replace

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np

from lungmech import checks
from lungmech.errors import ParameterError
from lungmech.fem.model import Model
from lungmech.fem.parametric import output_times
from lungmech.fem.quantities import Probe
from lungmech.fem.solver import Stepping
from lungmech.parallel.owned import owned_size
from lungmech.pgd import chebyshev
from lungmech.pgd.axes import DEGREE, Axis, full_turn
from lungmech.pgd.decomposition import Decomposition
from lungmech.pgd.fitted import energy_fit
from lungmech.pgd.fitting import FIT
from lungmech.pgd.greedy import Options, Round
from lungmech.pgd.indicator import indicator
from lungmech.pgd.march import March, Start
from lungmech.pgd.model import ESTIMATE, PGDModel, answerable, load_fractions, ramp_of
from lungmech.pgd.modes import Modes
from lungmech.pgd.online import online
from lungmech.pgd.sampled import Operator, Sample, mean_square, solve
from lungmech.pgd.terms import Terms, constants, kept, separated_terms, values_at
from lungmech.pgd.timeline import SampledTimeline
from lungmech.rom.basis import inner_product

__all__ = [
    "QUADRATURE",
    "Marched",
    "Newton",
    "Path",
    "axes_of",
    "build_nonlinear",
    "joined",
    "newton_pgd",
    "quadrature",
    "states",
]

QUADRATURE = 512  # the most residual assemblies an iteration, by default
STALLED = 20  # iterations after which a Newton–PGD that stopped coming closer gives up
SMALLEST = 1 / 16  # a failed step is halved down to this fraction of the path, no further
INTERVALS = 2  # the splines' intervals by default: 8 Gauss points an axis
ENRICH = 3  # with the tangents at the points' states, the most terms an iteration adds (once some exist)


@dataclass(frozen=True)
class Newton:
    """The Newton–PGD's ``quadrature``: the most residual assemblies an iteration — the axes'
    tensor Gauss grid where it has no more points, else that many Sobol' points (``seed``);
    the terms' relative change at which an output time has converged (``tolerance``) and the
    ``iterations`` it may take; with the tangents at the points' states (a load that depends
    on the state), the most terms an iteration adds to those it starts from (``enrich``)."""

    quadrature: int = QUADRATURE
    seed: int = 0
    tolerance: float = 1e-5
    iterations: int = 60
    enrich: int = ENRICH

    def __post_init__(self) -> None:
        checks.integer("PGD quadrature", self.quadrature, minimum=8)
        checks.integer("PGD seed", self.seed, minimum=0)
        checks.real("PGD Newton tolerance", self.tolerance, positive=True)
        checks.integer("PGD Newton iterations", self.iterations, minimum=1)
        checks.integer("PGD Newton enrichment", self.enrich, minimum=1)


def build_nonlinear(
    model: Model,
    stepping: Stepping,
    probe_points: Sequence[Sequence[float]] = (),
    intervals: int = INTERVALS,
    options: Options | None = None,
    newton: Newton = Newton(),
) -> tuple[PGDModel, list[Round]]:
    """The a priori :class:`PGDModel` of a nonlinear ``model`` over its parameters' box along
    ``stepping`` (module docstring): splines on ``intervals`` intervals, the greedy's
    ``options`` at every iteration, ``newton``'s sample and stopping; with every round of the
    greedy. Refused in one line before any work where it cannot answer (no parameter, loads on
    several ramps), and where the iterations do not converge.
    Collective."""
    answerable(model)
    ramp_of(model, stepping)
    load_fractions(model, stepping)
    options = options or Options()
    axes = axes_of(model, intervals)
    sample = quadrature(model, axes, newton)
    times = output_times(model, stepping)
    comm = model.geometry.mesh.comm
    W = inner_product(model, "energy")
    try:
        model.set_time(stepping.start)  # the tangent with the loads 0 (module docstring)
        path = Path(float(stepping.start), times, model.set_time)
        marched = newton_pgd(model, sample, path, options, newton, W, at_states=bool(model.state_dependent))
        found, blocks, seconds = marched.found, marched.blocks, marched.seconds
        tic = time.perf_counter()
        decomposition, timeline = joined(found, blocks, times, stepping.start)
        energies = marched.march.energies(states(found.Q, blocks, sample), times)
        energy, separated_energy = energy_fit(
            comm, energies, sample.units, [tuple(axes)], FIT, newton.seed, stepping.start, times
        )
        seconds["energy"] = time.perf_counter() - tic
        tic = time.perf_counter()
        model.set_time(stepping.end)
        last = Decomposition(tuple(axes), found.Q.copy(), *blocks[-1])
        estimates = indicator(model, last, W, model.parameters.sample(ESTIMATE, seed=31))
        seconds["indicator"] = time.perf_counter() - tic
    finally:
        W.destroy()
    tic = time.perf_counter()
    probe = Probe(model.geometry.mesh, probe_points) if len(probe_points) else None
    outputs = online(model, None, decomposition.modes, probe)
    seconds["outputs"] = time.perf_counter() - tic
    built = marched.record(options, newton) | {
        "energy_held_out": energy.held_out,
        "estimate": float(estimates.max()),
        "indicator_points": estimates.tolist(),
        "seconds": seconds,
    }
    found_model = PGDModel(
        model, decomposition, outputs, stepping, probe_points, built, timeline=timeline, energy=separated_energy
    )
    return found_model, marched.rounds


def axes_of(model: Model, intervals: int) -> list[Axis]:
    """One axis per parameter of ``model``: cubic splines on ``intervals`` intervals (a full
    turn on at least :data:`~lungmech.pgd.axes.DEGREE` + 1, periodic)."""
    return [
        Axis(parameter, max(intervals, DEGREE + 1) if full_turn(parameter) else intervals)
        for parameter in model.parameters
    ]


@dataclass(frozen=True)
class Path:
    """The loads' path a Newton–PGD follows: from ``start`` through each of ``targets`` in turn
    (the output times), ``drive`` setting the model's loads at a point of it (its time) and
    ``describe`` saying where that is, for a message."""

    start: float
    targets: np.ndarray
    drive: Callable[[float], None]
    describe: Callable[[float], str] = lambda t: f"t = {t:g} s"


@dataclass
class Marched:
    """A Newton–PGD's result: the terms at the path's end ``found``, each target's (R, X)
    ``blocks`` and ``iterations``, every round of the greedy, the ``march`` that assembled its
    residuals (for the energies at its points), its method's words, the tangent's number of
    operator terms and the ``seconds`` each part took."""

    found: Modes
    blocks: list[tuple[np.ndarray, list[np.ndarray]]]
    iterations: list[int]
    rounds: list[Round]
    march: March
    method: str
    operator_terms: int
    seconds: dict[str, float]

    def record(self, options: Options, newton: Newton) -> dict:
        """How it was built, for a model's ``built``."""
        return {
            "method": self.method,
            "intervals": [axis.intervals for axis in self.found.axes],
            "options": asdict(options),
            "newton": asdict(newton),
            "newton_iterations": self.iterations,
            "quadrature": len(self.march.points),  # the residual's points an iteration
            "training": self.march.points,  # the residuals' points (a trade's validation points avoid them)
            "rounds": [asdict(r) for r in self.rounds],
            "operator_terms": self.operator_terms,
        }


def newton_pgd(
    model: Model,
    sample: Sample,
    path: Path,
    options: Options,
    newton: Newton,
    W: PETSc.Mat,
    *,
    at_states: bool,
    start: Start | None = None,
) -> Marched:
    """The Newton–PGD of ``model``'s residual at the ``sample``'s points along ``path``, its
    states ``start``'s plus the terms' (default: from rest), the terms W-orthonormal, the updates
    taking the tangents at the points' states where ``at_states`` (module docstring). The model's
    tangent at rest is separated as its loads are now (0: the material's). Refused in one line
    where the iterations do not converge. Collective."""
    axes, comm = list(sample.axes), model.geometry.mesh.comm
    points = [model.parameters.from_unit(unit) for unit in sample.units]
    tic = time.perf_counter()
    tangent = separated_terms(model, axes, linearised=True, at=_centre(model, start))
    seconds = {"terms": time.perf_counter() - tic}
    try:
        tic = time.perf_counter()
        operator = _operator(model, tangent, points, sample.units)  # (at the start, as the terms)
        found = Modes(axes, operator.matrices, owned_size(model.space), comm)
        march = March(model, points, start)
        rounds: list[Round] = []
        iteration = _Iteration(march, operator, sample, W, options, newton, at_states)
        found, blocks, iterations = iteration.marched(found, rounds, path)
        seconds["newton"] = time.perf_counter() - tic
    finally:
        tangent.destroy()
    method = f"a priori, Newton on {len(points)} points of the box" + (
        ", the tangents at their states" if at_states else ""
    )
    return Marched(found, blocks, iterations, rounds, march, method, len(tangent.operator), seconds)


def _centre(model: Model, start: Start | None) -> np.ndarray | None:
    """``start``'s state at the box's centre (local entries, ghosts too; its other settings left
    in the model), where the tangent a new term's space part takes is linearised; None: the rest."""
    if start is None:
        return None
    centre = model.parameters.from_unit(np.full(len(model.parameters.names), 0.5))
    owned = owned_size(model.space)
    with model.kept_state():
        model.state.x.array[:owned] = start(centre)
        model.state.x.scatter_forward()
        return model.state.x.array.copy()


def states(Q: np.ndarray, blocks: Sequence[tuple[np.ndarray, list[np.ndarray]]], sample: Sample) -> list[np.ndarray]:
    """Each block's displacement at the sample's points, Q R (Πⱼ Xⱼ Bⱼᵀ) (owned entries × N)."""
    found = []
    for R, X in blocks:
        products = np.multiply.reduce([Xj @ B.T for Xj, B in zip(X, sample.bases)], axis=0)
        found.append(Q[:, : len(R)] @ (R @ products))
    return found


def quadrature(model: Model, axes: Sequence[Axis], newton: Newton) -> Sample:
    """The box's quadrature (module docstring): the axes' tensor Gauss grid, or where it has more
    than ``newton.quadrature`` points, that many of the model's Sobol' points (``newton.seed``)."""
    grid = Sample.tensor(axes)
    if len(grid.units) <= newton.quadrature:
        return grid
    points = model.parameters.sample(newton.quadrature, seed=newton.seed)
    sample = Sample.of(axes, np.array([model.parameters.to_unit(point) for point in points]))
    for axis, B in zip(axes, sample.bases):
        if np.linalg.matrix_rank(B) < axis.size:  # some spline's coefficient would be the ridge's choice
            raise ParameterError(
                f"PGD: {newton.quadrature} Sobol' points do not determine the {axis.size} splines of axis "
                f"{axis.parameter.name!r} ({axis.intervals} intervals): raise --quadrature or lower --intervals"
            )
    return sample


@dataclass(frozen=True)
class _Iteration:
    """What every Newton–PGD iteration works with: the residual's ``march``, the tangent
    ``operator`` at the ``sample``'s points, the energy product ``W``, the greedy's ``options``
    and ``newton``'s stopping and enrichment; ``at_states``: the updates take each point's
    tangent at its state on the modes' span (module docstring)."""

    march: March
    operator: Operator
    sample: Sample
    W: PETSc.Mat
    options: Options
    newton: Newton
    at_states: bool = False

    def marched(
        self, found: Modes, rounds: list[Round], path: Path
    ) -> tuple[Modes, list[tuple[np.ndarray, list[np.ndarray]]], list[int]]:
        """``path`` followed target after target (module docstring), a step halved where its
        iterations fail: the terms at the end, each target's (R, X) and its iterations.
        Refused in one line where a step of :data:`SMALLEST` of the path fails. Collective."""
        targets = path.targets
        length = float(targets[-1]) - path.start
        blocks: list[tuple[np.ndarray, list[np.ndarray]]] = []
        iterations: list[int] = []
        pending, reached = [float(t) for t in targets], path.start
        while pending:
            t = pending[0]
            path.drive(t)
            saved, tried = found.copy(), len(rounds)
            done, steps = self.converged(found, rounds)
            if not done and t - reached > SMALLEST * length:
                found = saved
                del rounds[tried:]  # (the failed attempt's)
                pending.insert(0, 0.5 * (reached + t))
                continue
            if not done:
                self._refuse(path, t, reached, steps, found)
            pending.pop(0)
            reached = t
            if np.any(np.isclose(targets, t, rtol=0.0, atol=1e-12 * max(1.0, abs(t)))):
                iterations.append(len(steps))
                blocks.append((found.R.copy(), [X.copy() for X in found.X]))
        return found, blocks, iterations

    def converged(self, found: Modes, rounds: list[Round]) -> tuple[bool, list[float]]:
        """Newton–PGD iterations at the model's current time until the terms change by less
        than ``newton.tolerance`` of themselves, or stop coming closer (after :data:`STALLED`
        iterations, the last few's smallest change not below half the earlier ones'); (converged,
        each iteration's change)."""
        sample, operator = self.sample, self.operator
        steps: list[float] = []
        for _ in range(self.newton.iterations):
            Z = found.R @ sample.products(found)  # the state's coordinates at the points (m × N)
            on_span = found.Q if self.at_states and found.count else None
            r, tangents = self.march.residuals(found.Q @ Z, on_span)
            finite = np.isfinite(r).all() and (tangents is None or np.isfinite(tangents).all())
            if not found.comm.allreduce(bool(finite), op=MPI.LAND):  # a state beyond the law's range
                return False, [*steps, np.inf]
            b = operator.apply_sampled(found, Z) - r
            step = operator if tangents is None else self._at_states(tangents, found, Z)
            most = self.newton.enrich if self.at_states else None  # (module docstring)
            rounds.extend(solve(step, sample, b, found, self.W, self.options, most))
            now = found.R @ sample.products(found)
            before = np.vstack([Z, np.zeros((len(now) - len(Z), Z.shape[1]))])
            size = mean_square(sample, found)
            steps.append(float(np.sqrt((sample.weights @ np.sum((now - before) ** 2, axis=0)) / size)) if size else 0.0)
            if steps[-1] <= self.newton.tolerance:
                return True, steps
            recent = STALLED // 2
            if not np.isfinite(steps[-1]) or (
                len(steps) >= STALLED and min(steps[-recent:]) > 0.5 * min(steps[:-recent])
            ):
                return False, steps
        return False, steps

    def _at_states(self, tangents: np.ndarray, found: Modes, Z: np.ndarray) -> Operator:
        """The operator whose updates take each point's tangent Qᵀ J_q Q on the span of Q
        (:class:`~lungmech.pgd.sampled.Operator`'s correction D_q = Qᵀ J_q Q − Qᵀ K̄(μ_q) Q)."""
        rest = np.einsum("iq,iab->qab", self.operator.kappa, np.array(found.reduced_operators()))
        correction = tangents - rest
        return replace(self.operator, correction=correction, shift=np.einsum("qab,bq->aq", correction, Z))

    def _refuse(self, path: Path, t: float, reached: float, steps: list[float], found: Modes) -> None:
        """The one line of a target whose step, halved to its smallest, still fails."""
        how = (
            f"the terms still changed by {steps[-1]:.1e} of themselves"
            if np.isfinite(steps[-1])
            else "its residual was not finite: a state beyond the law's range"
        )
        far = (
            "the tangents at the points' states did not bring the terms to rest; "
            if self.at_states
            else "the loads take the body too far from its tangent at rest (large rotations, say); "
        )
        why = (
            f"all {self.options.max_terms} terms (--modes) in use: raise it, or "
            if found.count >= self.options.max_terms and np.isfinite(steps[-1])
            else far
        )
        fraction = (t - reached) / (float(path.targets[-1]) - path.start)
        raise ParameterError(
            f"PGD: the Newton–PGD did not converge at {path.describe(t)} in {len(steps)} iterations ({how}), "
            f"its step from {path.describe(reached)} halved to {fraction:.3g} of the path: {why}"
            "give --samples for a PGD fitted to full solves"
        )


def _operator(model: Model, tangent: Terms, points: Sequence[Mapping[str, float]], units: np.ndarray) -> Operator:
    """The tangent at rest at the points: each distinct matrix of ``tangent`` once, its factor
    the value it multiplies (1 for K₀) times its Chebyshev factors on the curves' axes."""
    held = constants(model)
    with kept(model, held):
        values = np.array([values_at(model, held, dict(point)) for point in points])
    on = [curve.axis for curve in tangent.curves]
    counts = [curve.degrees for curve in tangent.curves]
    series = np.array([chebyshev.tensor(units[q, on].tolist(), counts) for q in range(len(points))])
    matrices, kappa, seen = [], [], set()
    for term in tangent.operator:
        if id(term.matrix) in seen:  # a value's several separated parts share its matrix
            continue
        seen.add(id(term.matrix))
        matrices.append(term.matrix)
        base = np.ones(len(points)) if term.entry is None else values[:, term.entry]
        kappa.append(base * series[:, term.degree])
    return Operator(matrices, np.array(kappa), tangent.symmetric)


def joined(
    found: Modes, blocks: Sequence[tuple[np.ndarray, list[np.ndarray]]], times: np.ndarray, start: float
) -> tuple[Decomposition, SampledTimeline]:
    """One decomposition of every time's terms (Q the last one's; an earlier time's R padded
    with zero rows), each term on at its own time alone."""
    m = found.Q.shape[1]
    reduced = np.hstack([np.vstack([R, np.zeros((m - len(R), R.shape[1]))]) for R, _ in blocks])
    coefficients = [np.vstack([X[j] for _, X in blocks]) for j in range(len(found.axes))]
    owner = np.concatenate([np.full(R.shape[1], i) for i, (R, _) in enumerate(blocks)])
    values = (owner[:, None] == np.arange(len(times))[None, :]).astype(float)
    return Decomposition(found.axes, found.Q.copy(), reduced, coefficients), SampledTimeline(start, times, values)
