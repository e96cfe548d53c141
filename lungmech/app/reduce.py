"""Reduced models of a scene: built offline from full-order runs, solved online like a scene.

Offline (:func:`build`): build the scene's model; if it has [inverse], unload the imaged mesh
once (at the default parameters); run the full model along its load path at every training
point — a seeded Sobol' sample of the scene's [parameters] box, and the load scales — and collect
snapshots; make the basis; save it with the start state, the reference mesh nodes, the training
points, the offline timings, and the scene itself with every file it reads (mesh, Φs0 data), so
that the model file is all ``lungmech rom solve model.npz --set name=value`` needs.

Online: :func:`embedded_scene` gives the scene stored in a model file, :func:`load` the
:class:`~lungmech.rom.reduced.ReducedModel` (``solve(mu)``), and :func:`reduced_order` the
``prepare`` step of :func:`lungmech.app.run.run`, so a reduced run writes the same outputs as a
full one.
"""

from __future__ import annotations

import contextlib
import copy
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path

from mpi4py import MPI

import numpy as np

from lungmech import checks
from lungmech.app import scene as scenes
from lungmech.app.run import IMAGED_AT_DEFAULTS, Scale, body_name, build_model, check_scale
from lungmech.app.scene import ImageLabel, Scene, differences, physics
from lungmech.errors import ModelFileError, ParameterError
from lungmech.fem.parameters import Parameters
from lungmech.fem.parametric import FullOrderModel
from lungmech.fem.quantities import Probe
from lungmech.fem.solver import NewtonSolver
from lungmech.fem.start import StartReport
from lungmech.lung.inverse import unloaded_reference
from lungmech.mesh import nodes
from lungmech.mesh.files import companions
from lungmech.parallel import on_root
from lungmech.parallel.destination import hold_signals_until_swap, output_file
from lungmech.parallel.layout import layout
from lungmech.registration.image import companions as image_companions
from lungmech.rom import ecsw, indicator, store
from lungmech.rom.basis import Basis, enrich
from lungmech.rom.greedy import Greedy, greedy
from lungmech.rom.modes import modal_basis, with_modal_derivatives
from lungmech.rom.pod import pod, snapshots
from lungmech.rom.polynomial import polynomial_basis
from lungmech.rom.reduced import ReducedModel

KINDS = ("pod", "modal", "modal+derivatives", "polynomial", "pod+modal")
HYPER = ("ecsw",)  # hyper-reductions


def build(
    scene: Scene,
    path: str | Path,
    kind: str = "pod",
    size: int = 20,
    scales: Sequence[Scale] | None = None,
    inner: str = "mass",
    order: int = 2,
    density: float = 1.0,
    comm: MPI.Comm = MPI.COMM_WORLD,
    samples: int | None = None,
    seed: int = 0,
    hyper: str | None = None,
    hyper_tolerance: float = 1e-4,
    tolerance: float | None = None,
) -> dict:
    """Build a reduced model of ``scene`` and save it to ``path`` (.npz); returns its summary.

    ``kind``: pod (of full runs at the training points), modal (K y = λ M y at the start
    state), modal+derivatives, polynomial (of ``order``), or pod+modal (enriched). ``size`` caps
    the number of vectors (POD may keep fewer: only directions above its noise level). The
    training points are ``samples`` Sobol' points of the scene's parameter box (``seed``;
    default 8 when the scene has [parameters], else its one point) times the load ``scales``
    (default 0.5, 1, 1.5 without parameters, 1 with them).
    ``hyper`` = "ecsw" hyper-reduces it (:mod:`lungmech.rom.ecsw`): a second pass over the
    training runs samples the cells that reproduce the reduced forces of every Newton iterate to
    ``hyper_tolerance`` (τ), and the sample is saved with the basis.
    ``tolerance`` trains the POD basis greedily (:mod:`lungmech.rom.greedy`) instead of at
    fixed points: full solves are added at the candidate — of ``samples`` Sobol' points (default
    32) — where the reduced model's error indicator is largest, until it meets ``tolerance``
    (relative energy-norm error) there; ``size`` then caps the basis. Hyper-reduced, the greedy
    judges the hyper-reduced model itself (an ECSW sample per round, from every Newton iterate
    of its full solves), and its last sample is the model's.
    ``path`` is checked before any work (an existing file is replaced only if it is a lungmech
    reduced model) and written only when the build succeeds.
    """
    if kind not in KINDS:
        raise ParameterError(f"basis kind must be one of {', '.join(KINDS)} (got {kind!r})")
    if hyper is not None and hyper not in HYPER:
        raise ParameterError(f"hyper-reduction must be one of {', '.join(HYPER)} (got {hyper!r})")
    checks.real("ECSW tolerance", hyper_tolerance)
    if not 0 < hyper_tolerance < 1:
        raise ParameterError(f"the ECSW tolerance must lie in (0, 1) (got {hyper_tolerance!r})")
    if isinstance(size, bool) or not (isinstance(size, int) and size >= 1):
        raise ParameterError(f"basis size must be a positive integer (got {size!r})")
    if tolerance is not None:
        _check_greedy(scene, kind, scales, tolerance)
    if scales is None:
        scales = (1.0,) if scene.parameters else (0.5, 1.0, 1.5)
    if not scales:
        raise ParameterError("give at least one training load scale")
    for scale in scales:
        check_scale(scene, scale)
    box = Parameters(scene.parameters)
    if samples is None:
        samples = (32 if tolerance is not None else 8) if box else 1
    checks.integer("training samples", samples, minimum=1)
    checks.integer("training seed", seed, minimum=0)
    training = box.sample(samples, seed) if box else [{}]
    path = store._suffix(path)
    with output_file(path, comm, inputs=scene.inputs, ours=store.is_model) as staging:
        hyper = (hyper, hyper_tolerance) if hyper else None
        return _build(scene, staging, kind, size, scales, training, inner, order, density, comm, hyper, tolerance)


