"""An error on one rank is an error on every rank.

Under MPI a rank that raises while the others go on to a collective call leaves them waiting
forever. The helpers here make failures collective: :func:`together` runs a block on every rank
and, if it failed anywhere, raises the same error (class and message) on all of them;
:func:`on_root` does the same for work that only rank 0 does (writing a file, drawing a
picture). :func:`arrive` is the last resort of the command line: it waits a bounded time for
every rank to reach the same error, so that a failure that was not collective ends the run
(``MPI_Abort``) instead of hanging it. :func:`deferred` holds SIGINT and SIGTERM back during a
block of collective work (writing outputs) and raises them on every rank together at its end.

All are collective: call them on every rank of the communicator.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from typing import TypeVar

from mpi4py import MPI

from lungmech import errors

__all__ = ["arrive", "deferred", "on_root", "raise_together", "together"]

T = TypeVar("T")


def raise_together(comm: MPI.Comm, error: BaseException | None) -> None:
    """Collective. If any rank passes an error, raise on every rank the error of the lowest
    failing rank: the rank's own exception there, an exception of the same lungmech class and
    message elsewhere (other exceptions become a :class:`~lungmech.errors.LungmechError`)."""
    if comm.size == 1:
        if error is not None:
            raise error
        return
    described = None if error is None else (type(error).__name__, _message(error))
    reports = comm.allgather(described)
    failing = [rank for rank, report in enumerate(reports) if report is not None]
    if not failing:
        return
    if error is not None and failing[0] == comm.rank:
        raise error
    name, message = reports[failing[0]]
    kind = getattr(errors, name, None)
    if not (isinstance(kind, type) and issubclass(kind, errors.LungmechError)):
        kind = errors.LungmechError
    raise kind(message)


@contextlib.contextmanager
def together(comm: MPI.Comm) -> Iterator[None]:
    """Run the block on every rank; if it raised anywhere, raise that error on all ranks.

    Collective at the end of the block. The block itself must not call collective operations
    that a failing rank would skip (keep it to local work: reading, checking, writing).
    """
    error = None
    try:
        yield
    except Exception as e:  # noqa: BLE001 - every error is handed to the other ranks
        error = e
    raise_together(comm, error)


def on_root(comm: MPI.Comm, work: Callable[[], T], root: int = 0) -> T | None:
    """Collective: ``work()`` on rank ``root`` only (returns its result there, None elsewhere);
    an error it raises is raised on every rank."""
    result = None
    with together(comm):
        if comm.rank == root:
            result = work()
    return result


def arrive(comm: MPI.Comm, timeout: float) -> bool:
    """Whether every rank reaches this call within ``timeout`` seconds (a non-blocking barrier).

    The command line calls it on a failure: if the failure was collective, every rank arrives
    at once; if not, the others are elsewhere (perhaps waiting for this rank) and the caller
    should abort the run rather than wait.
    """
    if comm.size == 1:
        return True
    request = comm.Ibarrier()
    deadline = time.monotonic() + timeout
    while not request.Test():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def _message(error: BaseException) -> str:
    if isinstance(error, OSError) and error.filename is not None:
        return f"'{error.filename}': {error.strerror or error}"
    return str(error) or type(error).__name__


@contextlib.contextmanager
def deferred(comm: MPI.Comm) -> Iterator[Callable[[], None]]:
    """Collective: SIGINT and SIGTERM wait during the block (the command line's handler only
    remembers them, :attr:`lungmech.errors.Interrupted.pending`), so a collective write or a
    swap is never cut in the middle on one rank. The block gets ``agree()``, collective, which
    raises :class:`~lungmech.errors.Interrupted` on every rank if a signal reached any of them;
    it is called at the block's end too. Nested blocks defer to the outermost."""
    errors.Interrupted.deferring += 1

    def agree() -> None:
        pending = errors.Interrupted.pending or 0
        signum = comm.allreduce(pending, op=MPI.MAX) if comm.size > 1 else pending
        if signum:
            errors.Interrupted.pending = signum
            raise errors.Interrupted(signum)

    try:
        yield agree
    finally:
        errors.Interrupted.deferring -= 1
    if errors.Interrupted.deferring == 0:
        agree()
