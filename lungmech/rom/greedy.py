"""Weak greedy training of a reduced basis over a parameter box, to an error tolerance.

Start from the full load path at the default parameters. Each round makes the POD basis of
every snapshot so far, solves that reduced model at every candidate point of the box (cheap) and
measures its error indicator η (:mod:`lungmech.rom.indicator`). If the largest η meets the
tolerance — over the candidates and, for the last model, its own training points too — the
basis is done. Otherwise the full model solves the load path at that candidate — or, with
``batch`` B, at the B candidates of largest η above the tolerance, solved together by the
training's ``paths`` (an ensemble's: at once) —: its states become snapshots, and the reduced
model's true error there (energy norm, as :func:`lungmech.rom.accuracy.errors`) is measured on
the way, so every full solve reports the indicator next to the error it estimates, and the
largest ratio error / indicator of the last three solves near the tolerance (at least 1)
scales the indicator before it is compared with the tolerance: an indicator that has
underestimated the error does not end the training early. Errors are relative to each load path's largest change, so each path's snapshots enter the POD
divided by their largest norm (a small load path weighs as much as a large one), and the POD
keeps the fewest vectors whose discarded energy of these lies below (tolerance / 10)²: the
truncation does not spend the error budget.

With ``hyper`` = τ the rounds judge the hyper-reduced model itself, cheaply: every Newton
iterate of the full solves is kept, each round trains an ECSW sample (:mod:`lungmech.rom.ecsw`)
on them for its basis and enrichment W, and each candidate's indicator is the answer's own
online one (:class:`~lungmech.rom.indicator.EnrichedIndicator`; the residual indicator where
there is no W). The true errors, and so the tolerance, are then those of the hyper-reduced
model, and the last round's sample comes with the basis.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from lungmech import checks
from lungmech.errors import ParameterError, SolverError
from lungmech.fem.model import Model
from lungmech.fem.parametric import FullOrderModel, Solution
from lungmech.fem.start import one_state
from lungmech.parallel.linalg import norms
from lungmech.rom import ecsw, load_paths
from lungmech.rom.accuracy import errors
from lungmech.rom.basis import Basis, inner_product
from lungmech.rom.ecsw import Sample
from lungmech.rom.indicator import ResidualIndicator, enrichment
from lungmech.rom.load_paths import Paths
from lungmech.rom.pod import pod
from lungmech.rom.reduced import ReducedModel

__all__ = ["Greedy", "Round", "greedy"]

log = logging.getLogger("lungmech")


@dataclass(frozen=True)
class Round:
    """One full solve of a round (a round of a batch greedy has several): the reduced model of
    ``size`` vectors judged every candidate, and ``point`` had one of its largest indicators η
    (inf: the reduced solve failed there). ``error`` is that model's true energy-norm error at
    ``point``, measured by the full solve that followed (None for the last, which ended the
    training: its ``point`` has the largest η of all)."""

    size: int
    point: dict[str, float]
    indicator: float
    error: float | None


@dataclass(frozen=True)
class Greedy:
    """The trained basis, the points whose full load paths it holds (the first: the defaults),
    the rounds, whether the largest indicator met the tolerance, every POD direction of the
    last round (``basis`` leads them; the next ones are an enrichment) and, trained with
    ``hyper``, the ECSW sample of the basis and its enrichment and the Newton iterates of the
    full solves, ``(state, time, parameters)`` each (to sample again at another τ:
    :meth:`lungmech.rom.ecsw.Training.replay`; a :class:`~lungmech.rom.reductor.Reductor` of
    it does)."""

    basis: Basis
    training: list[dict[str, float]]
    rounds: list[Round]
    met: bool
    modes: Basis
    sample: Sample | None = None
    safety: float = 1.0  # the factor on the indicator when it stopped (see _safety)
    iterates: tuple = ()
    tolerance: float | None = None  # what it trained to
    batch: int = 1  # full solves a round


def greedy(
    full: FullOrderModel,
    candidates: Sequence[Mapping[str, float]],
    tolerance: float,
    size: int = 40,
    inner: str = "energy",
    most: int | None = None,
    timings: dict[str, float] | None = None,
    hyper: float | None = None,
    batch: int = 1,
    paths: Paths | None = None,
) -> Greedy:
    """Train a POD basis of ``full`` until every candidate's indicator is ≤ ``tolerance``.

    ``candidates``: parameter points of the box (e.g. a Sobol' sample), where the reduced model
    is judged and from which full solves are chosen; ``size`` caps the basis; ``most`` caps the
    full solves (default: one per candidate, and the defaults'). ``hyper``: the ECSW tolerance
    τ of a hyper-reduced model to judge (see the module's doc). ``timings`` receives the
    seconds of the full solves, the POD, the ECSW training (and of it, the tangents and the
    compressions) and NNLS, and the judging. Each round is logged ("lungmech", INFO).
    ``batch``: the full solves a round adds — at the ``batch`` candidates of largest indicator,
    solved together by ``paths`` (default: one after another on ``full``; an ensemble's,
    :mod:`lungmech.app.training_paths`, solves them at once). Collective.
    """
    checks.real("greedy tolerance", tolerance)
    if not 0 < tolerance < 1:
        raise ParameterError(f"the greedy tolerance must lie in (0, 1) (got {tolerance!r})")
    if not candidates:
        raise ParameterError("the greedy training needs at least one candidate parameter point")
    most = len(candidates) + 1 if most is None else checks.integer("greedy full solves", most, minimum=1)
    batch = checks.integer("greedy batch", batch, minimum=1)
    if hyper is not None:
        checks.real("ECSW tolerance", hyper)
        if not 0 < hyper < 1:
            raise ParameterError(f"the ECSW tolerance must lie in (0, 1) (got {hyper!r})")
    model, seconds = full.model, {"snapshots": 0.0, "pod": 0.0, "judging": 0.0}
    seconds |= {"ecsw_training": 0.0, "nnls": 0.0} if hyper is not None else {}
    start = one_state(full.start, model)
    remaining = [full.parameters.values(point) for point in candidates]
    solved = paths or load_paths.serial(full, start)
    training, scaled = [], []  # the training points, and each one's snapshots divided by their largest norm
    rounds: list[Round] = []
    iterates: list = []  # with hyper: (owned rows, time, parameters) of every Newton iterate of the full solves
    indicator = ResidualIndicator(model)
    weight = inner_product(model, inner)

    def add(
        points: list[dict[str, float]], reduced: ReducedModel | None = None, answers: Sequence[Solution | None] = ()
    ) -> list[float | None]:
        """Solve the full paths at ``points``, keep their snapshots (and iterates), and return
        the true error at each of ``reduced``, which gave ``answers`` there (None: it failed)."""
        tic = time.perf_counter()
        found = solved([(point, 1.0) for point in points], hyper is not None)
        errors_here: list[float | None] = []
        for index, (point, path) in enumerate(zip(points, found, strict=True)):
            largest = float(np.max(norms(path.snapshots, weight, model.geometry.mesh.comm)))
            scaled.append(path.snapshots / largest if largest > 0 else path.snapshots)
            iterates.extend(path.iterates)
            training.append(point)
            approximate = answers[index] if answers else None
            errors_here.append(
                None if reduced is None or approximate is None else errors(reduced, path.solution, approximate).energy
            )
        seconds["snapshots"] += time.perf_counter() - tic
        return errors_here

    try:
        add([full.parameters.defaults])
        while True:
            tic = time.perf_counter()
            modes = pod(model, np.hstack(scaled), inner=inner, source={"training": list(training)})
            basis = _truncated(modes, size, tolerance)
            seconds["pod"] += time.perf_counter() - tic
            W = enrichment(basis, modes)
            sample = _sampled(model, basis, W, iterates, hyper, seconds) if hyper is not None else None
            tic = time.perf_counter()
            reduced = ReducedModel(
                model,
                basis,
                full.stepping,
                full.solver.options,
                start,
                full.outputs.probe_points,
                training,
                sample,
                W if sample is not None else None,
            )
            judged = [_judge(reduced, indicator, point) for point in remaining]
            seconds["judging"] += time.perf_counter() - tic
            worst = int(np.argmax([eta for eta, _ in judged])) if judged else None
            if worst is None or judged[worst][0] * _safety(rounds, tolerance) <= tolerance or len(training) >= most:
                # The last model is judged at its training points too: its basis is truncated
                # and its sample approximate, so it is not exact there, and with no candidate
                # left they are all the indicator has to say.
                judged += [_judge(reduced, indicator, point) for point in training]
                points = [*remaining, *training]
                worst = int(np.argmax([eta for eta, _ in judged]))
                eta = judged[worst][0]
                rounds.append(Round(basis.size, points[worst], eta, None))
                log.info(
                    f"greedy: {basis.size} vectors, largest indicator {eta:.2e} × safety {_safety(rounds, tolerance):.2f} "
                    f"(tolerance {tolerance:.0e})"
                )
                break
            safety = _safety(rounds, tolerance)  # a batch takes no candidate that meets the tolerance
            largest = _largest(judged, min(batch, most - len(training)))
            chosen = [i for i in largest if i == worst or judged[i][0] * safety > tolerance]
            points = [remaining[i] for i in chosen]
            found = add(points, reduced, [judged[i][1] for i in chosen])
            for i, point, error in zip(chosen, points, found, strict=True):
                eta = judged[i][0]
                rounds.append(Round(basis.size, point, eta, error))
                shown = f"{error:.2e}" if error is not None else "n/a (its reduced solve failed)"
                log.info(
                    f"greedy: {basis.size} vectors, indicator {eta:.2e} at {full.parameters.text(point)}: "
                    f"true error {shown}"
                )
            remaining = [point for i, point in enumerate(remaining) if i not in chosen]
    finally:
        indicator.destroy()
        if weight is not None:
            weight.destroy()
        full.reset()
    if timings is not None:
        timings.update(seconds)
    safety = _safety(rounds, tolerance)
    met = rounds[-1].indicator * safety <= tolerance
    return Greedy(basis, training, rounds, met, modes, sample, safety, tuple(iterates), tolerance, batch)


def _largest(judged: Sequence[tuple[float, object]], count: int) -> list[int]:
    """The indices of the ``count`` largest indicators, largest first (ties: the first given)."""
    order = sorted(range(len(judged)), key=lambda i: (-judged[i][0], i))
    return order[:count]


SAFETY_ROUNDS = 3  # the indicator's latest effectivities (a full solve's each) the safety factor takes


def _safety(rounds: Sequence[Round], tolerance: float) -> float:
    """The largest error / indicator of the last :data:`SAFETY_ROUNDS` full solves whose error was
    near the tolerance (at most 10 times it: where the indicator decides when to stop; far
    above, in the nonlinear regime of a poor basis, it only ranks the candidates), at least 1.
    The latest: the indicator of the basis at hand, not of the poorer ones before it."""
    ratios = [
        r.error / r.indicator
        for r in rounds
        if r.error is not None and r.error <= 10 * tolerance and 0 < r.indicator < np.inf
    ]
    return max([1.0, *ratios[-SAFETY_ROUNDS:]])


def _judge(
    reduced: ReducedModel, indicator: ResidualIndicator, point: dict[str, float]
) -> tuple[float, Solution | None]:
    """(η, the reduced answer) at ``point``: the answer's own online indicator, or else the
    residual one; (inf, None) when the reduced solve fails there."""
    try:
        approximate = reduced.solve(point)
    except SolverError:
        return np.inf, None
    if approximate.indicator is not None:
        return approximate.indicator, approximate
    return indicator(reduced, approximate), approximate


def _sampled(model: Model, basis: Basis, W: np.ndarray, iterates: list, tolerance: float, seconds: dict) -> Sample:
    """The ECSW sample of [V W] at ``tolerance``, trained on the stored ``iterates``."""
    tic = time.perf_counter()
    training = ecsw.Training(model, np.hstack([basis.vectors, W]))
    try:
        training.replay(iterates)
        seconds["ecsw_training"] += time.perf_counter() - tic
        for part, value in training.seconds.items():  # where the training's time went
            seconds[f"ecsw_{part}"] = seconds.get(f"ecsw_{part}", 0.0) + value
        tic = time.perf_counter()
        sample = training.sample(tolerance)
        seconds["nnls"] += time.perf_counter() - tic
    finally:
        training.destroy()
    return sample


def _truncated(basis: Basis, size: int, tolerance: float) -> Basis:
    """The fewest leading vectors whose discarded snapshot energy is ≤ (tolerance / 10)², at
    most ``size``."""
    kept = basis.truncate(energy=1 - (tolerance / 10) ** 2) if basis.size > 1 else basis
    return kept.truncate(min(size, kept.size))
