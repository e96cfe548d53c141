"""``lungmech trade``: every model of a scene measured on the same points, and the cheapest one
that meets a tolerance chosen.

The candidates are full models at several discretisations (:mod:`lungmech.app.ladder`: the
scene's mesh, a coarser remesh where a builder can make one, refinements; P1 and P2), reduced
models given as files (of the same physics), and, on request (:class:`Family`), a family of
reduced models built by the one reductor into lungmech's cache: the Galerkin model and its
hyper-reductions at several τ, from one training. The reference is the scene's mesh refined ``levels`` times,
finer than every candidate; its three finest levels give the observed order of convergence
and, where it agrees with the expected one, Richardson's estimate of the reference's own
error (:mod:`lungmech.trade.convergence`). The points are seeded Sobol' points none of the
models was trained on, and the box's corners (:mod:`lungmech.trade.points`). Each candidate
is measured in a process of its own (:mod:`lungmech.app.measure`: warm online time, start-up,
peak memory); full answers are kept in lungmech's cache, so that a second trade, or one
interrupted, solves only what it has not solved before.

Quantities that need no path are solved statically (``solve(μ, times=[t*])``) at t*, the
output time of the largest load (end-inspiration for a breath, :func:`peak_time`); ``pv``
solves the whole path.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

from mpi4py import MPI

import numpy as np

from lungmech import checks
from lungmech.app import answers
from lungmech.app import scene as scenes
from lungmech.app.cache import BUILDING, Cache, code_version, default_folder, key
from lungmech.app.field_errors import energy_errors, energy_norm_allowed
from lungmech.app.ladder import Discretisation, mixed_allowed, remeshed
from lungmech.app.measure import apart
from lungmech.app.model_file import embedded_names
from lungmech.app.reduce import build_family, check_physics, embedded_scene, family_files
from lungmech.app.run import full_order_model
from lungmech.errors import LungmechError, ParameterError
from lungmech.fem.parameters import Parameters
from lungmech.parallel.ensemble import Ensemble, Serial
from lungmech.pgd.store import is_pgd
from lungmech.rom import store
from lungmech.trade import quantities
from lungmech.trade.choice import Choice, Measured, check_tolerance, choose
from lungmech.trade.convergence import Convergence, observed_order
from lungmech.trade.points import ValidationPoints, validation_points

__all__ = ["Candidate", "Family", "Trade", "candidates", "peak_time", "trade"]

log = logging.getLogger("lungmech")


@dataclass(frozen=True)
class Candidate:
    """A model to measure: its ``name``, ``family`` ("full", "galerkin", "ecsw", "pgd") and what
    :mod:`lungmech.app.measure` builds it from (``request``)."""

    name: str
    family: str
    request: dict

    @classmethod
    def full(cls, discretisation: Discretisation) -> Candidate:
        return cls(f"full {discretisation.name}", "full", {"kind": "full", "discretisation": discretisation.content()})

    @classmethod
    def file(cls, path: str | Path, family: str, name: str | None = None) -> Candidate:
        return cls(name or Path(path).name, family, {"kind": "file", "path": str(Path(path).resolve())})


@dataclass(frozen=True)
class Family:
    """The reduced models a trade builds (``--build``): one POD of the full model's paths at
    ``samples`` seeded Sobol' points of the box (``seed``; default 8, or the loads at 0.5, 1,
    1.5 without parameters); at each basis size of ``sizes``, its leading vectors Galerkin and
    hyper-reduced by ECSW at each τ of ``taus`` (none: Galerkin alone) — the error and the
    speed per basis size and τ side by side."""

    taus: tuple[float, ...] = (1e-3, 1e-4, 1e-5)
    sizes: tuple[int, ...] = (20,)
    samples: int | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        for tau in self.taus:
            checks.real("ECSW tolerance τ", tau)
            if not 0 < tau < 1:
                raise ParameterError(f"--taus: an ECSW tolerance τ lies in (0, 1) (got {tau!r})")
        if not self.sizes:
            raise ParameterError("--sizes: give at least one basis size")
        for size in self.sizes:
            checks.integer("--sizes: a basis size", size, minimum=1)
        if self.samples is not None:
            checks.integer("--samples", self.samples, minimum=1)
        checks.integer("--seed", self.seed, minimum=0)
        family_files(self.taus, self.sizes)  # no τ or size twice


@dataclass
class Trade:
    """What a trade measured: the points, the candidates' results by name (the reference's
    too), their families and requests, the errors by quantity, each reduced model's error of
    reduction alone (against ``own``, the full model it reduces), the convergence, and the
    choice."""

    scene: str
    tolerance: float
    quantity: str
    points: ValidationPoints
    times: list[float] | None
    reference: str
    queries: int | None = None
    ensemble: str = ""
    full_solves: dict[str, int] = field(default_factory=dict)  # "solved" here and "kept" from before
    results: dict[str, dict] = field(default_factory=dict)
    families: dict[str, str] = field(default_factory=dict)
    requests: dict[str, dict] = field(default_factory=dict)
    errors: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    reduction: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # against ``own``
    own: str | None = None  # the full model on the scene's own mesh: the reduced models' own full model
    convergence: dict[str, Convergence] = field(default_factory=dict)
    measured: list[Measured] = field(default_factory=list)
    choice: Choice | None = None
    notes: list[str] = field(default_factory=list)


def peak_time(scene: scenes.Scene) -> float:
    """The output time at which the loads, each relative to its own largest value, sum largest
    (the latest of equals): end-inspiration for a breath, the end for a monotone ramp."""
    stepping = scene.stepping
    grid = sorted({*stepping.times, stepping.end, *np.linspace(stepping.start, stepping.end, 201)[1:]})
    ramps = [load.ramp for load in scene.loads if getattr(load, "ramp", None) is not None]
    if not ramps:
        return float(stepping.end)
    levels = np.array([[abs(ramp(t)) for t in grid] for ramp in ramps])
    levels /= np.maximum(levels.max(axis=1, keepdims=True), 1e-300)
    total = levels.sum(axis=0)
    return float(grid[int(np.flatnonzero(total >= total.max() - 1e-12)[-1])])


def candidates(
    scene: scenes.Scene, levels: int = 2, degrees: Sequence[int] = (1, 2), coarser: bool = True
) -> tuple[list[Candidate], Candidate, list[str]]:
    """The full candidates of ``scene`` — a remesh 2× coarser (where its builder makes one),
    its mesh refined 0 … ``levels`` − 1 times, each other degree of ``degrees`` on its mesh
    (a mixed scene's ≥ 2), and Taylor–Hood P2–P1 on its mesh where the scene's displacement
    formulation allows —, the reference (refined ``levels`` times) and notes on what was not
    made."""
    checks_levels(levels)
    notes: list[str] = []
    made = []
    own = Discretisation.of(scene)
    if coarser:
        try:
            remeshed(scene, 2.0)  # a check only: can the builder make it?
            made.append(Candidate.full(replace(own, level=-1)))
        except ParameterError as why:
            notes.append(f"no coarser full model: {why}")
    made += [Candidate.full(replace(own, level=level)) for level in range(levels)]
    made += [
        Candidate.full(replace(own, degree=degree))
        for degree in degrees
        if degree != scene.degree and (degree >= 2 or not own.mixed)
    ]
    if not own.mixed:
        try:
            mixed_allowed(scene)
            made.append(Candidate.full(Discretisation(0, max(2, scene.degree), mixed=True)))
        except ParameterError as why:
            notes.append(f"no mixed full model: {why}")
    return made, Candidate.full(replace(own, level=levels)), notes


def checks_levels(levels: int) -> None:
    if isinstance(levels, bool) or not isinstance(levels, int) or levels < 1:
        raise ParameterError(f"--levels: the reference is the scene's mesh refined 1 or more times (got {levels!r})")


def trade(
    scene_path: str | Path,
    tolerance: float,
    quantity: str = "volume",
    count: int = 8,
    models: Sequence[str | Path] = (),
    queries: int | None = None,
    cache: str | Path | None = None,
    levels: int = 2,
    seed: int = 12345,
    full: Sequence[Candidate] | None = None,
    build: Family | None = None,
    comm: MPI.Comm = MPI.COMM_WORLD,
    ensemble: Ensemble | None = None,
) -> Trade:
    """Measure the scene's candidates (``full`` ones, default :func:`candidates`, the model
    files ``models``, and the reduced models ``build`` names, built first) against the
    reference on the trade's points and choose (see the module's doc). ``cache``: lungmech's
    cache folder (default :func:`lungmech.app.cache.default_folder`). The full solves run on
    ``ensemble`` (default: :class:`~lungmech.parallel.ensemble.Serial` on ``comm``) into the
    cache, before each candidate is measured. Collective."""
    quantities.expected_order(quantity, 1)  # the name's check
    check_tolerance(tolerance)
    checks.integer("--points", count, minimum=1)
    if queries is not None:
        checks.integer("--queries", queries, minimum=1)
    path = Path(scene_path).resolve()
    scene = scenes.load(path)
    made, reference, notes = candidates(scene, levels)
    if full is not None:
        made = list(full)
    for model in models:
        _check_model(model, scene, comm)
    if quantity in quantities.FIELDS:
        energy_norm_allowed(full_order_model(scene, comm, start="inverse_motion").model)  # before any solve
    store_root = Cache(cache if cache is not None else default_folder(), comm)
    engine = ensemble if ensemble is not None else Serial(comm)
    built = _built(scene, build, store_root, engine, comm) if build is not None else {}
    files = [*models, *built.values()]
    files_as = [Candidate.file(model, _family(model)) for model in models]
    files_as += [Candidate.file(file, _family(file), name) for name, file in built.items()]
    trained = [point for model in files for point in _training(model)]
    points = validation_points(Parameters(scene.parameters), count, seed, trained)
    times = None if quantity == "pv" else [peak_time(scene)]
    found = Trade(
        str(path), tolerance, quantity, points, times, reference.name, queries, engine.description, notes=notes
    )
    _solve_all(found, path, [reference, *made], engine, str(store_root.root))
    for candidate in [reference, *made, *files_as]:
        request = {
            "scene": str(path),
            "candidate": candidate.request,
            "points": points.points,
            "times": times,
            "fields": quantity in quantities.FIELDS,
            "cache": str(store_root.root),
            "timed": candidate is not reference,
        }
        result = apart(request, comm)
        if "error" in result:
            raise LungmechError(f"candidate {candidate.name}: {result['error']}")
        found.results[candidate.name] = result
        found.families[candidate.name] = candidate.family
        found.requests[candidate.name] = candidate.request
    made = [candidate for candidate in made if not _same_as_scene_mesh(found, candidate, scene)]
    failed = [i for i, a in enumerate(found.results[reference.name]["answers"]) if a["failed"] is not None]
    if failed:
        found.notes.append(
            f"the reference failed at {len(failed)} of {len(points)} points (no model is judged there: each counts "
            f"as failed): {', '.join(f'{points.kinds[i]} {points.points[i]}' for i in failed)}"
        )
    _judge(found, scene, [reference, *made, *files_as], levels, store_root)
    return found


def _solve_all(found: Trade, scene: Path, full: Sequence[Candidate], engine: Ensemble, cache: str) -> None:
    """Every full candidate's answer at every point, solved on ``engine`` into the cache (the
    costliest first, so that groups share the work evenly); a solve that failed outside the
    solver is noted (its candidate's measurement fails the same way and says so)."""
    times = None if found.times is None else tuple(found.times)
    fields = found.quantity in quantities.FIELDS
    work = [
        answers.Task(str(scene), point, Discretisation(**candidate.request["discretisation"]), times, fields)
        for candidate in full
        for point in found.points.points
    ]
    work.sort(key=lambda task: 8.0**task.discretisation.level * 8.0 ** (task.discretisation.degree - 1), reverse=True)
    log.info("lungmech: %d full solves (%s)", len(work), engine.description)
    outcomes = engine.map(partial(answers.solved, cache=cache), work, lambda line: log.info("trade: %s", line))
    answers.forget()
    kept = sum(bool(outcome.value and outcome.value["kept"]) for outcome in outcomes)
    found.full_solves = {"solved": len(work) - kept, "kept": kept}
    for task, outcome in zip(work, outcomes, strict=True):
        if outcome.failed is not None:
            found.notes.append(f"full {task.discretisation.name} at {task.values}: {outcome.failed}")


def _check_model(path: str | Path, scene: scenes.Scene, comm: MPI.Comm) -> None:
    """Refuse a model file that is not a model of the scene's physics (in one line)."""
    if not Path(path).is_file():
        raise ParameterError(f"--models: '{path}' is not a file")
    content = store.read_on_root(path, comm)
    with embedded_scene(path, comm, content=content) as built:
        check_physics(Path(path), scenes.physics(built), scene)


def _built(scene: scenes.Scene, family: Family, cache: Cache, engine: Ensemble, comm: MPI.Comm) -> dict[str, Path]:
    """The family's model files by name ("POD Galerkin", "POD ECSW τ=0.0001", …), built into the
    cache once per content (the scene's every setting and file, the family, the code), their
    training solves on ``engine`` and kept in the cache too. Collective."""
    content = {
        "scene": scene.table,
        "physics": scenes.physics(scene),
        "files": {name: scenes.file_sha256(file) for name, file in embedded_names(scene).items()},
        "family": asdict(family),
        "code": code_version(BUILDING),
    }

    def fill(folder: Path) -> None:
        build_family(scene, folder, family.taus, family.sizes, family.samples, family.seed, comm, engine, cache.root)

    folder = cache.folder("models", key(content), fill)
    return {name: folder / file for name, file in family_files(family.taus, family.sizes).items()}


def _same_as_scene_mesh(found: Trade, candidate: Candidate, scene: scenes.Scene) -> bool:
    """A remesh that gave the scene's own mesh size back (a builder's other limits held): noted, dropped."""
    if candidate.request.get("discretisation", {}).get("level", 0) >= 0:
        return False
    scene_mesh = found.results.get(f"full {Discretisation.of(scene).name}")
    if scene_mesh is None or found.results[candidate.name]["dofs"] < (own := scene_mesh["dofs"]):
        return False
    found.notes.append(f"no coarser full model: the builder's mesh at twice the mesh size has {own} dofs too")
    del found.results[candidate.name]
    return True


def _judge(
    found: Trade, scene: scenes.Scene, measured: list[Candidate], levels: int, cache: Cache | None = None
) -> None:
    """The errors of every candidate, the reference's convergence, and the choice (``cache``:
    where the full solves kept their fields, for a quantity of fields)."""
    reference = found.results[found.reference]["answers"]
    names = ["pv"] if found.quantity == "pv" else ["volume"] + (["probes"] if scene.output.probes else [])
    for candidate in measured:
        answers = found.results[candidate.name]["answers"]
        found.errors[candidate.name] = {q: quantities.errors(answers, reference, q) for q in names}
        if "probes" in names:
            found.errors[candidate.name]["probes_mm"] = quantities.probe_millimetres(answers, reference)
    ladder = [f"full {Discretisation.of(scene, level).name}" for level in range(levels - 2, levels + 1)]
    solved: dict = {}  # the model files' fields, solved once for both meshes they are judged on
    if found.quantity in quantities.FIELDS:
        assert cache is not None, "a quantity of fields is judged on the fields the cache keeps"
        _judge_fields(found, scene, measured, ladder if levels >= 2 else [], cache, solved)
    if levels >= 2 and all(name in found.results for name in ladder):
        coarse, middle, fine = (found.results[name]["answers"] for name in ladder)
        for q in names:
            try:
                q0, q1, q2 = (quantities.normalised(a, reference, q).ravel() for a in (coarse, middle, fine))
                found.convergence[q] = observed_order(q0, q1, q2, quantities.expected_order(q, scene.degree))
            except ParameterError as why:
                found.notes.append(f"no observed order of {q}: {why}")
    _note_higher_degrees(found, measured)
    _judge_reduction(found, scene, measured, names, cache, solved)
    for q, order in found.convergence.items():
        last = found.errors[ladder[1]][q] if ladder[1] in found.errors else np.array([np.nan])
        if order.estimate is None and np.isfinite(last).any():
            found.notes.append(
                f"the reference's own error on {q} is not estimated (observed order {order.observed:.2f}, "
                f"expected {order.expected:g}); its last refinement moved it by up to {np.nanmax(last):.1e}, "
                "so errors near that are not told apart from the reference's own"
            )
    for candidate in measured:
        if candidate.name == found.reference:
            continue
        result, errors = found.results[candidate.name], found.errors[candidate.name][found.quantity]
        failed = int(np.isnan(errors).sum())
        worst = float(np.nanmax(errors)) if failed < len(errors) else math.inf
        online = result["online_seconds"] if result["online_seconds"] is not None else math.inf
        found.measured.append(
            Measured(candidate.name, candidate.family, worst, failed, online, float(result.get("offline_seconds", 0.0)))
        )
    convergence = found.convergence.get(found.quantity)
    accuracy = None if convergence is None or convergence.estimate is None else convergence.estimate
    found.choice = choose(found.measured, found.tolerance, found.quantity, found.queries, accuracy)


def _note_higher_degrees(found: Trade, measured: list[Candidate]) -> None:
    """Say where a full candidate's elements are of a higher degree than the reference's: there
    the reference may be the less accurate of the two, and the measured error its own."""
    named = [candidate for candidate in measured if candidate.name == found.reference]
    if not named:
        return
    reference = Discretisation(**named[0].request["discretisation"])
    higher = [
        candidate.name
        for candidate in measured
        if candidate.family == "full"
        and Discretisation(**candidate.request["discretisation"]).degree > reference.degree
    ]
    if higher:
        found.notes.append(
            f"{', '.join(higher)}: of a higher degree than the reference ({reference.name}), which may be the less "
            "accurate: the error measured there may be the reference's own"
        )


def _judge_reduction(
    found: Trade,
    scene: scenes.Scene,
    measured: list[Candidate],
    names: list[str],
    cache: Cache | None,
    solved: dict | None = None,
) -> None:
    """Each reduced model's error of reduction alone: against the full model on the scene's own
    mesh, which it reduces, on every quantity the trade judges — the share of its error that a
    larger basis or a smaller τ could remove; the rest is the mesh's. A model file of another
    mesh (its dofs differ) is noted and not judged so."""
    own = Discretisation.of(scene)
    found.own = f"full {own.name}" if f"full {own.name}" in found.results else None
    reduced = [c for c in measured if c.family != "full" and c.name != found.reference]
    if found.own is None or not reduced:
        return
    target = found.results[found.own]
    others = [c.name for c in reduced if found.results[c.name].get("dofs") != target.get("dofs")]
    if others:
        found.notes.append(
            f"{', '.join(others)}: not of the scene's own mesh ({target.get('dofs')} dofs), so no error of reduction "
            f"against {found.own} is measured"
        )
    reduced = [c for c in reduced if c.name not in others]
    for candidate in reduced:
        answers = found.results[candidate.name]["answers"]
        found.reduction[candidate.name] = {q: quantities.errors(answers, target["answers"], q) for q in names}
    if found.quantity in quantities.FIELDS and reduced:
        assert cache is not None and found.times is not None
        requests = {candidate.name: candidate.request for candidate in reduced}
        fields = energy_errors(
            found.scene, scene, found.points.points, found.times, own, requests, cache, solved=solved
        )
        for name, errors in fields.errors.items():
            found.reduction[name]["energy"] = errors


def _judge_fields(
    found: Trade,
    scene: scenes.Scene,
    measured: list[Candidate],
    ladder: list[str],
    cache: Cache,
    solved: dict | None = None,
) -> None:
    """The energy-norm errors of every candidate (:mod:`lungmech.app.field_errors`) and the
    reference's observed order in that norm."""
    assert found.times is not None  # (a static quantity)
    reference = Discretisation(**found.requests[found.reference]["discretisation"])
    requests = {candidate.name: candidate.request for candidate in measured}
    fields = energy_errors(
        found.scene, scene, found.points.points, found.times, reference, requests, cache, ladder, solved
    )
    found.notes += fields.notes
    for name, errors in fields.errors.items():
        found.errors[name]["energy"] = errors
    if fields.convergence is not None:
        found.convergence["energy"] = fields.convergence


def _family(path: str | Path) -> str:
    """ "pgd" for a PGD model file, "ecsw" for a hyper-reduced one, else "galerkin"."""
    metadata = _metadata(path)
    if is_pgd(metadata):
        return "pgd"
    return "ecsw" if metadata.get("extra", {}).get("reduced", {}).get("hyper") else "galerkin"


def _training(path: str | Path) -> list[dict[str, float]]:
    """The parameter points a model file was trained on (a fitted PGD: its sample; an a priori
    one: none), which the trade's points avoid."""
    extra = _metadata(path).get("extra", {})
    points = (
        extra["pgd"]["built"].get("training", []) if "pgd" in extra else extra.get("reduced", {}).get("training", [])
    )
    return [dict(point) for point in points]


def _metadata(path: str | Path) -> dict[str, Any]:
    """A model file's metadata, its record of how it was made (:mod:`lungmech.rom.store`)."""
    metadata, _ = store.read_on_root(path, MPI.COMM_SELF, arrays=False)
    return metadata