def _check_greedy(scene: Scene, kind: str, scales, tolerance) -> None:
    """Refuse a greedy build it cannot do, in one line."""
    checks.real("tolerance", tolerance)
    if not 0 < tolerance < 1:
        raise ParameterError(f"the tolerance (a relative energy-norm error) must lie in (0, 1) (got {tolerance!r})")
    if not scene.parameters:
        raise ParameterError(
            "--tolerance trains over the scene's [parameters] box, and this scene has none: add [parameters] "
            "(e.g. a load amplitude), or give --size"
        )
    if kind != "pod":
        raise ParameterError(f"--tolerance trains a POD basis (got --basis {kind})")
    if scales is not None:
        raise ParameterError(
            "--tolerance trains at the scene's loads over its [parameters] box; put a load's amplitude in "
            "[parameters] instead of giving --scales"
        )


def _build(
    scene: Scene,
    path: Path,
    kind: str,
    size: int,
    scales,
    training: list[dict],
    inner: str,
    order: int,
    density: float,
    comm: MPI.Comm,
    hyper: tuple[str, float] | None,
    tolerance: float | None,
) -> dict:
    timings = {}
    tic = time.perf_counter()
    model = build_model(scene, comm)
    where = layout(model.space)  # its dof order stays valid when [inverse] moves the nodes
    node_space, node_order = nodes.displacement_space(model.geometry.mesh)
    solver = NewtonSolver(model, scene.newton)
    timings["build_and_compile"] = time.perf_counter() - tic
    tic = time.perf_counter()
    if scene.inverse is not None:
        unloaded_reference(model, scene.stepping.start, scene.inverse, solver=solver)
    else:
        model.set_time(scene.stepping.start)
    start = model.state.x.array.copy()
    timings["inverse"] = time.perf_counter() - tic

    parts: list[Basis] = []
    trained = modes = None
    if tolerance is not None:
        full = FullOrderModel(model, scene.stepping, solver=solver, probes=scene.output.probes, start=start)
        judged = hyper[1] if hyper is not None else None  # a hyper-reduced model is judged as itself
        trained = greedy(full, training, tolerance, size=size, inner=inner, timings=timings, hyper=judged)
        training, modes = trained.training, trained.modes
        parts.append(trained.basis)
    elif kind in ("pod", "pod+modal"):
        tic = time.perf_counter()
        data = snapshots(model, scene.stepping, scales, solver=solver, start=start, parameters=training)
        timings["snapshots"] = time.perf_counter() - tic
        tic = time.perf_counter()
        source = {"scales": _plain(scales), "training": training}
        modes = pod(model, data, inner=inner, source=source)
        parts.append(modes.truncate(min(size, modes.size)))
        timings["svd"] = time.perf_counter() - tic
    if kind in ("modal", "modal+derivatives", "pod+modal"):
        tic = time.perf_counter()
        eigenmodes = modal_basis(model, size, density=density)
        parts.append(with_modal_derivatives(model, eigenmodes) if kind == "modal+derivatives" else eigenmodes)
        timings["eigensolve"] = time.perf_counter() - tic
    if kind == "polynomial":
        tic = time.perf_counter()
        parts.append(polynomial_basis(model, order, inner=inner))
        timings["basis"] = time.perf_counter() - tic
    basis = enrich(model, *parts) if len(parts) > 1 else parts[0]
    basis = basis.truncate(min(size, basis.size)) if kind != "modal+derivatives" else basis

    arrays = {"start": where.gather(start[: basis.vectors.shape[0]])}  # canonical, on rank 0 (None elsewhere)
    enrichment = indicator.enrichment(basis, modes if kind == "pod" and basis.kind == "pod" else None)
    arrays["enrichment"] = where.gather(enrichment)
    hyper_summary = None
    if hyper is not None:
        sample = trained.sample if trained is not None else None  # the greedy's, of this basis and W
        sample = sample or ecsw.train(
            model,
            replace(basis, vectors=np.hstack([basis.vectors, enrichment])),  # W's residual is sampled too
            solver,
            lambda: snapshots(model, scene.stepping, scales, solver=solver, start=start, parameters=training),
            hyper[1],
            timings,
        )
        arrays |= {f"ecsw/{name}": data for name, data in sample.export(model.geometry.mesh).items()}
        cells = model.geometry.mesh.topology.index_map(model.geometry.mesh.topology.dim).size_global
        hyper_summary = {"method": hyper[0], "tolerance": hyper[1], "samples": sample.count(comm), "cells": cells}
    if scene.inverse is not None:
        arrays["reference_nodes"] = nodes.positions(node_space, node_order)
    extra = {
        "scene": str(Path(scene.source).resolve()) if scene.source else None,
        "title": scene.title,
        "imaged_fingerprint": where.fingerprint,
        "loads": len(scene.loads),
        "scales": _plain(scales),
        "training": training,
        "parameters": model.parameters.describe(),
        "offline_seconds": timings,
        "scene_table": scene.table,
        "files": _embedded_names(scene),
        "hyper": hyper_summary,
        "greedy": _greedy_summary(trained, tolerance, model.parameters),
    }
    arrays |= {f"file:{name}": data for name, data in _file_bytes(scene, comm).items()}
    hold_signals_until_swap()  # the model file is a collective write
    store.write(path, model, basis, extra=extra, arrays=arrays)
    return {
        "kind": basis.kind,
        "size": basis.size,
        "dofs": where.size,
        "values": basis.values.tolist(),
        "offline_seconds": timings,
        "hyper": hyper_summary,
        "greedy": extra["greedy"],
    }


