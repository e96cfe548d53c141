"""Reduced models of a scene: built offline from full-order runs, solved online like a scene.

Offline (:func:`build`): the scene's full-order model, started as its reduced models are (a scene
with [inverse]: on its fixed imaged mesh, its reference found at every μ by the inverse motion,
:mod:`lungmech.rom.imaged`), goes to the one
reductor (:func:`lungmech.rom.reductor.reduce`) with the basis recipe, the training points — a
seeded Sobol' sample of the scene's [parameters] box and the load scales, or a greedy over it
to a tolerance — and the hyper-reduction asked for; the reduced model is written by
:func:`lungmech.rom.store.write_reduced`, with the scene itself and every file it reads
(:mod:`lungmech.app.model_file`), so that the model file is all ``lungmech rom solve model.npz
--set name=value`` needs.

Online: :func:`load` gives the :class:`~lungmech.rom.reduced.ReducedModel` of a model file on the
scene it holds, and :func:`reduced_order` the ``model`` of :func:`lungmech.app.run.run`, so a
reduced run writes the same outputs as a full one, through the same ``solve(μ)``.
"""

from __future__ import annotations

import contextlib
import functools
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from mpi4py import MPI

import numpy as np

from lungmech import checks
from lungmech.app.cache import Cache, default_folder
from lungmech.app.model_file import embedded_name, embedded_scene, file_bytes, scene_record
from lungmech.app.run import Scale, build_model, check_scale
from lungmech.app.scene import Scene, differences, physics
from lungmech.app.training_paths import EnsemblePaths, forget, image_of, training_model
from lungmech.errors import ModelFileError, ParameterError
from lungmech.fem.parameters import Parameters
from lungmech.fem.quantities import Probe
from lungmech.parallel.destination import hold_signals_until_swap, output_file
from lungmech.parallel.ensemble import Ensemble, Serial
from lungmech.parallel.layout import layout
from lungmech.rom import reductor, store
from lungmech.rom.reduced import ReducedModel

if TYPE_CHECKING:
    from lungmech.fem.model import Model
    from lungmech.pgd.model import PGDModel

__all__ = [
    "build",
    "build_family",
    "check_physics",
    "embedded_name",
    "embedded_scene",
    "family_files",
    "load",
    "reduced_order",
    "trained_range",
    "training_solves",
]

KINDS = ("pod", "modal", "modal+derivatives", "polynomial", "pod+modal")
HYPER = ("ecsw",)  # hyper-reductions


