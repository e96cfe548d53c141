"""Many independent tasks, one interface, three ways to run them.

A task is serialisable data; ``work(task, comm)`` solves it on the communicator it is given and
returns something JSON-like (a full solve's answer, say). :meth:`Ensemble.map` runs every task
and returns an :class:`Outcome` per task, in their order: its value, or why it failed, in one
line. A failing task never stops the others, in any mode.

* :class:`Serial` — every task in this process, one after another, on the whole communicator
  (the default: a single machine, or a run already under ``mpiexec`` whose every solve is
  parallel).
* :class:`Groups` — inside one ``mpiexec -n P``: the world split into P/k groups of k ranks
  (``comm.Split``, the ensemble pattern of Firedrake's ``Ensemble``), each group solving its
  own tasks, dealt round-robin in the order given (give the costliest first); every rank gets
  every outcome. The groups never wait for one another until the end: each tells the first
  rank of a task done by a message it does not wait on (a one-sided counter, tried first,
  held a group until the busy first rank next called MPI). A process that dies ends the run (MPI's rule); the tasks' own results, kept
  by the caller (lungmech's cache), make a rerun resume.
* :class:`Pool` — an existing engine's :class:`concurrent.futures.Executor` whose workers may
  be k-rank MPI jobs (Parsl's, :mod:`lungmech.parallel.engine`, on this machine or through
  Slurm or PBS): each task is submitted as ``run_task(work, task)``, or the engine's launcher,
  which solves it on the worker's communicator; a task whose worker died is submitted once more.

A pool's workers cap their BLAS and OpenMP threads to one per rank before they solve
(:func:`lungmech._threads.cap_threads`), as ``import lungmech`` does in a rank of several:
threaded dense algebra competing for cores slows a solve far more than the oversubscription
factor (an ECSW build took 14× longer under a load of 2–8).

Progress: one line for the ensemble, on the first rank — tasks done of the total, failures and
the time left at the pace so far.
"""

from __future__ import annotations

import concurrent.futures
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from mpi4py import MPI

from lungmech._threads import cap_threads
from lungmech.errors import Interrupted, LungmechError, ParameterError

__all__ = ["Ensemble", "Groups", "Kept", "Outcome", "Pool", "Serial", "attempt", "run_task", "same_ranks"]

T = TypeVar("T")
R = TypeVar("R")
Work = Callable[[T, MPI.Comm], R]


@dataclass(frozen=True)
class Outcome(Generic[R]):
    """A task's value, or why it failed (one line; then ``value`` is None)."""

    value: R | None
    failed: str | None = None


class Ensemble(ABC):
    """Runs independent tasks (see the module's doc)."""

    @abstractmethod
    def map(self, work: Work, tasks: Sequence[Any], progress: Callable[[str], None] | None = None) -> list[Outcome]:
        """An :class:`Outcome` per task, in their order; ``progress`` receives one line per task
        done. Collective over the ensemble's communicator."""

    @property
    @abstractmethod
    def description(self) -> str:
        """How it runs, for a report ("serial on 2 ranks", "2 groups of 1 rank", …)."""

    @abstractmethod
    def check(self, comm: MPI.Comm) -> None:
        """Refuse in one line to be driven from the ranks of ``comm`` if it cannot be."""

    def runs_here(self, comm: MPI.Comm) -> bool:
        """Whether every task runs in this process on exactly ``comm``'s ranks (a task may then
        use what lives on them)."""
        return False


