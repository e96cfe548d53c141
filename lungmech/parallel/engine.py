"""Many solves beyond one process: Parsl's MPI executor as the ensemble's :class:`~lungmech.
parallel.ensemble.Pool`, its tasks k-rank MPI jobs.

Parsl (``pip install lungmech[cluster]``) runs tasks on workers it starts through a provider
— this machine (:func:`local_pool`), Slurm or PBS (:func:`pool` with Parsl's provider) — and
in its MPI mode gives each task its ranks as ``$PARSL_MPI_PREFIX`` (``mpiexec -n k …`` or
``srun -n k …``). A task here is :func:`launched`: the worker runs ``python -m
lungmech.parallel.engine IN OUT`` under that prefix, which solves it on its k ranks
(:func:`~lungmech.parallel.ensemble.run_task`) and gives the outcome back; a one-rank task
runs in the worker itself, whose model the next task may reuse. A task's own
failure is its outcome; a process that dies (killed, out of memory) makes the task's future
fail, and the pool submits it once more.

Why Parsl, not executorlib: both run k-rank Python functions, but on this machine executorlib
hung for good where a task failed on one rank only, where mpiexec was not on PATH and on
Ctrl-C, and its retries are per worker, not per task; Parsl surfaced each of those as a failed
future, retries a task whose worker was lost, and has Slurm and PBS providers (docs: the MPI
guide, "Many solves").
"""

from __future__ import annotations

import logging
import os
import pickle
import shlex
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from lungmech.errors import ParameterError
from lungmech.parallel.ensemble import Outcome, Pool, Work, run_task

__all__ = ["launched", "local_pool", "pool"]


