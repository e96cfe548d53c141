"""The a posteriori PGD: a PGD model fitted to full solves, for any model a full solve answers —
nonlinear laws, follower pressures, loads that depend on the state.

The seminar's PGD is a priori (:mod:`lungmech.pgd.greedy`): no full solve, but its separated
forms need a residual affine in the state. Here the full model is solved at N points μₛ of the
box (a Sobol' sample, on any ensemble: :mod:`lungmech.parallel.ensemble`), and its states
uₛ(tᵢ) − u_rest at the nt output times are fitted by separated terms:

    u(μ, tᵢ) ≈ Σₖ ūₖ qₖ(μ) τₖ(tᵢ),   qₖ(μ) = Πⱼ λₖʲ(μⱼ),

closest in the energy norm of W (:func:`lungmech.rom.basis.inner_product`) summed over the
samples (:mod:`lungmech.pgd.fitting`). The states are first written in their POD basis Φ
(W-orthonormal, :func:`lungmech.parallel.linalg.pod`): the best ūₖ lie in the span of the
data, so the whole fit is a dense problem of the POD coordinates, solved alike on every rank
(rank 0's, broadcast). The terms' space parts a ∈ ℝʳ become space modes by an SVD, A = U S Vᵀ:
Q = Φ U (W-orthonormal), R = S Vᵀ. The strain energy, no quadratic form of a nonlinear
model's state, is fitted the same way from the full solves' own (J).

A :class:`~lungmech.pgd.model.PGDModel` then answers ``solve(μ)`` as the a priori one does, its
terms moving along the path by their fitted τₖ (:class:`~lungmech.pgd.timeline.SampledTimeline`),
each scalar load at r(t)/r(T) of its value at the path's end (its own ramp r). On an imaged
body the breath is fitted from t₀ on, and the body's reference ξ(μ) beside it
(:mod:`lungmech.pgd.imaged`).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict

from mpi4py import MPI

import numpy as np

from lungmech import checks
from lungmech.errors import ParameterError
from lungmech.fem.inverse_motion import InverseMotion
from lungmech.fem.model import Model
from lungmech.fem.parameters import Parameters
from lungmech.fem.parametric import FullOrderModel, output_times
from lungmech.fem.quantities import Probe
from lungmech.fem.solver import Stepping
from lungmech.parallel import linalg
from lungmech.parallel.owned import owned_size
from lungmech.pgd import imaged as imaged_pgd
from lungmech.pgd.axes import DEGREE, Axis, full_turn
from lungmech.pgd.decomposition import Decomposition
from lungmech.pgd.fitting import FIT, Fit, fit
from lungmech.pgd.greedy import Options
from lungmech.pgd.model import PGDModel, answerable, load_fractions
from lungmech.pgd.online import online
from lungmech.pgd.timeline import SampledTimeline
from lungmech.rom.basis import inner_product, zero_imposed
from lungmech.rom.load_paths import Paths, relative_to, serial

__all__ = ["INTERVALS", "SINGULAR", "energy_fit", "fitted"]

SINGULAR = 1e-12  # the terms' space parts: directions below this fraction of the largest are dropped
INTERVALS = (1, 2, 4, 8)  # the splines' intervals a fit chooses from, on held-out samples


def fitted(
    full: FullOrderModel,
    samples: int,
    intervals: int | None = None,
    options: Options | None = None,
    probe_points: Sequence[Sequence[float]] = (),
    seed: int = 0,
    paths: Paths | None = None,
    fixed: Mapping[str, float] | None = None,
) -> tuple[PGDModel, dict[str, Fit]]:
    """The PGD model of ``full`` fitted to its solves at ``samples`` Sobol' points of the box
    (``seed``; the parameters of ``fixed`` held at those values), each parameter's modes cubic
    splines on ``intervals`` intervals (default: the choice of :data:`INTERVALS` best on
    held-out samples; a periodic axis takes at least 4) (module docstring); with the fits of the
    state, of the strain energy (their held-out errors against the number of terms) and, on an
    imaged body, of its reference ξ(μ) (:mod:`lungmech.pgd.imaged`). ``paths`` solves the full
    load paths (default: one after another on ``full``). Refused in one line before any solve
    where it cannot answer: no parameter, loads not at rest at the start (but on an imaged body), a scalar load
    0 at the path's end. Collective."""
    model, stepping = full.model, full.stepping
    answerable(model)
    imaged = isinstance(full.start, InverseMotion)
    if not imaged:
        _from_rest(model, stepping)
    load_fractions(model, stepping)
    checks.integer("PGD samples", samples, minimum=8)
    box = model.parameters
    held = box.values(fixed or {})  # (unknown names refused)
    held = {name: held[name] for name in fixed or {}}
    candidates = _choices(box, INTERVALS if intervals is None else (intervals,))
    options = options or FIT
    comm = model.geometry.mesh.comm
    tic = time.perf_counter()
    points = [box.values(dict(point) | held) for point in box.sample(samples, seed)]
    start = relative_to(full)
    solved = (paths or serial(full, start))([(point, 1.0) for point in points], False)
    full.reset()
    seconds = {"full_solves": time.perf_counter() - tic}
    tic = time.perf_counter()
    times = output_times(model, stepping)
    for path in solved:
        if not np.allclose(path.solution.times, times, rtol=0.0, atol=1e-12 * max(1.0, abs(stepping.end))):
            raise ParameterError("PGD: a full solve reported other output times than the model's (a lungmech error)")
    owned = owned_size(model.space)
    states = [list(path.solution.states) for path in solved]
    energies = np.array([path.solution.outputs["strain_energy"] for path in solved])  # N × nt (J)
    if imaged:  # from t₀ on: the image, its other fields x_ξ(μ)'s (they move with μ), and its energy
        with model.kept_state():
            model.reset()
            start = model.state.x.array.copy()
        times = np.concatenate([[stepping.start], times])
        states = [[x0, *path] for x0, path in zip(imaged_pgd.image_states(full, solved).T, states)]
        energies = np.column_stack([imaged_pgd.start_energies(full, solved), energies])
    data = np.column_stack([state[:owned] - start[:owned] for path in states for state in path])
    units = np.array([box.to_unit(point) for point in points])
    decomposition, state = _separated(model, data, samples, units, candidates, options, seed)
    energy, separated_energy = energy_fit(comm, energies, units, candidates, options, seed, stepping.start, times)
    fits = {"state": state, "strain_energy": energy}
    reference = None
    if imaged:
        assert isinstance(full.start, InverseMotion)
        inverse = full.start.inverse
        with inverse.kept_state():
            inverse.reset()
            rest = inverse.state.x.array[: owned_size(inverse.space)].copy()
        xi = np.column_stack([path.inverse - rest for path in solved if path.inverse is not None])
        found_xi, fits["reference"] = _separated(inverse, xi, samples, units, candidates, options, seed)
    seconds["fit"] = time.perf_counter() - tic
    tic = time.perf_counter()
    probe = Probe(model.geometry.mesh, probe_points) if len(probe_points) else None
    outputs = online(model, None, decomposition.modes, probe)
    if imaged:
        reference = imaged_pgd.reference(full, found_xi, probe)
    seconds["outputs"] = time.perf_counter() - tic
    built = {
        "method": "fitted to full solves",
        "samples": samples,
        "seed": seed,
        "training": points,  # the full solves' points (a trade's validation points avoid them)
        "fixed": held,
        "intervals": [axis.intervals for axis in state.axes],
        "energy_intervals": [axis.intervals for axis in energy.axes],
        "options": asdict(options),
        "held_out": state.held_out,
        "held_out_by_intervals": state.curves,
        "training_error": state.training,
        "energy_held_out": energy.held_out,
        "estimate": state.held_out[state.separated.terms - 1],  # every answer's indicator
        "seconds": seconds,
    }
    if reference is not None:
        built["reference_held_out"] = fits["reference"].held_out
        built["reference_intervals"] = [axis.intervals for axis in fits["reference"].axes]
    found = PGDModel(
        model,
        decomposition,
        outputs,
        stepping,
        probe_points,
        built,
        timeline=SampledTimeline(stepping.start, times, state.separated.timeline),
        energy=separated_energy,
        reference=reference,
    )
    return found, fits


