"""A reduction's full training solves on an ensemble, kept in lungmech's cache.

The full load paths a reduced model is trained on — a greedy's rounds, a fixed Sobol' sample —
are independent solves: :class:`EnsemblePaths` hands them to an ensemble
(:mod:`lungmech.parallel.ensemble`: serially, in groups of ranks, or on an engine's workers),
each as a :class:`PathTask` that any process runs alike (:func:`training_path`: the scene's full
model, as :func:`lungmech.app.reduce.build` trains it, solved at μ). A solved path travels
through the cache (:mod:`lungmech.app.cache`, kind "paths"): its snapshots, its states at the
output times and, for a hyper-reduction, its Newton iterates, in the canonical dof order
(:func:`lungmech.rom.load_paths.canonical`), named by the SHA-256 of what determines them — the
scene's physics, load path and solver settings, μ, the load scale, the code. So a build that
was interrupted finds every path it solved before, and the next build of the same scene with
another basis size, τ or tolerance too. An engine's workers on other machines need the cache
on a file system they share.

Only the first rank of the build reads an entry, and scatters it to the ranks of the build's
model (:func:`lungmech.rom.load_paths.placed`); paths solved on the build's own ranks are the
same to the last bit as solved in place.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial
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
from lungmech.fem.start import one_state
from lungmech.parallel.ensemble import Ensemble, Serial
from lungmech.parallel.layout import Layout, layout
from lungmech.rom.load_paths import LoadPath, Run, canonical, placed, solve_path

__all__ = ["EnsemblePaths", "PathTask", "forget", "image_of", "training_model", "training_path"]

log = logging.getLogger("lungmech")

KIND = "paths"  # the cache's kind of entry
TRAINING = (*ANSWERING, "app/training_paths.py")  # the code a training path depends on


@dataclass(frozen=True)
class PathTask:
    """The full load path of the scene (file ``scene``) at ``values`` μ with the loads' change
    scaled by ``scale``, with its Newton iterates when ``iterates``."""

    scene: str
    values: Mapping[str, float]
    scale: float | tuple[float, ...] = 1.0
    iterates: bool = False


def image_of(scene: Scene) -> Image | None:
    """How a scene's reduced models place its mesh: a scene with [inverse] and parameters is
    imaged at the start, and its reduced models solve the image's motion at every μ
    (:mod:`lungmech.rom.imaged`); without parameters its one reference is found once."""
    return Image.motion(scene.stepping.start) if scene.inverse is not None and scene.parameters else None


def training_model(scene: Scene, comm: MPI.Comm) -> FullOrderModel:
    """The scene's full model as its reduced models are trained on it: an imaged body's on its
    fixed image, its reference found at every μ; another's from its equilibrium at the
    defaults. Collective."""
    image = image_of(scene)
    model = build_model(scene, comm, image=image)
    return full_order_model(scene, comm, start="inverse_motion" if image else "defaults", model=model)


def entry(scene: Scene, task: PathTask) -> str:
    """The cache entry's name of ``task``'s path."""
    answer = content(scene, Task(task.scene, task.values, Discretisation.of(scene)))
    scale = np.asarray(task.scale, dtype=float).tolist()
    return key(
        answer | {"what": "training path", "scale": scale, "iterates": task.iterates, "code": code_version(TRAINING)}
    )


def training_path(
    task: PathTask, comm: MPI.Comm, cache: str, full: tuple[FullOrderModel, Layout] | None = None
) -> dict:
    """Solve ``task``'s path on ``comm`` into the cache folder ``cache``, unless it is there
    already; returns its entry's name and whether it was ``kept`` before. ``full``: the
    training model itself and its layout, on ``comm`` (a serial ensemble on the build's
    ranks), else one is built (and kept for the process's next task). Collective: the work of
    an ensemble."""
    kept = Cache(cache, comm)
    scene = scenes.load(task.scene)
    name = entry(scene, task)
    if kept.has(KIND, f"{name}.npz"):
        return {"entry": name, "kept": True}
    model, where = _model(scene, task, comm) if full is None else full
    try:
        path = solve_path(model, task.values, one_state(model.start, model.model), task.iterates, task.scale)
    finally:
        model.reset()
    kept.write_arrays(KIND, name, canonical(path, where))
    solution = path.solution
    return {"entry": name, "kept": False, "seconds": solution.seconds, "newton_iterations": solution.newton_iterations}


class _Last:
    """The training model of a process's last scene, on its communicator, and its layout."""

    scene: str | None = None
    comm: MPI.Comm | None = None
    model: tuple[FullOrderModel, Layout] | None = None


def forget() -> None:
    """Drop the training model :func:`training_path` keeps (before its communicator is freed)."""
    _Last.scene = _Last.comm = _Last.model = None


def _model(scene: Scene, task: PathTask, comm: MPI.Comm) -> tuple[FullOrderModel, Layout]:
    if _Last.model is None or _Last.scene != task.scene or _Last.comm is not comm:
        _Last.model = None
        full = training_model(scene, comm)
        _Last.scene, _Last.comm, _Last.model = task.scene, comm, (full, layout(full.model.space))
    return _Last.model


class EnsemblePaths:
    """The :data:`~lungmech.rom.load_paths.Paths` of a training on ``ensemble``: the full load
    paths of the scene (file ``scene``) solved as :class:`PathTask`\\ s into lungmech's cache
    folder ``cache`` and placed on ``full`` (the build's own training model). Collective over
    ``full``'s communicator (an engine's pool: one rank)."""

    def __init__(self, scene: str, full: FullOrderModel, ensemble: Ensemble, cache: str) -> None:
        self.scene, self.full, self.ensemble, self.cache = scene, full, ensemble, cache
        self.comm = full.model.geometry.mesh.comm
        self.where = layout(full.model.space)
        self.solved = self.kept = 0  # paths solved by this build, and found in the cache

    def __call__(self, runs: Sequence[Run], iterates: bool) -> list[LoadPath]:
        tasks = [PathTask(self.scene, dict(point), _scale(scale), iterates) for point, scale in runs]
        here = isinstance(self.ensemble, Serial) and MPI.Comm.Compare(self.ensemble.comm, self.comm) != MPI.UNEQUAL
        work = partial(training_path, cache=self.cache, full=(self.full, self.where) if here else None)
        outcomes = self.ensemble.map(work, tasks, lambda line: log.info("training: %s", line))
        for (point, _), outcome in zip(runs, outcomes, strict=True):
            if outcome.failed is not None:
                text = self.full.parameters.text(self.full.parameters.values(point))
                raise SolverError(f"the full training solve at {text} failed: {outcome.failed}")
        kept = Cache(self.cache, self.comm)
        found = []
        for outcome in outcomes:
            value = outcome.value
            assert value is not None  # (a failure was raised above)
            arrays = kept.read_arrays(KIND, value["entry"])
            if self.comm.bcast(arrays is None if self.comm.rank == 0 else None, root=0):
                lost = kept.path(KIND, f"{value['entry']}.npz")
                raise ParameterError(f"cache: the training path {lost} it had just kept cannot be read")
            found.append(placed(arrays, self.where, iterates))
            self.kept += bool(value["kept"])
            self.solved += not value["kept"]
        return found


def _scale(scale: float | Sequence[float]) -> float | tuple[float, ...]:
    """A load scale as plain numbers: one factor, or one per load."""
    if np.ndim(scale) == 0:
        return float(cast(float, scale))
    return tuple(float(s) for s in cast(Sequence[float], scale))
