"""One candidate of a trade measured in a process of its own: its answers at every point, its
warm online time, its start-up and its peak memory.

    python -m lungmech.app.measure REQUEST.json RESULT.json

:func:`apart` starts that process and reads its result: a subprocess on one rank, and under
``mpiexec`` as many processes as the caller's ranks, spawned (``MPI_Comm_spawn``), so that a
trade on P ranks measures each candidate on P ranks of its own.

``REQUEST`` names the scene file, the candidate — a full model at a discretisation
(``{"kind": "full", "discretisation": {...}}``) or a model file (``{"kind": "file", "path":
...}``) —, the points μ, the output times (null: the whole path), whether a full model's
fields are kept (``fields``) and lungmech's cache folder.
A process of its own makes the peak resident memory that of this candidate alone. Full-order
answers come from the cache where it has them (:func:`lungmech.app.answers.kept_answer`) and
go into it otherwise. The first solve of the process is its warm-up: a reduced model solves
the first point once before the timed ones, and a full model's first solve is left out of the
median (its assembly's first pass; the forms were compiled at start-up).
"""

from __future__ import annotations

import functools
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, cast

from mpi4py import MPI

from lungmech._threads import under_launcher
from lungmech.app import reduce
from lungmech.app import scene as scenes
from lungmech.app.answers import Task, answer, kept_answer
from lungmech.app.cache import Cache
from lungmech.app.ladder import Discretisation, at
from lungmech.app.run import full_order_model
from lungmech.errors import Interrupted, LungmechError
from lungmech.fem.parametric import ParametricModel
from lungmech.parallel import on_root
from lungmech.rom import store

__all__ = ["apart", "measure"]

# the parts of a build's ECSW training that its own time holds already (rom.reductor: ecsw.Training.seconds)
NESTED = ("ecsw_tangents", "ecsw_compression")


def measure(request: dict[str, Any], comm: MPI.Comm = MPI.COMM_WORLD) -> dict[str, Any]:
    """The candidate of ``request`` measured at its points (see the module's doc). A full model
    whose answers are all kept, and which is not ``timed`` (the reference), is not even built.
    Collective."""
    scene = scenes.load(request["scene"])
    cache = Cache(request["cache"], comm)
    candidate, points = request["candidate"], request["points"]
    times = request.get("times")
    full = candidate["kind"] == "full"
    began = time.perf_counter()
    start_up = 0.0

    @functools.cache
    def model() -> ParametricModel:
        nonlocal start_up
        began = time.perf_counter()
        built: ParametricModel
        if full:
            built = full_order_model(at(scene, discretisation, cache, comm), comm, start="inverse_motion")
        else:
            built = reduce.load(candidate["path"], comm)
            answer(built, points[0], times)  # the warm-up
        start_up = time.perf_counter() - began
        return built

    answers, kept = [], []
    if full:
        discretisation = Discretisation(**candidate["discretisation"])
        for point in points:
            when = None if times is None else tuple(times)
            task = Task(str(request["scene"]), point, discretisation, when, bool(request.get("fields")))
            found, was_kept = kept_answer(cache, scene, task, model)
            answers.append(found)
            kept.append(was_kept)
    else:
        answers, kept = [answer(model(), point, times) for point in points], [False] * len(points)
    solved = [a["seconds"] for a, k in zip(answers, kept) if not k and a["failed"] is None]
    if full and request.get("timed", True) and len(solved) < 2:
        # its answers came from the cache: its time and memory are measured here all the same
        again = [answer(model(), point, times) for point in points[: 2 - len(solved)]]
        solved += [a["seconds"] for a in again if a["failed"] is None]
    if full and len(solved) > 1:
        solved = solved[1:]  # the first solve of the process: its warm-up
    timed = solved or [a["seconds"] for a in answers if a["failed"] is None]
    peak = _peak_rss_mib()
    return {
        "answers": answers,
        "kept": kept,
        "online_seconds": statistics.median(timed) if timed else None,
        "timed_solves": len(timed),
        "online_measured_here": bool(solved),
        "start_up_seconds": start_up if model.cache_info().currsize else None,
        "peak_rss_mib": comm.allreduce(peak, op=MPI.MAX),
        "dofs": next((a["dofs"] for a in answers if a.get("dofs")), None),
        "ranks": comm.size,
        "seconds": time.perf_counter() - began,
    } | _offline(candidate, comm, model() if not full else None)


