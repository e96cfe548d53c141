"""One solve of many, and its answer: the unit of work of a trade and of the ensembles that run it
(:mod:`lungmech.parallel.ensemble`: :func:`solved` is the work every mode runs alike).

A :class:`Task` is serialisable — the scene's file, the parameter values μ, the
discretisation, the output times, whether its fields are kept — so that any process can run it
the same way. Its answer is what a trade compares (:mod:`lungmech.trade.quantities`): the
outputs at the output times, the start's volume, the solve's time, or why the solve failed.
Full-order answers are kept in lungmech's cache (:mod:`lungmech.app.cache`) under the task's
content (:func:`content`): the scene's physics, its load path and solver settings, its probes,
μ, the discretisation and the code's version; with ``fields``, beside them the start state and
the last output's as full fields in the canonical dof order (:func:`kept_fields`, for the
energy-norm errors of :mod:`lungmech.app.field_errors`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from mpi4py import MPI

import numpy as np

from lungmech.app import scene as scenes
from lungmech.app.cache import Cache, code_version, key
from lungmech.app.ladder import Discretisation, at
from lungmech.app.scene import Scene, file_sha256, physics
from lungmech.errors import LungmechError
from lungmech.fem.parametric import ParametricModel, Step
from lungmech.parallel.ensemble import Kept
from lungmech.parallel.layout import layout
from lungmech.parallel.owned import owned_values

__all__ = ["Task", "answer", "content", "entry", "forget", "kept_answer", "kept_fields", "solved"]


@dataclass(frozen=True)
class Task:
    """Solve the scene (file ``scene``) at ``values`` μ, discretised as ``discretisation``,
    with outputs at ``times`` (None: the scene's output times, the whole path); ``fields``:
    keep the start state and the last output's too."""

    scene: str
    values: Mapping[str, float]
    discretisation: Discretisation
    times: tuple[float, ...] | None = None
    fields: bool = False

    def to_json(self) -> dict:
        return {
            "scene": self.scene,
            "values": dict(self.values),
            "discretisation": self.discretisation.content(),
            "times": None if self.times is None else list(self.times),
            "fields": self.fields,
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Task:
        times = data.get("times")
        return cls(
            str(data["scene"]),
            {k: float(v) for k, v in data["values"].items()},
            Discretisation(**data["discretisation"]),
            None if times is None else tuple(float(t) for t in times),
            bool(data.get("fields", False)),
        )


def content(scene: Scene, task: Task) -> dict:
    """What a full-order answer depends on (its cache key is the SHA-256 of this)."""
    table = scene.table
    mesh_file = scene.geometry.get("file")
    return {
        "physics": physics(scene),
        "mesh_file": None if mesh_file is None else file_sha256(mesh_file),
        "stepping": table.get("stepping", {}),
        "newton": table.get("newton", {}),
        "probes": [list(map(float, p)) for p in scene.output.probes],
        "values": {name: float(value) for name, value in sorted(task.values.items())},
        "discretisation": task.discretisation.content(),
        "times": None if task.times is None else [float(t) for t in task.times],
        "code": code_version(),
    }


def answer(
    model: ParametricModel,
    values: Mapping[str, float],
    times: Sequence[float] | None,
    fields: list[np.ndarray] | None = None,
) -> dict:
    """``model.solve(values, times=times)`` as numbers (SI units: m³, m, J, s; the scalar loads
    and the formulation's averages under ``outputs``, every output's unit under ``units``); a
    solve that fails is an answer too: ``failed`` says why in one line, and its outputs are
    absent. Given a list ``fields``, a solve that succeeds appends to it the start state and
    the last output's as full fields (the fem model's owned entries; a reduced model's
    x₀ + V q: O(mesh)). Collective."""
    dofs = _dofs(model)
    began = time.perf_counter()
    started: list[tuple[np.ndarray, float]] = []

    def keep_start(step: Step) -> None:
        if step.phase == "start":
            started.append((step.state(), step.time))

    try:
        watch = keep_start if fields is not None else None
        solution = model.solve(dict(values), times=None if times is None else list(times), on_step=watch)
    except (LungmechError, RuntimeError, ArithmeticError) as error:  # PETSc's errors are RuntimeErrors
        why = str(error).splitlines()[0] if str(error) else type(error).__name__
        origin = "solver" if isinstance(error, LungmechError) else "library"  # lungmech's own verdict, or PETSc's
        return {"failed": why, "error": origin, "seconds": time.perf_counter() - began, "dofs": dofs}
    seconds = time.perf_counter() - began
    if fields is not None:
        fields += [_field(model, *started[0]), _field(model, solution.states[-1], float(solution.times[-1]))]
    outputs = solution.outputs
    start = solution.start.details if solution.start is not None else {}
    others = [name for name in outputs if name.startswith(("loads/", "averages/"))]
    return {
        "failed": None,
        "seconds": seconds,
        "dofs": dofs,
        "times": np.asarray(solution.times, dtype=float).tolist(),
        "volume": np.asarray(outputs["volume"], dtype=float).tolist(),
        "strain_energy": np.asarray(outputs["strain_energy"], dtype=float).tolist(),
        "probes": np.asarray(outputs["probes"], dtype=float).tolist() if "probes" in outputs else [],
        "start_volume": float(start["volume"]) if "volume" in start else None,
        "start": None
        if solution.start is None
        else {"kind": solution.start.kind, "description": solution.start.description},
        "newton_iterations": int(solution.newton_iterations),
        "indicator": solution.indicator,
        "outputs": {name: np.asarray(outputs[name], dtype=float).tolist() for name in others},
        "units": {name: _unit(solution.units, name) for name in ("volume", "strain_energy", *others)},
    }


def _field(model: ParametricModel, state: np.ndarray, at: float) -> np.ndarray:
    """The full field of a solution's ``state`` at time ``at``: the fem model's owned entries."""
    model.fields(state, at)
    return owned_values(model.model.state)


def _unit(units: Mapping[str, str], name: str) -> str:
    """An output's unit: its own, or its kind's ("loads/pleural": a load's, Pa)."""
    return units.get(name) or units[name.split("/")[0]]


def _dofs(model: ParametricModel) -> int:
    """The full model's unknowns (a reduced model's full model's, on its body alone too)."""
    if full_size := getattr(model, "full_size", None):
        return int(full_size["dofs"])
    space = model.model.state.function_space
    return int(space.dofmap.index_map.size_global * space.dofmap.index_map_bs)


def entry(scene: Scene, task: Task) -> str:
    """The name of ``task``'s entries in the cache: its answer ("answers") and its fields ("fields")."""
    return key(content(scene, task))


def kept_answer(cache: Cache, scene: Scene, task: Task, model: Callable[[], ParametricModel]) -> tuple[dict, bool]:
    """The full-order answer to ``task`` from the cache, or solved by ``model()`` (built only
    then) and kept — a failure lungmech's solver reports too (the same task fails the same
    way), not a library's error (out of memory, say: on more ranks it may pass) —; and whether
    it was kept before. A task with ``fields`` keeps them too (:func:`kept_fields`): an answer
    kept without them is solved again. Collective."""
    name = entry(scene, task)
    kept = cache.read_json("answers", name)
    if kept is not None and (not task.fields or kept["failed"] is not None or cache.array_names("fields", name)):
        return kept, True
    built = model()
    fields: list[np.ndarray] | None = [] if task.fields else None
    found = answer(built, task.values, task.times, fields)
    if found["failed"] is None or found.get("error") == "solver":  # not a failure of this process's means
        if fields:
            cache.write_arrays("fields", name, kept_fields(built, fields))
        cache.write_json("answers", name, found)
    return found, False


def kept_fields(model: ParametricModel, fields: Sequence[np.ndarray]) -> dict[str, np.ndarray] | None:
    """The start and last states ``fields`` (owned entries) of a full model as the cache keeps
    them: in the canonical dof order (:mod:`lungmech.parallel.layout`), with the mesh's
    fingerprint and the ranks they were solved on; on rank 0 (None on the others). Collective."""
    where = layout(model.model.space)
    start, end = (where.gather(field) for field in fields)
    if where.comm.rank != 0:
        return None
    assert start is not None and end is not None  # (gathered on rank 0)
    return {"fingerprint": np.array(where.fingerprint), "start": start, "end": end, "ranks": np.array(where.comm.size)}


def solved(task: Task, comm: MPI.Comm, cache: str) -> dict:
    """The full-order answer to ``task`` on ``comm``, from lungmech's cache folder ``cache`` or
    solved and kept there (``kept`` says which): the work of an ensemble
    (:mod:`lungmech.parallel.ensemble`). The model of a process's last scene and
    discretisation is kept for its next task. Collective."""
    kept = Cache(cache, comm)
    scene = scenes.load(task.scene)
    found, was_kept = kept_answer(kept, scene, task, lambda: _model(scene, task, kept, comm))
    return found | {"kept": was_kept}


_LAST: Kept[ParametricModel] = Kept()  # the model of a process's last scene and discretisation


def _model(scene: Scene, task: Task, cache: Cache, comm: MPI.Comm) -> ParametricModel:
    from lungmech.app.run import full_order_model

    which = entry(scene, Task(task.scene, {}, task.discretisation))  # the scene's content, not its path
    return _LAST.get(
        which, comm, lambda: full_order_model(at(scene, task.discretisation, cache, comm), comm, start="inverse_motion")
    )


def forget() -> None:
    """Drop the model :func:`solved` keeps (before its communicator is freed, say)."""
    _LAST.forget()
