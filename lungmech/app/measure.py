"""One candidate of a trade measured in a process of its own: its answers at every point, its
warm online time, its start-up and its peak memory.

    python -m lungmech.app.measure REQUEST.json RESULT.json

``REQUEST`` names the scene file, the candidate — a full model at a discretisation
(``{"kind": "full", "discretisation": {...}}``) or a model file (``{"kind": "file", "path":
...}``) —, the points μ, the output times (null: the whole path) and lungmech's cache folder.
A process of its own makes the peak resident memory that of this candidate alone. Full-order
answers come from the cache where it has them (:func:`lungmech.app.answers.kept_answer`) and
go into it otherwise. The first solve of the process is its warm-up: a reduced model solves
the first point once before the timed ones, and a full model's first solve is left out of the
median (its assembly's first pass; the forms were compiled at start-up).
"""

from __future__ import annotations

import json
import resource
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from mpi4py import MPI

from lungmech.app import reduce
from lungmech.app import scene as scenes
from lungmech.app.answers import Task, answer, kept_answer
from lungmech.app.cache import Cache
from lungmech.app.ladder import Discretisation, at
from lungmech.app.run import full_order_model
from lungmech.errors import LungmechError
from lungmech.fem.parametric import ParametricModel
from lungmech.parallel import on_root

__all__ = ["measure"]


def measure(request: dict[str, Any], comm: MPI.Comm = MPI.COMM_WORLD) -> dict[str, Any]:
    """The candidate of ``request`` measured at its points (see the module's doc). Collective."""
    scene = scenes.load(request["scene"])
    cache = Cache(request["cache"], comm)
    candidate = request["candidate"]
    times = request.get("times")
    began = time.perf_counter()
    model: ParametricModel
    if candidate["kind"] == "full":
        discretisation = Discretisation(**candidate["discretisation"])
        model = full_order_model(at(scene, discretisation, cache, comm), comm, start="inverse_motion")
    else:
        model = reduce.load(candidate["path"], comm)
        answer(model, request["points"][0], times)  # the warm-up
    start_up = time.perf_counter() - began
    answers, kept = [], []
    for point in request["points"]:
        if candidate["kind"] == "full":
            task = Task(str(request["scene"]), point, discretisation, None if times is None else tuple(times))
            found, was_kept = kept_answer(cache, scene, task, model)
        else:
            found, was_kept = answer(model, point, times), False
        answers.append(found)
        kept.append(was_kept)
    solved = [a["seconds"] for a, k in zip(answers, kept) if not k and a["failed"] is None]
    if candidate["kind"] == "full" and len(solved) > 1:
        solved = solved[1:]  # the first solve of the process: its warm-up
    timed = solved or [a["seconds"] for a in answers if a["failed"] is None]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB
    return {
        "answers": answers,
        "kept": kept,
        "online_seconds": statistics.median(timed) if timed else None,
        "online_measured_here": bool(solved),
        "start_up_seconds": start_up,
        "peak_rss_mib": comm.allreduce(peak, op=MPI.MAX),
        "dofs": _dofs(model),
        "ranks": comm.size,
    } | _offline(model, candidate["kind"])


def _offline(model: ParametricModel, kind: str) -> dict[str, Any]:
    """A model file's offline cost as its build recorded it (s, every part), its basis size."""
    if kind == "full":
        return {"offline_seconds": 0.0}
    built = getattr(model, "built", {}) or {}
    return {
        "offline_seconds": float(sum(built.get("timings", {}).values())),
        "basis_size": int(getattr(model, "size", 0)),
        "hyper": built.get("hyper"),
    }


def _dofs(model: ParametricModel) -> int:
    """The full model's unknowns (a reduced model's full model's, where it has one)."""
    space = model.model.state.function_space
    return int(space.dofmap.index_map.size_global * space.dofmap.index_map_bs)


def main(argv: list[str]) -> int:
    """Measure the request in ``argv[0]``, write the result to ``argv[1]``; a bad input or a
    failed start-up is one line in the result (``error``) and exit code 2."""
    comm = MPI.COMM_WORLD
    request_path, result_path = (Path(a) for a in argv)
    try:
        result = measure(json.loads(request_path.read_text()), comm)
    except LungmechError as error:
        result, code = {"error": str(error)}, 2
    else:
        code = 0
    on_root(comm, lambda: result_path.write_text(json.dumps(result) + "\n"))
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