def build(
    scene: Scene,
    path: str | Path,
    kind: str = "pod",
    size: int = 20,
    scales: Sequence[Scale] | None = None,
    inner: str = "energy",
    order: int = 2,
    density: float = 1.0,
    comm: MPI.Comm = MPI.COMM_WORLD,
    samples: int | None = None,
    seed: int = 0,
    hyper: str | None = None,
    hyper_tolerance: float = 1e-4,
    tolerance: float | None = None,
    hyper_size: int | None = None,
    judge: float | None = None,
    batch: int = 1,
    ensemble: Ensemble | None = None,
    cache: str | Path | None = None,
) -> dict:
    """Build a reduced model of ``scene`` and save it to ``path`` (.npz); returns its summary.

    ``kind``: pod (of full runs at the training points), modal (K y = λ M y at the start
    state), modal+derivatives, polynomial (of ``order``), or pod+modal (enriched). ``size`` caps
    the number of vectors (POD may keep fewer: only directions above its noise level). The
    training points are ``samples`` Sobol' points of the scene's parameter box (``seed``;
    default 8 when the scene has [parameters], else its one point) times the load ``scales``
    (default 0.5, 1, 1.5 without parameters, 1 with them). ``inner``: the bases' inner product
    (energy, the default, in which tolerances and errors are measured; mass; l2).
    ``hyper`` = "ecsw" hyper-reduces it (:mod:`lungmech.rom.ecsw`) at τ = ``hyper_tolerance``;
    ``hyper_size`` then truncates the basis to that many vectors (the sample trained on the whole).
    ``tolerance`` trains the POD basis greedily (:mod:`lungmech.rom.greedy`) instead of at
    fixed points: full solves are added at the candidate — of ``samples`` Sobol' points (default
    32) — where the reduced model's error indicator is largest, until it meets ``tolerance``
    (relative energy-norm error) there; ``size`` then caps the basis. Hyper-reduced, the greedy
    judges the hyper-reduced model itself at τ = ``judge`` (default ``hyper_tolerance``), and the
    model's sample is re-sampled at ``hyper_tolerance`` from the same Newton iterates.
    ``batch``: the greedy's full solves a round (at its ``batch`` largest indicators).
    The training's full solves run on ``ensemble`` (default: this process, on ``comm``) and are
    kept in lungmech's ``cache`` folder (default :func:`lungmech.app.cache.default_folder`), so a
    build that was interrupted resumes from them (:mod:`lungmech.app.training_paths`); an imaged
    body's run in this process alone, and so does the second pass of a fixed sample's solves
    that trains its ECSW sample (a greedy's reuses its iterates).
    ``path`` is checked before any work (an existing file is replaced only if it is a lungmech
    reduced model) and written only when the build succeeds.
    """
    if kind not in KINDS:
        raise ParameterError(f"basis kind must be one of {', '.join(KINDS)} (got {kind!r})")
    if hyper is not None and hyper not in HYPER:
        raise ParameterError(f"hyper-reduction must be one of {', '.join(HYPER)} (got {hyper!r})")
    if hyper is None and (hyper_size is not None or judge is not None):
        raise ParameterError("--ecsw-size and --ecsw-judge shape a hyper-reduction: give --hyper ecsw")
    if judge is not None and tolerance is None:
        raise ParameterError("--ecsw-judge is the τ a greedy training judges at: give --tolerance")
    box = Parameters(scene.parameters)
    if tolerance is not None:  # the value first, then whether it can act
        reductor.TrainingSet(tolerance=tolerance)
    if tolerance is not None and not box:
        raise ParameterError(
            "--tolerance trains over the scene's [parameters] box, and this scene has none: add [parameters] "
            "(e.g. a load amplitude), or give --size"
        )
    if tolerance is not None and kind != "pod":
        raise ParameterError(f"--tolerance trains a POD basis (got --basis {kind})")
    if tolerance is not None and scales is not None:
        raise ParameterError(
            "--tolerance trains at the scene's loads over its [parameters] box; put a load's amplitude in "
            "[parameters] instead of giving --scales"
        )
    if scales is None:
        scales = (1.0,) if scene.parameters else (0.5, 1.0, 1.5)
    if not scales:
        raise ParameterError("give at least one training load scale")
    for scale in scales:
        check_scale(scene, scale)
    if samples is None:
        samples = (32 if tolerance is not None else 8) if box else 1
    checks.integer("training samples", samples, minimum=1)
    checks.integer("training seed", seed, minimum=0)
    recipe = _recipe(kind, size, order, density)
    training = reductor.TrainingSet(box.sample(samples, seed) if box else [{}], tuple(scales), tolerance, batch)
    ecsw = reductor.ECSW(hyper_tolerance, judge, hyper_size) if hyper else None
    where = training_solves(scene, ensemble, cache, comm)
    path = store.suffixed(path)
    with output_file(path, comm, inputs=scene.inputs, ours=store.is_model) as staging:
        return _build(scene, [(staging, ecsw, None)], recipe, training, inner, comm, solves=where)


@contextlib.contextmanager
def _forgetting() -> Iterator[None]:
    """Within the block, the training models a process keeps for its next path; dropped after
    (an ensemble's groups free their communicators)."""
    try:
        yield
    finally:
        forget()