class Serial(Ensemble):
    """Every task on the whole ``comm``, one after another, in this process."""

    def __init__(self, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
        self.comm = comm

    @property
    def description(self) -> str:
        return f"serial on {self.comm.size} rank{'s' * (self.comm.size > 1)}"

    def check(self, comm: MPI.Comm) -> None:
        if not same_ranks(self.comm, comm):
            raise ParameterError("a serial ensemble runs on the ranks it was made on: make it on the caller's")

    def runs_here(self, comm: MPI.Comm) -> bool:
        return same_ranks(self.comm, comm)

    def map(self, work: Work, tasks: Sequence[Any], progress: Callable[[str], None] | None = None) -> list[Outcome]:
        pace = Pace(len(tasks), progress if self.comm.rank == 0 else None)
        outcomes = []
        for task in tasks:
            outcomes.append(self.comm.bcast(attempt(work, task, self.comm), root=0))  # one outcome on every rank
            pace.done(outcomes[-1])
        return outcomes


class Groups(Ensemble):
    """The world ``comm`` split into groups of ``size`` ranks, each solving its share of the
    tasks (round-robin in their order) on its group's communicator. Collective over ``comm``."""

    PROGRESS = 7  # the tag of a group's "one more task done" message to the first rank

    def __init__(self, size: int = 1, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
        if isinstance(size, bool) or not isinstance(size, int) or size < 1 or comm.size % size:
            raise ParameterError(
                f"--group-size: groups of k ranks must divide the {comm.size} ranks of the run (got {size!r})"
            )
        self.comm, self.size = comm, size
        self.count = comm.size // size
        self.group = comm.Split(comm.rank // size, comm.rank)

    @property
    def description(self) -> str:
        return f"{self.count} group{'s' * (self.count > 1)} of {self.size} rank{'s' * (self.size > 1)}"

    def check(self, comm: MPI.Comm) -> None:
        if not same_ranks(self.comm, comm):
            raise ParameterError("groups split the ranks they were made on: make them on the caller's")

    def map(self, work: Work, tasks: Sequence[Any], progress: Callable[[str], None] | None = None) -> list[Outcome]:
        colour, world = self.comm.rank // self.size, self.comm
        mine = range(colour, len(tasks), self.count)
        pace = Pace(len(tasks), progress if world.rank == 0 else None)
        told = [0, 0]  # tasks done and failed, as the first rank knows them
        sent = []
        found = {}
        for index in mine:
            found[index] = attempt(work, tasks[index], self.group)
            failed = found[index].failed is not None
            if world.rank == 0:
                told = [told[0] + 1, told[1] + failed]
                told = _heard(world, told, self.PROGRESS, pace)
            elif self.group.rank == 0:
                sent.append(world.isend(failed, dest=0, tag=self.PROGRESS))
        if world.rank == 0:
            expected = len(tasks) - len(range(0, len(tasks), self.count))  # the other groups' tasks
            while told[0] - len(mine) < expected:
                told = _heard(world, told, self.PROGRESS, pace, wait=True)
        MPI.Request.Waitall(sent)
        gathered = self.comm.allgather(found if self.group.rank == 0 else {})
        outcomes = {index: outcome for part in gathered for index, outcome in part.items()}
        pace.report(len(tasks), sum(outcome.failed is not None for outcome in outcomes.values()))
        return [outcomes[index] for index in range(len(tasks))]

    def free(self) -> None:
        """Free the groups' communicator (collective)."""
        self.group.Free()


class Pool(Ensemble):
    """Tasks submitted to ``executor`` (a :class:`concurrent.futures.Executor` of an existing
    engine, its workers possibly MPI jobs) as ``function(work, task, **options)``
    (:func:`run_task` by default; :func:`lungmech.parallel.engine.launched` for Parsl's MPI
    tasks). A task whose future fails — its worker died; the task's own failure is an
    outcome — is submitted ``retries`` times more. Runs on the caller's rank (give it a
    one-rank caller); close it (``with``) to stop the engine."""

    def __init__(
        self,
        executor: concurrent.futures.Executor,
        function: Callable[..., Outcome] | None = None,
        options: dict | None = None,
        retries: int = 1,
        description: str = "",
        closed: Callable[[], None] | None = None,
    ) -> None:
        self.executor = executor
        self.closed = closed  # what else to tidy once the engine stopped (its run folder, say)
        self.function: Callable[..., Outcome] = function or run_task
        self.options, self.retries = dict(options or {}), retries
        self._description = description or f"{type(executor).__name__} workers"

    @property
    def description(self) -> str:
        return self._description

    def check(self, comm: MPI.Comm) -> None:
        if comm.size > 1:
            raise ParameterError("an engine's pool is driven from one rank (its workers are the parallel part)")

    def __enter__(self) -> Pool:
        return self

    def __exit__(self, kind: type[BaseException] | None, *rest: object) -> None:
        self.close(wait=kind is None)

    def close(self, wait: bool = True) -> None:
        """Stop the engine's workers: once its tasks are done, or at once (``wait`` False: an
        error or an interrupt)."""
        try:
            self.executor.shutdown(wait=wait)
        finally:
            if self.closed is not None:
                self.closed()

    def map(self, work: Work, tasks: Sequence[Any], progress: Callable[[str], None] | None = None) -> list[Outcome]:
        pace = Pace(len(tasks), progress)
        futures = {self._submit(work, task): (index, 0) for index, task in enumerate(tasks)}
        outcomes: dict[int, Outcome] = {}
        try:
            while futures:
                done, _ = concurrent.futures.wait(futures, return_when=concurrent.futures.FIRST_COMPLETED)
                for future in done:
                    index, tries = futures.pop(future)
                    try:
                        outcome = future.result()
                    except Exception as error:  # the worker, not the task: the task's own errors are outcomes
                        if tries < self.retries:
                            futures[self._submit(work, tasks[index])] = (index, tries + 1)
                            continue
                        outcome = Outcome(None, f"its worker failed {tries + 1}× ({_line(error)})")
                    outcomes[index] = outcome
                    pace.done(outcome)
        except KeyboardInterrupt:
            raise Interrupted(2) from None
        finally:
            for future in futures:
                future.cancel()
        return [outcomes[index] for index in range(len(tasks))]

    def _submit(self, work: Work, task: Any) -> concurrent.futures.Future:
        return self.executor.submit(self.function, work, task, **self.options)


class Kept(Generic[T]):
    """What a process keeps from one task of an ensemble for its next — the model of its last
    scene, say —: made again when what it is made from (``which``) or the communicator
    differs. :meth:`forget` drops it (before its communicator is freed)."""

    def __init__(self) -> None:
        self._which: object = None
        self._comm: MPI.Comm | None = None
        self._value: T | None = None

    def get(self, which: object, comm: MPI.Comm, make: Callable[[], T]) -> T:
        """The value kept for ``which`` on ``comm``, or ``make()``'s, kept (collective when
        ``make`` is)."""
        if self._value is None or self._which != which or self._comm is not comm:
            self.forget()
            self._value = make()
            self._which, self._comm = which, comm
        return self._value

    def forget(self) -> None:
        self._which = self._comm = self._value = None


def same_ranks(one: MPI.Comm, other: MPI.Comm) -> bool:
    """Whether two communicators hold the same ranks in the same order."""
    return MPI.Comm.Compare(one, other) in (MPI.IDENT, MPI.CONGRUENT)


def run_task(work: Work, task: Any) -> Outcome:
    """``work(task, comm)`` on a worker, ``comm`` its world (a k-rank MPI job's k ranks), its
    threads capped first: what :class:`Pool` submits."""
    cap_threads()
    return attempt(work, task, MPI.COMM_WORLD)


def attempt(work: Work, task: Any, comm: MPI.Comm) -> Outcome:
    """``work(task, comm)`` as an :class:`Outcome`: a lungmech error, or any other exception
    (a bug, a library's error), is the task's failure in one line; an interrupt is not."""
    try:
        return Outcome(work(task, comm))
    except (Interrupted, KeyboardInterrupt):
        raise
    except LungmechError as error:
        return Outcome(None, _line(error))
    except Exception as error:
        return Outcome(None, f"{type(error).__name__}: {_line(error)}")


class Pace:
    """The ensemble's progress line: tasks done of ``total``, failures, the time left."""

    def __init__(self, total: int, say: Callable[[str], None] | None) -> None:
        self.total, self.say = total, say
        self.started = time.perf_counter()
        self.finished = self.failures = 0

    def done(self, outcome: Outcome) -> None:
        self.report(self.finished + 1, self.failures + (outcome.failed is not None))

    def report(self, finished: int, failures: int) -> None:
        self.finished, self.failures = finished, failures
        if self.say is None:
            return
        spent = time.perf_counter() - self.started
        left = spent / finished * (self.total - finished) if finished else float("nan")
        failed = f", {failures} failed" if failures else ""
        self.say(f"{finished}/{self.total} solves done{failed}, about {_duration(left)} left")


def _heard(comm: MPI.Comm, told: list[int], tag: int, pace: Pace, wait: bool = False) -> list[int]:
    """The first rank: every "task done" message waiting (one at least, with ``wait``) added to
    ``told`` (done, failed), and the progress line updated."""
    status = MPI.Status()
    while wait or comm.iprobe(source=MPI.ANY_SOURCE, tag=tag, status=status):
        failed = comm.recv(source=MPI.ANY_SOURCE, tag=tag)
        told = [told[0] + 1, told[1] + bool(failed)]
        wait = False
    pace.report(*told)
    return told


def _line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def _duration(seconds: float) -> str:
    if seconds != seconds:  # nan: no pace yet
        return "?"
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"