def _peak_rss_mib() -> float:
    """This process's peak resident memory (MiB): Linux's VmHWM, of this program alone (getrusage's
    ru_maxrss survives exec, so a subprocess would report its launcher's size at the fork);
    ru_maxrss where there is no /proc."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def _offline(candidate: dict[str, Any], comm: MPI.Comm, model: ParametricModel | None) -> dict[str, Any]:
    """A model file's offline cost as its build recorded it (s, every part: the full model and
    its inverse problem, the training solves, the basis, the hyper-reduction; the full solves
    it took), its basis size and hyper-reduction."""
    if candidate["kind"] == "full":
        return {"offline_seconds": 0.0, "full_solves": 0}
    metadata, _ = store.read_on_root(candidate["path"], comm, arrays=False)
    extra = metadata.get("extra", {})
    built = extra.get("reduced", {}).get("built", {})
    phases = {k: v for k, v in extra.get("offline_seconds", {}).items() if k not in NESTED}
    return {
        "offline_seconds": float(sum(phases.values())),
        "full_solves": built.get("full_solves"),
        "basis_size": int(getattr(model, "size", 0)),
        "hyper": built.get("hyper"),
    }


def apart(request: dict[str, Any], comm: MPI.Comm = MPI.COMM_WORLD) -> dict[str, Any]:
    """The result of :func:`measure` for ``request``, measured in processes of its own (see the
    module's doc): on one rank a subprocess, under ``mpiexec`` ``comm.size`` spawned ranks,
    whose first sends the result back. A failed start-up is ``{"error": one line}``. Ctrl-C or
    SIGTERM there is an :class:`~lungmech.errors.Interrupted` here. Collective."""
    folder = comm.bcast(on_root(comm, lambda: tempfile.mkdtemp(prefix="lungmech-measure-")), root=0)
    asked, told = Path(folder) / "request.json", Path(folder) / "result.json"
    try:
        on_root(comm, lambda: asked.write_text(json.dumps(request)))
        arguments = ["-m", "lungmech.app.measure", str(asked), str(told)]
        if under_launcher():
            result, stderr = _spawned(cast(MPI.Intracomm, comm), arguments), ""
        else:
            result, stderr = _subprocess(arguments, told) if comm.rank == 0 else (None, "")
        result = comm.bcast(result, root=0)
    finally:
        on_root(comm, lambda: _remove(Path(folder)))
    if result is None:
        return {"error": (stderr.strip().splitlines() or ["the measuring process ended without a result"])[-1]}
    return result


def _spawned(comm: MPI.Intracomm, arguments: list[str]) -> dict | None:
    """The result of ``comm.size`` ranks spawned to run ``python arguments``, sent by their
    first to this group's first (polled: signals are handled while it waits)."""
    children = comm.Spawn(sys.executable, args=arguments, maxprocs=comm.size)
    result = None
    if comm.rank == 0:
        while not children.Iprobe(source=0):
            time.sleep(0.02)
        result = children.recv(source=0)
    children.Disconnect()
    return result


def _subprocess(arguments: list[str], told: Path) -> tuple[dict | None, str]:
    """The result a subprocess running ``python arguments`` wrote to ``told``, and its stderr."""
    try:
        done = subprocess.run([sys.executable, *arguments], capture_output=True, text=True)
    except KeyboardInterrupt:
        raise Interrupted(2) from None
    if done.returncode in (130, -2, 143, -15):
        raise Interrupted(2 if done.returncode in (130, -2) else 15)
    return (json.loads(told.read_text()) if told.is_file() else None), done.stderr


def _remove(folder: Path) -> None:
    for entry in folder.iterdir():
        entry.unlink()
    folder.rmdir()


def main(argv: list[str]) -> int:
    """Measure the request in ``argv[0]``, write the result to ``argv[1]``; a bad input or a
    failed start-up is one line in the result (``error``) and exit code 2. Spawned by
    :func:`apart`, it sends the result to its parent instead."""
    comm = MPI.COMM_WORLD
    request_path, result_path = (Path(a) for a in argv)
    try:
        result, code = measure(json.loads(request_path.read_text()), comm), 0
    except LungmechError as error:
        result, code = {"error": str(error)}, 2
    except Exception as error:  # a bug: one line for the trade's table, the code says which
        result, code = {"error": f"internal error ({type(error).__name__}: {error})"}, 3
    parent = MPI.Comm.Get_parent()
    if parent == MPI.COMM_NULL:
        on_root(comm, lambda: result_path.write_text(json.dumps(result) + "\n"))
    else:  # spawned by apart(): the result goes back to the parent's first rank
        if comm.rank == 0:
            parent.send(result, dest=0)
        parent.Disconnect()
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