def training_solves(
    scene: Scene, ensemble: Ensemble | None, cache: str | Path | None, comm: MPI.Comm
) -> tuple[Ensemble, str] | None:
    """Where the training's full solves run and are kept: ``ensemble`` (default: serial on
    ``comm``) and the ``cache`` folder (made now: a folder not lungmech's is refused before any
    work); None for a scene made in Python (with no file to name it)."""
    if scene.source is None:  # made in Python: solved here, not kept (a kept path is named by the scene's file)
        if ensemble is not None:
            raise ParameterError("an ensemble solves a scene from its file: give the scene as a file")
        return None
    if ensemble is not None:
        ensemble.check(comm)
    folder = Path(cache) if cache is not None else default_folder()
    Cache(folder, comm)  # its checks, on the first rank
    return ensemble or Serial(comm), str(folder.expanduser().resolve())


def _recipe(kind: str, size: int, order: int, density: float) -> reductor.Recipe:
    """The basis recipe a ``--basis`` kind names."""
    if kind == "pod":
        return reductor.POD(size)
    if kind in ("modal", "modal+derivatives"):
        return reductor.Modal(size, density, derivatives=kind == "modal+derivatives")
    if kind == "polynomial":
        return reductor.Polynomial(order, size)
    return reductor.Enriched((reductor.POD(size), reductor.Modal(size, density)), size)


def build_family(
    scene: Scene,
    folder: str | Path,
    taus: Sequence[float],
    sizes: Sequence[int] = (20,),
    samples: int | None = None,
    seed: int = 0,
    comm: MPI.Comm = MPI.COMM_WORLD,
    ensemble: Ensemble | None = None,
    cache: str | Path | None = None,
) -> dict[str, Path]:
    """A family of reduced models of ``scene`` from one reductor, for a trade to measure side by
    side: at each basis size k of ``sizes``, the POD Galerkin model of the POD's k leading
    vectors and its ECSW hyper-reductions at each τ of ``taus`` (none: Galerkin alone; the files
    and names of :func:`family_files`), trained at ``samples`` Sobol'
    points (``seed``; default 8 with [parameters], else the loads at 0.5, 1, 1.5). The training
    solves are done once for all of them (one POD, of the largest size), the ECSW training once
    for every τ and size; each file records
    the seconds and full solves it would have cost alone. ``folder`` is an empty folder of
    lungmech's own (a cache entry's staging folder: nothing is checked or replaced there);
    returns the files by model name. The training solves run on ``ensemble`` and are kept in
    ``cache``, as :func:`build`'s (an imaged body's in this process). Collective."""
    files = family_files(taus, sizes)  # no τ or size twice, before any work
    for size in sizes:
        checks.integer("basis size", size, minimum=1)
    made = [(None, k) for k in sizes] + [(reductor.ECSW(tau, size=k), k) for tau in taus for k in sizes]
    box = Parameters(scene.parameters)
    samples = samples if samples is not None else (8 if box else 1)
    checks.integer("training samples", samples, minimum=1)
    checks.integer("training seed", seed, minimum=0)
    scales = (1.0,) if box else (0.5, 1.0, 1.5)
    training = reductor.TrainingSet(box.sample(samples, seed) if box else [{}], scales)
    models = [(Path(folder) / file, *how) for file, how in zip(files.values(), made, strict=True)]
    solves = training_solves(scene, ensemble, cache, comm)
    recipe = reductor.POD(max(sizes))
    _build(scene, models, recipe, training, "energy", comm, hold_signals=False, judged=False, solves=solves)
    return {name: Path(folder) / file for name, file in files.items()}


def family_files(taus: Sequence[float], sizes: Sequence[int] = (20,)) -> dict[str, str]:
    """The files of :func:`build_family`'s models by name, Galerkin's at every size first, then
    each τ's: "POD Galerkin" (``galerkin.npz``) and "POD ECSW τ=<τ>" (``ecsw-<τ>.npz``) for
    each τ of ``taus`` with one size; with several, each name and file ends in its size k ("POD
    Galerkin k=10", ``galerkin-10.npz``)."""
    if not sizes:
        raise ParameterError("give at least one basis size for the family's models")
    if len(set(sizes)) != len(sizes):
        raise ParameterError(f"the basis sizes are given twice: {', '.join(map(str, sizes))}")
    if len(set(taus)) != len(taus):
        raise ParameterError(f"the ECSW tolerances τ are given twice: {', '.join(f'{tau:g}' for tau in taus)}")
    one = len(sizes) == 1
    named = {}
    for tau in (None, *taus):
        for k in sizes:
            name = "POD Galerkin" if tau is None else f"POD ECSW τ={tau:g}"
            file = "galerkin" if tau is None else f"ecsw-{tau:g}"
            named[name if one else f"{name} k={k}"] = f"{file}.npz" if one else f"{file}-{k}.npz"
    return named