def energy_fit(
    comm: MPI.Comm,
    energies: np.ndarray,
    units: np.ndarray,
    choices: Sequence[Sequence[Axis]],
    options: Options,
    seed: int,
    start: float,
    times: np.ndarray,
) -> tuple[Fit, tuple[Decomposition, SampledTimeline]]:
    """The strain energy's separated fit (:func:`~lungmech.pgd.fitting.fit`) to its values
    ``energies`` (J, N points × output ``times``; rank 0's) at the points' ``units``: the fit,
    and as a PGD model holds it, a one-mode decomposition and its timeline. Collective."""
    found = fit(comm.bcast(energies[None] if comm.rank == 0 else None), units, choices, options, seed)  # 1 × N × nt
    separated = Decomposition(found.axes, np.ones((1, 1)), found.separated.amplitudes, found.separated.coefficients)
    return found, (separated, SampledTimeline(start, times, found.separated.timeline))


def _separated(
    model: Model,
    data: np.ndarray,
    samples: int,
    units: np.ndarray,
    choices: Sequence[Sequence[Axis]],
    options: Options,
    seed: int,
) -> tuple[Decomposition, Fit]:
    """The decomposition fitted to ``data`` (owned rows of ``model``'s state, samples × times
    columns, sample by sample): their POD in the energy norm (W-orthonormal), its coordinates
    fitted by separated terms (:func:`~lungmech.pgd.fitting.fit`), the terms' space parts made
    space modes by an SVD (module docstring); their timeline is the fit's. Collective."""
    comm = model.geometry.mesh.comm
    W = inner_product(model, "energy")
    try:
        basis = linalg.pod(zero_imposed(model, data), W, comm)
    finally:
        W.destroy()
    r, nt = basis.modes.shape[1], data.shape[1] // samples
    coordinates = comm.bcast(basis.coefficients.T.reshape(r, samples, nt) if comm.rank == 0 else None)
    found = fit(coordinates, units, choices, options, seed)
    amplitudes = found.separated.amplitudes * (found.separated.timeline[:, 0] if nt == 1 else 1.0)  # one time: folded
    U, S, Vt = np.linalg.svd(amplitudes, full_matrices=False)
    keep = S > SINGULAR * S[0] if S.size and S[0] > 0 else np.zeros(len(S), bool)
    decomposition = Decomposition(
        found.axes, basis.modes @ U[:, keep], S[keep, None] * Vt[keep], found.separated.coefficients
    )
    return decomposition, found


def _from_rest(model: Model, stepping: Stepping) -> None:
    """Refuse in one line a path whose loads are not 0 at its start: a fitted PGD's state is 0
    there, unless the body is imaged (its start is then fitted too)."""
    for load in model.loads:
        if load.ramp(stepping.start) != 0.0:
            label = getattr(load, "label", type(load).__name__)
            raise ParameterError(
                f"PGD: load '{label}' is {load.ramp(stepping.start):g}, not 0, at the path's start "
                f"(t = {stepping.start:g} s): a fitted PGD's path starts at rest, or on an imaged body ([inverse])"
            )


def _choices(parameters: Parameters, intervals: Sequence[int]) -> list[tuple[Axis, ...]]:
    """The parameters' axes at each of ``intervals`` (a periodic axis at 4 at least), each
    choice once, fewest coefficients first."""
    for k in intervals:
        checks.integer("PGD intervals", k, minimum=1)
    found: dict[tuple[int, ...], tuple[Axis, ...]] = {}
    for k in sorted(intervals):
        axes = tuple(Axis(p, max(k, DEGREE + 1) if full_turn(p) else k) for p in parameters)
        found.setdefault(tuple(axis.intervals for axis in axes), axes)
    return list(found.values())
