"""A reduction's full training solves on an ensemble, kept in lungmech's cache.

The full load paths a reduced model is trained on — a greedy's rounds, a fixed Sobol' sample —
are independent solves: :class:`EnsemblePaths` hands them to an ensemble
(:mod:`lungmech.parallel.ensemble`: serially, in groups of ranks, or on an engine's workers),
each as a :class:`PathTask` that any process runs alike (:func:`training_path`: the scene's full
model, as :func:`lungmech.app.reduce.build` trains it, solved at μ). A solved path travels
through the cache (:mod:`lungmech.app.cache`, kind "paths"): its snapshots, its states at the
output times and, for a hyper-reduction, its Newton iterates, in the canonical dof order
(:func:`lungmech.rom.load_paths.canonical`), named by the SHA-256 of what determines them — the
scene's physics, mesh file, load path and solver settings, μ, the load scale, the code. So a
build that was interrupted finds every path it solved before, and the next build of the same
scene with another basis size or tolerance too; a hyper-reduction, which needs the iterates,
solves again a path kept without them, and keeps it with them. The build names each path from
the scene it solves; a worker that reads the scene's file refuses it if it changed since. An
engine's workers on other machines need the cache on a file system they share.

Only the first rank of the build reads an entry, and scatters it to the ranks of the build's
model (:func:`lungmech.rom.load_paths.placed`); a path solved on as many ranks is the same to
the last bit as solved in place (each entry records its ranks). A path is gathered whole on the
first rank that writes it, as a model file's basis is.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import cast

from mpi4py import MPI

import numpy as np

from lungmech.app import scene as scenes
from lungmech.app.answers import Task, content
from lungmech.app.cache import ANSWERING, Cache, code_version, key
from lungmech.app.ladder import Discretisation
from lungmech.app.run import build_model, full_order_model
from lungmech.app.scene import Scene
from lungmech.errors import ParameterError, SolverError
from lungmech.fem.parametric import FullOrderModel
from lungmech.fem.placement import Image
from lungmech.parallel.ensemble import Ensemble, Kept
from lungmech.parallel.layout import Layout, layout
from lungmech.rom.load_paths import LoadPath, Run, canonical, placed, relative_to, solve_path

__all__ = [
    "EnsemblePaths",
    "PathTask",
    "entry",
    "forget",
    "image_of",
    "scene_key",
    "training_model",
    "training_path",
]

log = logging.getLogger("lungmech")

KIND = "paths"  # the cache's kind of entry
TRAINING = (*ANSWERING, "app/training_paths.py")  # the code a training path depends on


@dataclass(frozen=True)
class PathTask:
    """The full load path of the scene (file ``scene``) at ``values`` μ with the loads' change
    scaled by ``scale``, with its Newton iterates when ``iterates``; ``entry``: its name in the
    cache, as the build named it from the scene it solves (:func:`entry`)."""

    scene: str
    values: Mapping[str, float]
    scale: float | tuple[float, ...]
    iterates: bool
    entry: str


def image_of(scene: Scene) -> Image | None:
    """How a scene's reduced models place its mesh: a scene with [inverse] and parameters is
    imaged at the start, and its reduced models solve the image's motion at every μ
    (:mod:`lungmech.rom.imaged`); without parameters its one reference is found once."""
    return Image.motion(scene.stepping.start) if scene.inverse is not None and scene.parameters else None


def training_model(scene: Scene, comm: MPI.Comm) -> tuple[FullOrderModel, Layout]:
    """The scene's full model as its reduced models are trained on it — an imaged body's on its
    fixed image, its reference found at every μ; another's from its equilibrium at the
    defaults (a scene with [inverse] moved to its reference then) — and the canonical layout of
    its mesh as built, before a start moves it: the mesh a model file and a kept path name by
    its fingerprint. Collective."""
    image = image_of(scene)
    model = build_model(scene, comm, image=image)
    where = layout(model.space)
    return full_order_model(scene, comm, start="inverse_motion" if image else "defaults", model=model), where


def scene_key(scene: Scene) -> str:
    """What a scene's training paths depend on but μ and the load scale: its physics, its mesh
    file, its load path and solver settings, and the code (not its probes or output times: a
    path's snapshots and states are the same without them)."""
    answer = content(scene, Task(str(scene.source), {}, Discretisation.of(scene)))
    kept = {name: value for name, value in answer.items() if name not in ("probes", "values", "times", "code")}
    return key(kept | {"what": "training path", "code": code_version(TRAINING)})


def entry(scene: str, values: Mapping[str, float], scale: float | Sequence[float]) -> str:
    """The cache entry's name of the path at ``values`` μ and load ``scale`` of the scene whose
    :func:`scene_key` is ``scene``. One entry whether or not it holds the Newton iterates (a
    path solved with them serves a build without)."""
    point = {name: float(value) for name, value in sorted(values.items())}
    return key({"scene": scene, "values": point, "scale": np.asarray(scale, dtype=float).tolist()})


def training_path(
    task: PathTask, comm: MPI.Comm, cache: str, full: tuple[FullOrderModel, Layout] | None = None
) -> dict:
    """Solve ``task``'s path on ``comm`` into the cache folder ``cache``, unless it is there
    already (with its iterates, if asked for; an unreadable entry is solved again); returns its
    entry's name and whether it was ``kept`` before. ``full``: the build's own training model
    and its layout, on ``comm`` (a serial ensemble on the build's ranks); else the scene is read
    from its file — refused if it is no longer the scene the build named the task from — and
    its model built (and kept for the process's next task). Collective: the work of an
    ensemble."""
    kept = Cache(cache, comm)
    names = kept.array_names(KIND, task.entry)
    if names is not None and (not task.iterates or "iterates" in names):
        return {"entry": task.entry, "kept": True}
    if full is None:
        scene = scenes.load(task.scene)
        named = scene_key(scene)
        if entry(named, task.values, task.scale) != task.entry:
            raise ParameterError(
                f"scene '{task.scene}' is not the scene the build read (changed since, or made in Python): "
                "build again from the file"
            )
        full = _LAST.get(named, comm, lambda: training_model(scene, comm))
    model, where = full
    try:
        path = solve_path(model, task.values, relative_to(model), task.iterates, task.scale)
    finally:
        model.reset()
    kept.write_arrays(KIND, task.entry, canonical(path, where))
    solution = path.solution
    return {
        "entry": task.entry,
        "kept": False,
        "seconds": solution.seconds,
        "newton_iterations": solution.newton_iterations,
    }


_LAST: Kept[tuple[FullOrderModel, Layout]] = Kept()  # the training model of a process's last scene


def forget() -> None:
    """Drop the training model :func:`training_path` keeps (before its communicator is freed)."""
    _LAST.forget()


class EnsemblePaths:
    """The :data:`~lungmech.rom.load_paths.Paths` of a training on ``ensemble``: the full load
    paths of ``scene`` (read from its file) solved as :class:`PathTask`\\ s into lungmech's
    cache folder ``cache`` and placed on ``full``, the build's own training model of it, whose
    canonical layout is ``where``. Collective over ``full``'s communicator (an engine's pool:
    one rank)."""

    def __init__(self, scene: Scene, full: FullOrderModel, where: Layout, ensemble: Ensemble, cache: str) -> None:
        if scene.source is None:
            raise ParameterError("an ensemble solves a scene from its file: give the scene as a file")
        self.scene, self.key = str(Path(scene.source).resolve()), scene_key(scene)
        self.full, self.where, self.ensemble, self.cache = full, where, ensemble, cache
        self.comm = full.model.geometry.mesh.comm
        self.solved = self.kept = 0  # paths solved by this build, and found in the cache

    def __call__(self, runs: Sequence[Run], iterates: bool) -> list[LoadPath]:
        tasks = [
            PathTask(self.scene, dict(point), _scale(scale), iterates, entry(self.key, point, scale))
            for point, scale in runs
        ]
        here = self.ensemble.runs_here(self.comm)  # then on the build's own model
        work = partial(training_path, cache=self.cache, full=(self.full, self.where) if here else None)
        outcomes = self.ensemble.map(work, tasks, lambda line: log.info("training: %s", line))
        for (point, _), outcome in zip(runs, outcomes, strict=True):
            if outcome.failed is not None:
                text = self.full.parameters.text(self.full.parameters.values(point))
                raise SolverError(f"the full training solve at {text} failed: {outcome.failed}")
        kept = Cache(self.cache, self.comm)
        found = []
        for task, outcome in zip(tasks, outcomes, strict=True):
            value = outcome.value
            assert value is not None  # (a failure was raised above)
            arrays = kept.read_arrays(KIND, task.entry)
            if self.comm.bcast(arrays is None if self.comm.rank == 0 else None, root=0):
                lost = kept.path(KIND, f"{task.entry}.npz")
                raise ParameterError(f"cache: the training path {lost} was removed or damaged during the build")
            found.append(placed(arrays, self.where, iterates))
            self.kept += bool(value["kept"])
            self.solved += not value["kept"]
        return found


def _scale(scale: float | Sequence[float]) -> float | tuple[float, ...]:
    """A load scale as plain numbers: one factor, or one per load."""
    if np.ndim(scale) == 0:
        return float(cast(float, scale))
    return tuple(float(s) for s in cast(Sequence[float], scale))