def _build(
    scene: Scene,
    models: Sequence[tuple[Path, reductor.ECSW | None, int | None]],
    recipe: reductor.Recipe,
    training: reductor.TrainingSet,
    inner: str,
    comm: MPI.Comm,
    hold_signals: bool = True,
    judged: bool = True,
    solves: tuple[Ensemble, str] | None = None,
) -> dict:
    """Each (path, hyper-reduction, Galerkin's basis size) of ``models`` from one :class:`~lungmech.rom.reductor.Reductor`
    of the scene's full model; returns the summary of the last. ``hold_signals``: the paths are
    an output's (:func:`~lungmech.parallel.destination.output_file`), whose swap the signals
    wait for once the writing begins. ``judged``: a greedy's rounds judge at the last
    hyper-reduction's τ (a family of fixed training has no judge). ``solves``: the ensemble
    the training's full solves run on and the cache folder they are kept in (None: in this
    process, not kept)."""
    timings = {}
    tic = time.perf_counter()
    # an imaged body's reduced models answer its problem at every μ: trained on the fixed image;
    # without parameters its one reference is the defaults', found once (exact, and no basis of ξ)
    full, where = training_model(scene, comm)  # where: of the imaged mesh (a solve checks it)
    timings["build_and_inverse"] = time.perf_counter() - tic
    hypers = [hyper for _, hyper, _ in models if hyper is not None]
    judge = hypers[-1].judge or hypers[-1].tolerance if hypers and judged else None
    arrays = {f"file:{name}": data for name, data in file_bytes(scene, comm).items()}
    paths = None if solves is None else EnsemblePaths(scene, full, where, *solves)
    with reductor.Reductor(full, recipe, training, inner, judge, paths) as made, _forgetting():
        for path, hyper, size in models:
            reduced = made.reduce(hyper, size)
            spent = timings | reduced.built["timings"]
            extra = scene_record(scene, where.fingerprint, full.parameters.describe()) | {
                "scales": reduced.built["scales"],
                "offline_seconds": spent,
                "training_paths": None if paths is None else {"solved": paths.solved, "kept": paths.kept},
            }
            hyper_summary = store.hyper_record(reduced)
            if hold_signals:
                hold_signals_until_swap()  # the model file is a collective write
            store.write_reduced(path, reduced, extra, arrays)
    return {
        "kind": reduced.basis.kind,
        "size": reduced.size,
        "dofs": where.size,
        "values": reduced.basis.values.tolist(),
        "offline_seconds": spent,
        "hyper": hyper_summary,
        "greedy": reduced.built["greedy"],
        "training_paths": None
        if paths is None
        else {"solved": paths.solved, "kept": paths.kept, "cache": paths.cache, "where": paths.ensemble.description},
    }


def reduced_order(
    path: str | Path, inside: bool = False, fields: bool = True, content: tuple[dict, dict] | None = None
) -> Callable[[Scene, MPI.Comm], ReducedModel | PGDModel]:
    """The ``model`` of :func:`lungmech.app.run.run` for the reduced model stored at ``path``: a
    function of the run's scene and communicator. ``inside``: the run's scene is the one the
    file holds (:func:`embedded_scene`), else it is checked to model the same physics. Without
    ``fields`` (no full field is asked for), a hyper-reduced model of its own scene is loaded on
    its body alone, with no full mesh (:func:`lungmech.rom.store.load_body`). ``content``: what
    :func:`lungmech.rom.store.read_on_root` gave, when the caller has read the file."""
    return lambda scene, comm: _loaded(Path(path), scene, comm, inside, fields, content)


