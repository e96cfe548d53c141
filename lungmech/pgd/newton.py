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
updates of the terms then take that tangent — a Newton step on the modes' span — and only a
new term's space part takes K̄ (:class:`~lungmech.pgd.sampled.Operator`'s correction). An
iteration adds at most ``Newton.enrich`` terms once some exist, as a Krylov method adds one
direction an iteration: the terms are kept for the directions the true problem needs (left
free, the iterations spent all 40 terms of the balanced lung's budget and then diverged);
a new term's right-hand side is what the updates left on the modes' span. Such iterations
assemble a Jacobian at every point too: on the breath of ``benchmarks/pgd.py``, which needs
none of this, they made a build several times slower for no accuracy, so a model without
such a load keeps the tangent at rest.

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
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, replace

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix

from lungmech import checks, jit
from lungmech.errors import ParameterError
from lungmech.fem.model import Model
from lungmech.fem.parametric import output_times
from lungmech.fem.quantities import Probe, assemble_owned, strain_energy
from lungmech.fem.solver import Stepping
from lungmech.fem.state_dependent import StateDependent
from lungmech.parallel.linalg import apply, gram
from lungmech.parallel.owned import owned_size
from lungmech.pgd import chebyshev
from lungmech.pgd.axes import DEGREE, Axis, full_turn
from lungmech.pgd.decomposition import Decomposition
from lungmech.pgd.fitted import energy_fit
from lungmech.pgd.fitting import FIT
from lungmech.pgd.greedy import Options, Round
from lungmech.pgd.indicator import indicator
from lungmech.pgd.model import ESTIMATE, PGDModel, answerable, load_fractions, ramp_of
from lungmech.pgd.modes import Modes
from lungmech.pgd.online import online
from lungmech.pgd.sampled import Operator, Sample, mean_square, solve
from lungmech.pgd.terms import Terms, constants, kept, separated_terms, values_at
from lungmech.pgd.timeline import SampledTimeline
from lungmech.rom.basis import inner_product

__all__ = ["QUADRATURE", "Newton", "build_nonlinear", "quadrature"]

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
    axes = [
        Axis(parameter, max(intervals, DEGREE + 1) if full_turn(parameter) else intervals)
        for parameter in model.parameters
    ]
    sample = quadrature(model, axes, newton)
    units = sample.units
    points = [model.parameters.from_unit(unit) for unit in units]
    times = output_times(model, stepping)
    comm = model.geometry.mesh.comm
    tic = time.perf_counter()
    # the tangent with the loads 0: the material's (a follower pressure's own may make it indefinite)
    model.set_time(stepping.start)
    tangent = separated_terms(model, axes, linearised=True)
    W: PETSc.Mat | None = None
    seconds = {"terms": time.perf_counter() - tic}
    try:
        W = inner_product(model, "energy")
        tic = time.perf_counter()
        operator = _operator(model, tangent, points, units)  # (at the start, as the terms)
        found = Modes(axes, operator.matrices, owned_size(model.space), comm)
        march = _March(model, points)
        rounds: list[Round] = []
        iteration = _Iteration(march, operator, sample, W, options, newton, bool(model.state_dependent))
        found, blocks, iterations = iteration.marched(found, rounds, stepping)
        seconds["newton"] = time.perf_counter() - tic
        tic = time.perf_counter()
        decomposition, timeline = _joined(found, blocks, times, stepping.start)
        last = Decomposition(tuple(axes), found.Q.copy(), *blocks[-1])
        energies = march.energies(found.Q, blocks, sample, times)
        energy, separated_energy = energy_fit(
            comm, energies, units, [tuple(axes)], FIT, newton.seed, stepping.start, times
        )
        seconds["energy"] = time.perf_counter() - tic
        tic = time.perf_counter()
        model.set_time(stepping.end)
        estimates = indicator(model, last, W, model.parameters.sample(ESTIMATE, seed=31))
        seconds["indicator"] = time.perf_counter() - tic
    finally:
        tangent.destroy()
        if W is not None:
            W.destroy()
    tic = time.perf_counter()
    probe = Probe(model.geometry.mesh, probe_points) if len(probe_points) else None
    outputs = online(model, None, decomposition.modes, probe)
    seconds["outputs"] = time.perf_counter() - tic
    built = {
        "method": f"a priori, Newton on {len(units)} points of the box"
        + (", the tangents at their states" if model.state_dependent else ""),
        "intervals": [axis.intervals for axis in axes],
        "options": asdict(options),
        "newton": asdict(newton),
        "newton_iterations": iterations,
        "quadrature": len(units),  # the residual's points an iteration
        "training": points,  # the residuals' points (a trade's validation points avoid them)
        "rounds": [asdict(r) for r in rounds],
        "operator_terms": len(tangent.operator),
        "energy_held_out": energy.held_out,
        "estimate": float(estimates.max()),
        "indicator_points": estimates.tolist(),
        "seconds": seconds,
    }
    found_model = PGDModel(
        model, decomposition, outputs, stepping, probe_points, built, timeline=timeline, energy=separated_energy
    )
    return found_model, rounds


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

    march: _March
    operator: Operator
    sample: Sample
    W: PETSc.Mat
    options: Options
    newton: Newton
    at_states: bool = False

    def marched(
        self, found: Modes, rounds: list[Round], stepping: Stepping
    ) -> tuple[Modes, list[tuple[np.ndarray, list[np.ndarray]]], list[int]]:
        """The path followed output time after output time (module docstring), a step halved
        where its iterations fail: the terms at the end, each output time's (R, X) and its
        iterations. Refused in one line where a step of :data:`SMALLEST` of the path fails.
        Collective."""
        times = output_times(self.march.model, stepping)
        blocks: list[tuple[np.ndarray, list[np.ndarray]]] = []
        iterations: list[int] = []
        pending, reached = [float(t) for t in times], float(stepping.start)
        while pending:
            t = pending[0]
            self.march.model.set_time(t)
            saved, tried = found.copy(), len(rounds)
            done, steps = self.converged(found, rounds)
            if not done and t - reached > SMALLEST * (stepping.end - stepping.start):
                found = saved
                del rounds[tried:]  # (the failed attempt's)
                pending.insert(0, 0.5 * (reached + t))
                continue
            if not done:
                self._refuse(t, reached, steps, found)
            pending.pop(0)
            reached = t
            if np.any(np.isclose(times, t, rtol=0.0, atol=1e-12 * max(1.0, abs(t)))):
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
            most = None if tangents is None else self.newton.enrich
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

    def _refuse(self, t: float, reached: float, steps: list[float], found: Modes) -> None:
        """The one line of a time whose step, halved to its smallest, still fails."""
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
        raise ParameterError(
            f"PGD: the Newton–PGD did not converge at t = {t:g} s in {len(steps)} iterations ({how}), "
            f"its step from {reached:g} s halved to {t - reached:g} s: {why}"
            "give --samples for a PGD fitted to full solves"
        )


class _March:
    """The model's residual, its tangent on the modes' span and its strain energy at the
    sample's ``points``, its state the rest plus a given displacement of its modes' space (a
    state-dependent load's coefficients θ = Θ(u) set from that state)."""

    def __init__(self, model: Model, points: Sequence[Mapping[str, float]]) -> None:
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
            self.rest = model.state.x.array[: self.owned].copy()

    def _at(self, point: Mapping[str, float], u: np.ndarray) -> None:
        model = self.model
        model.set_parameters(point)
        model.state.x.array[: self.owned] = self.rest + u
        model.state.x.scatter_forward()
        self._coupled.update()

    def residuals(self, U: np.ndarray, Q: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """R(u_rest + U_q; μ_q) at the model's current time (owned entries × N, 0 where imposed)
        and, given space modes ``Q``, the tangent there on their span, Qᵀ J_q Q (N × m × m; J_q
        with a state-dependent load's coupling U Vᵀ, :mod:`lungmech.fem.state_dependent`)."""
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

    def energies(
        self, Q: np.ndarray, blocks: Sequence[tuple[np.ndarray, list[np.ndarray]]], sample: Sample, times: np.ndarray
    ) -> np.ndarray:
        """The strain energy (J) at each point and output time of the blocks' states (N × times)."""
        energy = strain_energy(self.model)
        found = np.empty((len(self.points), len(times)))
        with kept(self.model, self._held):
            for i, ((R, X), t) in enumerate(zip(blocks, times)):
                self.model.set_time(float(t))
                Lam = np.multiply.reduce([Xj @ B.T for Xj, B in zip(X, sample.bases)], axis=0)
                U = Q[:, : len(R)] @ (R @ Lam)
                for q, point in enumerate(self.points):
                    self._at(point, U[:, q])
                    found[q, i] = energy()
        return found


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


def _joined(
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