def _greedy_summary(trained: Greedy | None, tolerance: float | None, parameters: Parameters) -> dict | None:
    """What the greedy training did, as plain values (an indicator of inf — the reduced solve
    failed there — as None)."""
    if trained is None:
        return None
    return {
        "tolerance": tolerance,
        "met": trained.met,
        "safety": trained.safety,
        "full_solves": len(trained.training),
        "rounds": [
            {
                "size": r.size,
                "point": r.point,
                "where": parameters.text(r.point),
                "indicator": r.indicator if np.isfinite(r.indicator) else None,
                "error": r.error,
            }
            for r in trained.rounds
        ],
    }


def reduced_order(path: str | Path, inside: bool = False) -> Callable[[Scene, MPI.Comm], ReducedModel]:
    """The ``model`` of :func:`lungmech.app.run.run` for the reduced model stored at ``path``: a
    function of the run's scene and communicator. ``inside``: the run's scene is the one the
    file holds (:func:`embedded_scene`), else it is checked to model the same physics."""
    return lambda scene, comm: _reduced(Path(path), build_model(scene, comm), scene, inside)


def load(path: str | Path, comm: MPI.Comm = MPI.COMM_WORLD) -> ReducedModel:
    """The reduced model stored at ``path``, self-contained: its scene and mesh come from the file.
    Collective."""
    with embedded_scene(path, comm) as scene:
        model = build_model(scene, comm)
    return _reduced(Path(path), model, scene, inside=True)


