"""The suite runs twice in ``make test``: on one rank (two pytest workers), and under
``mpiexec -n 2`` for its cheap part. A test runs both ways unless it is marked:

* ``serial``: one rank only (it starts processes of its own, or makes and reads files from one
  process); left out of the 2-rank run, as is a test that reads what was printed (``capsys``:
  rank 0 prints).
* ``mpi``: meaningful on two or more ranks only (it compares a distributed result with one
  computed on ``COMM_SELF``); left out of the one-rank run.

``tmp_path`` is one folder for all ranks (rank 0's), so a test writes and reads its files as a
user's run does. lungmech's cache (``$LUNGMECH_CACHE``) is a folder of the session's, removed
at its end: the suite never writes into the user's.
"""

import atexit
import gc
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path

from mpi4py import MPI

import pytest

if os.environ.get("PYTEST_XDIST_WORKER"):  # workers share the cores: one BLAS thread each (lungmech._threads)
    for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
        os.environ.setdefault(_name, "1")

import lungmech  # noqa: E402, F401  (orders MPI before the DOLFINx bindings; under mpiexec, one BLAS thread a rank)

if "LUNGMECH_CACHE" not in os.environ:  # lungmech's cache: one folder of the session's, not the user's
    _cache = tempfile.mkdtemp(prefix="lungmech-test-cache-") if MPI.COMM_WORLD.rank == 0 else None
    os.environ["LUNGMECH_CACHE"] = MPI.COMM_WORLD.bcast(_cache, root=0)
    if _cache is not None:
        atexit.register(shutil.rmtree, _cache, ignore_errors=True)


def _serial(item) -> bool:
    """Marked ``serial``, or reading what was printed (``capsys``, ``capfd``): rank 0 prints."""
    return "serial" in item.keywords or bool({"capsys", "capfd"} & set(getattr(item, "fixturenames", ())))


def pytest_collection_modifyitems(config, items):
    """Deselect the tests that do not belong to this run: the serial ones under MPI, the ``mpi``
    ones on one rank."""
    if MPI.COMM_WORLD.size > 1:
        left_out = [item for item in items if _serial(item) and "mpi" not in item.keywords]
    else:
        left_out = [item for item in items if "mpi" in item.keywords]
    if left_out:
        config.hook.pytest_deselected(items=left_out)
        items[:] = [item for item in items if item not in left_out]


def pytest_runtest_logreport(report):
    """Under MPI, a test that failed on one rank leaves the others waiting in a collective call:
    say which test failed, and how, then stop every rank (the run's exit code is not 0)."""
    comm = MPI.COMM_WORLD
    if comm.size > 1 and report.failed:
        sys.stderr.write(f"\n[rank {comm.rank}] {report.nodeid} failed ({report.when}):\n{report.longreprtext}\n")
        sys.stderr.flush()
        comm.Abort(1)


@pytest.fixture
def tmp_path(request, tmp_path_factory) -> Path:
    """A temporary folder of the test's own: one for all ranks under MPI (rank 0 makes it)."""
    comm = MPI.COMM_WORLD
    folder = None
    if comm.rank == 0:
        folder = str(tmp_path_factory.mktemp(re.sub(r"\W", "_", request.node.name)[:30], numbered=True))
    return Path(comm.bcast(folder, root=0))


@pytest.fixture(autouse=True)
def _collective_teardown():
    """Under MPI, PETSc objects are destroyed collectively: collect them on every rank together,
    and free the parallel ones PETSc holds for a collective destruction (each test starts
    clean). On one rank nothing waits on another: Python's own collector is left to it (a full
    collection after every test was a tenth of the one-rank run's time)."""
    yield
    if MPI.COMM_WORLD.size == 1:
        return
    gc.collect()
    from petsc4py import PETSc

    PETSc.garbage_cleanup(MPI.COMM_WORLD)
    MPI.COMM_WORLD.Barrier()