def load(path: str | Path, comm: MPI.Comm = MPI.COMM_WORLD, fields: bool = False) -> ReducedModel | PGDModel:
    """The reduced (or PGD) model stored at ``path``, self-contained: its scene and mesh come from the file;
    a hyper-reduced one on its body alone unless ``fields`` (a full field) are wanted. Collective."""
    content = store.read_on_root(path, comm)
    with embedded_scene(path, comm, content=content) as scene:
        return _loaded(Path(path), scene, comm, True, fields, content)


def _loaded(
    path: Path, scene: Scene, comm: MPI.Comm, inside: bool, fields: bool, content: tuple[dict, dict] | None
) -> ReducedModel | PGDModel:
    content = content if content is not None else store.read_on_root(path, comm)
    extra = content[0]["extra"]
    imaged = extra.get("reduced", {}).get("image") is not None or extra.get("pgd", {}).get("image") is not None
    record = extra.get("reduced", {})
    image = image_of(scene) if imaged else None  # (a file of 0.2 moved the reference)
    if inside and not fields and record.get("body") is not None:
        build = functools.partial(build_model, scene, comm, image=image)  # of the body's geometry
        return store.load_body(path, build, scene.stepping, scene.newton, content, comm)
    return _reduced(path, build_model(scene, comm, image=image), scene, inside, content)


def _reduced(
    path: Path, model: Model, scene: Scene, inside: bool, content: tuple[dict, dict]
) -> ReducedModel | PGDModel:
    """The reduced model of ``path`` on ``model`` (the scene's, just built on its mesh).
    ``inside``: ``scene`` is the file's own; otherwise it must model the physics of the file's
    scene. Probe points are located on the mesh as built (for an imaged body: in the image)."""
    comm = model.geometry.mesh.comm
    metadata, arrays = content  # arrays on rank 0 only
    if not inside:
        with embedded_scene(path, comm, content=(metadata, arrays)) as built:
            check_physics(path, physics(built), scene)
    if layout(model.space).fingerprint != metadata["extra"]["imaged_fingerprint"]:
        raise ModelFileError(f"{path} was built for another mesh or discretisation than this scene's")
    if metadata["kind"] == "pgd":  # its probes' map was made at the build's points
        from lungmech.pgd.store import load_pgd  # (SciPy's splines: only for a PGD model)

        points = metadata["extra"]["pgd"]["probes"]
        if [[float(c) for c in p] for p in scene.output.probes] != points:
            raise ModelFileError(f"{path} was built with other probe points than this scene's [output] probes")
        return load_pgd(path, model, scene.stepping, content)
    probes = Probe(model.geometry.mesh, scene.output.probes) if scene.output.probes else ()
    return store.load_reduced(path, model, scene.stepping, scene.newton, probes, content=(metadata, arrays))


def check_physics(path: Path, built: dict, scene: Scene) -> None:
    """Refuse a reduced model whose scene models other physics (``built``, its :func:`physics`)
    than ``scene`` (law, parameters, loads, boundaries, formulation, start), saying what differs."""
    if lines := differences(built, physics(scene)):
        shown = "; ".join(lines[:4]) + (f"; and {len(lines) - 4} more" if len(lines) > 4 else "")
        raise ModelFileError(
            f"{path} was built for other physics than this scene's: {shown}. Build a reduced model "
            "of this scene, or use --scale to change the loads' amplitude"
        )


def trained_range(extra: dict, scale: Scale) -> str | None:
    """A note when ``scale`` lies outside the training scales of the model: it extrapolates."""
    if not extra.get("scales"):
        return None
    trained = np.array([np.broadcast_to(np.asarray(s, dtype=float), (extra["loads"],)) for s in extra["scales"]])
    given = np.broadcast_to(np.asarray(scale, dtype=float), (extra["loads"],))
    low, high = trained.min(axis=0), trained.max(axis=0)
    if np.all((low - 1e-12 <= given) & (given <= high + 1e-12)):
        return None
    return (
        f"load scale {np.asarray(scale).tolist()} lies outside the trained range "
        f"[{low.tolist()}, {high.tolist()}]: the reduced model extrapolates"
    )