def _reduced(path: Path, model, scene: Scene, inside: bool) -> ReducedModel:
    """The reduced model of ``path`` on ``model`` (the scene's, just built on its mesh).
    ``inside``: ``scene`` is the file's own; otherwise it must model the physics of the file's
    scene. A model of a scene with [inverse] moves the mesh to the unloaded reference stored
    with it (found at the default parameters), and says so in every answer's start."""
    comm = model.geometry.mesh.comm
    metadata, arrays = store.read_on_root(path, comm)  # arrays on rank 0 only
    extra = metadata["extra"]
    if not inside:
        with embedded_scene(path, comm, content=(metadata, arrays)) as built:
            check_physics(path, physics(built), scene)
    where = layout(model.space)  # of the imaged mesh; its dof order survives moving the nodes
    if where.fingerprint != extra["imaged_fingerprint"]:
        raise ModelFileError(f"{path} was built for another mesh or discretisation than this scene's")
    probes = Probe(model.geometry.mesh, scene.output.probes) if scene.output.probes else ()  # in the image
    described = None
    if "reference_nodes" in arrays:  # the unloaded reference found offline
        imaged = model.geometry.volume()
        nodes.place_canonical(*nodes.displacement_space(model.geometry.mesh), arrays["reference_nodes"])
        described = StartReport(
            "equilibrium",
            IMAGED_AT_DEFAULTS.format(body=body_name(model)),
            details={"imaged_volume": imaged, "reference_volume": model.geometry.volume()},
        )
    basis, _, arrays = store.load(path, model, content=(metadata, arrays))  # checked on the moved mesh
    owned = basis.vectors.shape[0]
    model.state.x.array[:owned] = where.scatter(arrays["start"])
    model.state.x.scatter_forward()
    start = model.state.x.array.copy()
    model.set_time(scene.stepping.start)
    training = metadata["extra"].get("training", [])
    sample = _sample(model, metadata["extra"].get("hyper"), arrays)
    enrichment = where.scatter(arrays["enrichment"]) if "enrichment" in arrays else None
    return ReducedModel(
        model, basis, scene.stepping, scene.newton, start, probes, training, sample, enrichment, described
    )


def _sample(model, hyper: dict | None, arrays: dict) -> ecsw.Sample | None:
    """The ECSW sample stored with a hyper-reduced model (arrays on rank 0), placed on this mesh."""
    if hyper is None:
        return None
    mesh = model.geometry.mesh
    data = mesh.comm.bcast({name[len("ecsw/") :]: a for name, a in arrays.items() if name.startswith("ecsw/")})
    if "internal_cells" not in data or not all(f"{name}_weights" in data for name in ("internal", "strain_energy")):
        raise ModelFileError("the reduced model is damaged: its ECSW sample is incomplete; rebuild it")
    return ecsw.Sample.place(mesh, data, hyper["tolerance"])


def check_physics(path: Path, built: dict, scene: Scene) -> None:
    """Refuse a reduced model whose scene models other physics (``built``, its :func:`physics`)
    than ``scene`` (law, parameters, loads, boundaries, formulation, start), saying what differs."""
    if lines := differences(built, physics(scene)):
        shown = "; ".join(lines[:4]) + (f"; and {len(lines) - 4} more" if len(lines) > 4 else "")
        raise ModelFileError(
            f"{path} was built for other physics than this scene's: {shown}. Build a reduced model "
            "of this scene, or use --scale to change the loads' amplitude"
        )


def trained_range(extra: dict, scale) -> str | None:
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


def _plain(scales) -> list:
    return [np.asarray(s, dtype=float).tolist() for s in scales]


def _embedded_names(scene: Scene) -> dict[str, str]:
    """Where each file the scene reads goes inside the model file: the mesh (with its companions)
    under mesh/, a file of cell values (Φs0, κ, …) under data/<key>/."""
    names = {}
    if "file" in scene.geometry:
        mesh = Path(scene.geometry["file"])
        for part in [mesh, *(p for p in companions(mesh) if p.exists())]:
            names[f"mesh/{part.name}"] = str(part)
    for key, path in scenes.cell_data(scene.formulation).items():
        names[f"data/{key}/{path.name}"] = str(path)
    for parameter in scene.parameters:  # label images of regions, with their data files
        marker = getattr(parameter.region, "marker", None)
        if isinstance(marker, ImageLabel):
            data = [Path(marker.path).with_name(name) for name in image_companions(marker.path)]
            for part in [marker.path, *(d for d in data if d.exists())]:
                names[f"regions/{Path(part).name}"] = str(part)
    return names