def launched(work: Work, task: Any, parsl_resource_specification: dict | None = None) -> Outcome:
    """In a Parsl worker: ``work(task, comm)`` on the ranks Parsl gave the task
    (``$PARSL_MPI_PREFIX``), in processes of their own; a one-rank task in the worker itself,
    which keeps what the work keeps between its tasks (the last model built, say). A process
    that failed without an outcome (killed, say) raises, for the pool to retry."""
    if (parsl_resource_specification or {}).get("num_ranks", 1) == 1:
        return run_task(work, task)
    folder = Path(tempfile.mkdtemp(prefix="lungmech-task-"))
    try:
        given, told = folder / "task.pickle", folder / "outcome.pickle"
        given.write_bytes(pickle.dumps((work, task)))
        prefix = os.environ.get("PARSL_MPI_PREFIX", "")
        arguments = shlex.join([sys.executable, "-m", "lungmech.parallel.engine", str(given), str(told)])
        command = f"{prefix} {arguments}"
        done = subprocess.run(command, shell=True, capture_output=True, text=True)  # the prefix is a shell line
        if not told.is_file():
            last = (done.stderr.strip().splitlines() or [f"exit code {done.returncode}"])[-1]
            raise RuntimeError(f"the task's processes ended without an outcome ({last})")
        return pickle.loads(told.read_bytes())
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def pool(
    provider: Any,
    workers: int,
    ranks: int = 1,
    launcher: str = "mpiexec",
    per_core: bool = False,
    closed: Callable[[], None] | None = None,
) -> Pool:
    """A :class:`~lungmech.parallel.ensemble.Pool` of ``workers`` concurrent tasks of ``ranks``
    MPI ranks each, on Parsl's ``provider`` (e.g. ``parsl.providers.SlurmProvider``; its
    ``worker_init`` activates lungmech's environment), each task launched by ``launcher``
    ("mpiexec" or "srun"). ``per_core``: the provider's nodes are cores (one line per core in
    the node file, :func:`local_pool`). Close it (``with``) to stop Parsl's processes (and
    then call ``closed``); its run folder of logs is removed then."""
    for name, value in (("workers", workers), ("ranks", ranks)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ParameterError(f"--{name}: a whole number ≥ 1 (got {value!r})")
    ParslPoolExecutor, Config, MPIExecutor = _parsl()

    logging.getLogger("parsl").propagate = False  # its configuration goes to its log file, not the console

    here = Path(sys.executable).parent
    interchange = [str(here / "interchange.py")]
    if setsid := shutil.which("setsid"):  # Ctrl-C in a terminal then leaves Parsl's interchange to cleanup()
        interchange.insert(0, setsid)
    executor = MPIExecutor(
        label="lungmech",
        provider=provider,
        max_workers_per_block=workers,
        mpi_launcher=launcher,
        heartbeat_period=2,  # a lost worker is found in seconds, not half a minute
    )
    # a list of arguments, as its base executor takes them (MPIExecutor's checked annotation
    # allows one string only, which cannot hold setsid's)
    executor.interchange_launch_cmd = interchange
    logs = tempfile.mkdtemp(prefix="lungmech-parsl-")
    config = Config(executors=[executor], retries=0, strategy_period=0.2, run_dir=logs)
    shape = {"num_nodes": ranks, "ranks_per_node": 1} if per_core else {"num_nodes": 1, "ranks_per_node": ranks}

    def tidy() -> None:
        shutil.rmtree(logs, ignore_errors=True)
        if closed is not None:
            closed()

    return Pool(
        ParslPoolExecutor(config=config),
        launched,
        {"parsl_resource_specification": shape | {"num_ranks": ranks}},
        description=f"Parsl, {workers} worker{'s' * (workers > 1)} of {ranks} rank{'s' * (ranks > 1)}",
        closed=tidy,
    )


def _parsl() -> tuple[Any, Any, Any]:
    """Parsl's pool executor, config and MPI executor; refused in one line where Parsl is not
    installed."""
    try:
        from parsl.concurrent import ParslPoolExecutor
        from parsl.config import Config
        from parsl.executors import MPIExecutor
    except ImportError:
        raise ParameterError("--engine parsl needs Parsl: pip install 'lungmech[cluster]'") from None
    return ParslPoolExecutor, Config, MPIExecutor


def local_pool(workers: int = 2, ranks: int = 1) -> Pool:
    """A Parsl pool on this machine: ``workers`` tasks at once, each on ``ranks`` ranks of this
    environment's ``mpiexec`` (a node file of one line per core, as a batch system would give);
    the workers see this process's ``PYTHONPATH``."""
    _parsl()  # installed?
    from parsl.launchers import SimpleLauncher
    from parsl.providers import LocalProvider

    cores = os.cpu_count() or 1
    if isinstance(workers, int) and isinstance(ranks, int) and workers * ranks > cores:
        raise ParameterError(
            f"--workers × --worker-ranks: {workers} × {ranks} ranks is more than this machine's {cores} cores"
        )
    folder = Path(tempfile.mkdtemp(prefix="lungmech-nodes-"))
    nodes = folder / "nodefile"
    nodes.write_text("localhost\n" * cores)
    here = Path(sys.executable).parent
    provider = LocalProvider(
        launcher=SimpleLauncher(),
        init_blocks=1,
        min_blocks=0,
        max_blocks=1,
        worker_init=f"export PBS_NODEFILE={nodes}; export PATH={here}:$PATH"
        + (f"; export PYTHONPATH={shlex.quote(path)}" if (path := os.environ.get("PYTHONPATH")) else ""),
    )
    try:
        return pool(provider, workers, ranks, "mpiexec", per_core=True, closed=lambda: shutil.rmtree(folder, True))
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise


def main(argv: list[str]) -> int:
    """``python -m lungmech.parallel.engine TASK OUTCOME``: the pickled (work, task) of ``TASK``
    run on this job's ranks (:func:`~lungmech.parallel.ensemble.run_task`), its outcome pickled
    to ``OUTCOME`` by the first rank: what :func:`launched` runs."""
    from mpi4py import MPI

    given, told = (Path(arg) for arg in argv)
    work, task = pickle.loads(given.read_bytes())
    outcome = run_task(work, task)
    if MPI.COMM_WORLD.rank == 0:
        partial = told.with_suffix(".partial")
        partial.write_bytes(pickle.dumps(outcome))
        partial.replace(told)  # whole or absent
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
