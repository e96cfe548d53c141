import gc

from mpi4py import MPI

import pytest

import lungmech  # noqa: F401  (orders MPI before the DOLFINx bindings)


@pytest.fixture(autouse=True)
def _collective_teardown():
    """PETSc objects are destroyed collectively: collect them on every rank together."""
    yield
    gc.collect()
    MPI.COMM_WORLD.Barrier()
