import gc
import os

from mpi4py import MPI

import pytest

if os.environ.get("PYTEST_XDIST_WORKER"):  # workers share the cores: one BLAS thread each (lungmech._threads)
    for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
        os.environ.setdefault(_name, "1")

import lungmech  # noqa: E402, F401  (orders MPI before the DOLFINx bindings; under mpiexec, one BLAS thread a rank)


@pytest.fixture(autouse=True)
def _collective_teardown():
    """PETSc objects are destroyed collectively: collect them on every rank together."""
    yield
    gc.collect()
    MPI.COMM_WORLD.Barrier()


@pytest.fixture
def shared_tmp_path(tmp_path):
    """One temporary folder for all ranks: rank 0's (pytest makes one per process)."""
    from pathlib import Path

    return Path(MPI.COMM_WORLD.bcast(str(tmp_path), root=0))
