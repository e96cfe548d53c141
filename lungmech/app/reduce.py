"""Reduced models of a scene: built offline from full-order runs, solved online like a scene.

Offline (:func:`build`): build the scene's model; if it has [inverse], unload the imaged mesh
once; run the full model for each training load scale and collect snapshots; make the basis;
save it with the start state, the reference mesh nodes and the offline timings. Online
(:func:`reduced_order`): the ``prepare`` step of :func:`lungmech.app.run.run` that puts the stored
reference and start state in place and returns a :class:`ReducedSolver`, so a reduced run
writes the same outputs as a full one.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from functools import partial
from pathlib import Path

import numpy as np
from mpi4py import MPI

from lungmech.app.run import Scale, build_model, check_scale
from lungmech.app.scene import Scene, differences, physics
from lungmech.errors import ModelFileError, ParameterError
from lungmech.fem.solver import NewtonSolver
from lungmech.lung.inverse import unloaded_reference
from lungmech.mesh import nodes
from lungmech.parallel.destination import output_file
from lungmech.parallel.layout import layout
from lungmech.rom import store
from lungmech.rom.basis import Basis, enrich
from lungmech.rom.galerkin import ReducedSolver
from lungmech.rom.modes import modal_basis, with_modal_derivatives
from lungmech.rom.pod import pod, snapshots
from lungmech.rom.polynomial import polynomial_basis

KINDS = ("pod", "modal", "modal+derivatives", "polynomial", "pod+modal")


def build(
    scene: Scene,
    path: str | Path,
    kind: str = "pod",
    size: int = 20,
    scales: Sequence[Scale] = (0.5, 1.0, 1.5),
    inner: str = "mass",
    order: int = 2,
    density: float = 1.0,
    comm: MPI.Comm = MPI.COMM_WORLD,
) -> dict:
    """Build a reduced model of ``scene`` and save it to ``path`` (.npz); returns its summary.

    ``kind``: pod (of full runs at the load ``scales``), modal (K y = λ M y at the start
    state), modal+derivatives, polynomial (of ``order``), or pod+modal (enriched). ``size`` caps
    the number of vectors (POD may keep fewer: only directions above its noise level).
    ``path`` is checked before any work (an existing file is replaced only if it is a lungmech
    reduced model) and written only when the build succeeds.
    """
    if kind not in KINDS:
        raise ParameterError(f"basis kind must be one of {', '.join(KINDS)} (got {kind!r})")
    if isinstance(size, bool) or not (isinstance(size, int) and size >= 1):
        raise ParameterError(f"basis size must be a positive integer (got {size!r})")
    if not scales:
        raise ParameterError("give at least one training load scale")
    for scale in scales:
        check_scale(scene, scale)
    path = store._suffix(path)
    with output_file(path, comm, inputs=scene.inputs, ours=store.is_model) as staging:
        return _build(scene, staging, kind, size, scales, inner, order, density, comm)


def _build(
    scene: Scene, path: Path, kind: str, size: int, scales, inner: str, order: int, density: float, comm: MPI.Comm
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
    if kind in ("pod", "pod+modal"):
        tic = time.perf_counter()
        data = snapshots(model, scene.stepping, scales, solver=solver, start=start)
        timings["snapshots"] = time.perf_counter() - tic
        tic = time.perf_counter()
        parts.append(pod(model, data, inner=inner, size=size, source={"scales": _plain(scales)}))
        timings["svd"] = time.perf_counter() - tic
    if kind in ("modal", "modal+derivatives", "pod+modal"):
        tic = time.perf_counter()
        modes = modal_basis(model, size, density=density)
        parts.append(with_modal_derivatives(model, modes) if kind == "modal+derivatives" else modes)
        timings["eigensolve"] = time.perf_counter() - tic
    if kind == "polynomial":
        tic = time.perf_counter()
        parts.append(polynomial_basis(model, order, inner=inner))
        timings["basis"] = time.perf_counter() - tic
    basis = enrich(model, *parts) if len(parts) > 1 else parts[0]
    basis = basis.truncate(min(size, basis.size)) if kind != "modal+derivatives" else basis

    arrays = {"start": where.gather(start[: basis.vectors.shape[0]])}  # canonical, on rank 0 (None elsewhere)
    if scene.inverse is not None:
        arrays["reference_nodes"] = nodes.positions(node_space, node_order)
    extra = {
        "scene": str(Path(scene.source).resolve()) if scene.source else None,
        "title": scene.title,
        "physics": physics(scene),
        "imaged_fingerprint": where.fingerprint,
        "loads": len(scene.loads),
        "scales": _plain(scales),
        "offline_seconds": timings,
    }
    store.write(path, model, basis, extra=extra, arrays=arrays)
    return {
        "kind": basis.kind,
        "size": basis.size,
        "dofs": where.size,
        "values": basis.values.tolist(),
        "offline_seconds": timings,
    }


def reduced_order(path: str | Path):
    """The ``prepare`` of :func:`lungmech.app.run.run` for the reduced model stored at ``path``."""
    return partial(_prepare, Path(path))


def _prepare(path: Path, model, scene: Scene, folder: Path) -> tuple[ReducedSolver, dict | None]:
    metadata, arrays = store.read_on_root(path, model.geometry.mesh.comm)  # arrays on rank 0 only
    extra = metadata["extra"]
    check_physics(path, extra, scene)
    where = layout(model.space)  # of the imaged mesh; its dof order survives moving the nodes
    if where.fingerprint != extra["imaged_fingerprint"]:
        raise ModelFileError(f"{path} was built for another mesh or discretisation than this scene's")
    if "reference_nodes" in arrays:  # the unloaded reference found offline
        nodes.place_canonical(*nodes.displacement_space(model.geometry.mesh), arrays["reference_nodes"])
    del arrays  # rank 0's copy; load reads the file again and checks it against the moved mesh
    basis, _, arrays = store.load(path, model)
    owned = basis.vectors.shape[0]
    model.state.x.array[:owned] = where.scatter(arrays["start"])
    model.state.x.scatter_forward()
    model.set_time(scene.stepping.start)
    solver = ReducedSolver(model, basis, scene.newton, start=model.state.x.array.copy())
    return solver, {"reference": "from the reduced model"} if "reference_nodes" in arrays else None


def check_physics(path: Path, extra: dict, scene: Scene) -> None:
    """Refuse a reduced model made for other physics than ``scene``'s (law, parameters, loads,
    boundaries, formulation, start), saying what differs."""
    if "physics" not in extra:
        raise ModelFileError(f"{path} predates lungmech's physics check; rebuild it with 'lungmech rom build'")
    if lines := differences(extra["physics"], physics(scene)):
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