def _file_bytes(scene: Scene, comm: MPI.Comm) -> dict[str, np.ndarray | None]:
    """The bytes of the scene's files (rank 0; None on the others)."""
    names = _embedded_names(scene)
    if comm.rank != 0:
        return dict.fromkeys(names)
    return {name: np.frombuffer(Path(source).read_bytes(), dtype=np.uint8) for name, source in names.items()}


@contextlib.contextmanager
def embedded_scene(
    path: str | Path, comm: MPI.Comm = MPI.COMM_WORLD, content: tuple[dict, dict] | None = None
) -> Iterator[Scene]:
    """The scene a model file holds, with its files unpacked into a private temporary folder for
    the duration of the block (rank 0 unpacks; the ranks must share that folder's file system).
    Collective. ``content``: what :func:`lungmech.rom.store.read_on_root` gave, when the caller
    has read the file already.

    The file is data: each embedded file's name must be one lungmech writes (:func:`embedded_name`),
    and it is created new inside the folder, never followed through a link; anything else refuses
    the model file before a byte is written.
    """
    metadata, arrays = content if content is not None else store.read_on_root(path, comm)
    extra = metadata["extra"]
    if "scene_table" not in extra:
        raise ModelFileError(f"{path} holds no scene (built before lungmech 0.2); name the scene after the model file")
    files = extra.get("files")
    if not isinstance(files, dict) or not isinstance(extra["scene_table"], dict):
        raise ModelFileError(f"'{path}' is damaged: its scene or its list of files is not a table")
    for name in files:
        embedded_name(path, name, arrays)
    folder = comm.bcast(tempfile.mkdtemp(prefix="lungmech-model-") if comm.rank == 0 else None)  # mode 0700
    try:

        def unpack() -> None:
            for name in files:
                target = Path(folder, *name.split("/"))
                target.parent.mkdir(parents=True, exist_ok=True)
                # O_EXCL | O_NOFOLLOW: a new file, not one a link points to (none can be there).
                flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW
                with os.fdopen(os.open(target, flags, 0o600), "wb") as stream:
                    stream.write(arrays[f"file:{name}"].tobytes())

        on_root(comm, unpack)
        table = copy.deepcopy(extra["scene_table"])
        for name, source in files.items():
            unpacked = str(Path(folder, *name.split("/")))
            if name.startswith("mesh/") and Path(str(source)).name == Path(table["geometry"].get("file", "")).name:
                table["geometry"]["file"] = unpacked
            if name.startswith("data/"):  # data/<key>/<file>: a file of cell values (Φs0, κ, …)
                table["formulation"][name.split("/")[1]] = unpacked
            for entry in table.get("parameters", {}).values():
                region = entry.get("region")
                if isinstance(region, dict) and Path(str(region.get("image", ""))).name == Path(str(source)).name:
                    region["image"] = unpacked
        yield scenes.parse(table, folder=Path(folder))
    except BaseException:
        # Not collective: a failure (or Ctrl-C) may have reached this rank alone, and a barrier
        # here would hang it; the folder is temporary, so rank 0 removes it as it can.
        if comm.rank == 0:
            shutil.rmtree(folder, ignore_errors=True)
        raise
    comm.barrier()  # every rank is done with the files
    if comm.rank == 0:
        shutil.rmtree(folder, ignore_errors=True)


_PLACES = {"mesh": 2, "regions": 2, "data": 3}  # where lungmech puts a scene's files, and the parts of their names


def embedded_name(path: str | Path, name: object, arrays: dict) -> None:
    """Refuse, in one line, a model file whose embedded file ``name`` is not one lungmech writes —
    ``mesh/<file>``, ``regions/<file>`` or ``data/<key>/<file>``, with plain names: relative, no ``..``, no empty part, no backslash or NUL — or has no bytes."""
    parts = name.split("/") if isinstance(name, str) else []
    plain = all(part not in ("", ".", "..") and "\\" not in part and "\0" not in part for part in parts)
    expected = _PLACES.get(parts[0]) if parts else None
    if not (plain and len(parts) == expected and (expected == 2 or parts[1].isidentifier())):
        raise ModelFileError(
            f"'{path}' is refused: it names an embedded file {name!r}, which is not a name lungmech writes "
            "(mesh/<file>, regions/<file>, data/<key>/<file>); a model file never writes outside its own folder"
        )
    if f"file:{name}" not in arrays:
        raise ModelFileError(f"'{path}' is damaged: it lists the embedded file '{name}' but holds no bytes for it")
