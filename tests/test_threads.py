"""One BLAS thread per MPI rank: set under mpiexec when unset, a user's value kept, nothing
changed in one process."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.serial  # starts mpiexec itself

MPIEXEC = Path(sys.executable).parent / "mpiexec"
SHOW = (  # every rank's values, printed by rank 0
    "import lungmech, os; from mpi4py import MPI; "
    "found = MPI.COMM_WORLD.gather(f\"{os.environ.get('OPENBLAS_NUM_THREADS')} {os.environ.get('OMP_NUM_THREADS')}\"); "
    "MPI.COMM_WORLD.rank == 0 and print('\\n'.join(found))"
)


def _run(command: list[str], **environment: str) -> list[str]:
    clean = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
    done = subprocess.run(command, env=clean | environment, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return sorted(done.stdout.split("\n")[:-1])


@pytest.mark.skipif(not MPIEXEC.exists(), reason="no mpiexec beside this Python")
def test_a_rank_of_several_gets_one_blas_thread_unless_the_user_chose():
    assert _run([str(MPIEXEC), "-n", "2", sys.executable, "-c", SHOW]) == ["1 1", "1 1"]
    assert _run([str(MPIEXEC), "-n", "2", sys.executable, "-c", SHOW], OPENBLAS_NUM_THREADS="2") == ["2 1", "2 1"]
    assert _run([sys.executable, "-c", SHOW]) == ["None None"]


@pytest.mark.skipif(not MPIEXEC.exists(), reason="no mpiexec beside this Python")
def test_a_script_that_loads_numpy_first_gets_one_blas_thread_a_rank_too():
    """NumPy's pools start before lungmech is imported: lungmech limits them (threadpoolctl)."""
    show = (
        "import numpy, threadpoolctl, lungmech; from mpi4py import MPI; "
        "found = MPI.COMM_WORLD.gather(str(max(p['num_threads'] for p in threadpoolctl.threadpool_info()))); "
        "MPI.COMM_WORLD.rank == 0 and print('\\n'.join(found))"
    )
    assert _run([str(MPIEXEC), "-n", "2", sys.executable, "-c", show]) == ["1", "1"]
