"""One BLAS thread per MPI rank, unless the user said otherwise.

OpenBLAS (NumPy's, SciPy's) starts a thread per core in every process. Under ``mpiexec -n N``
on N cores that is N² threads, and the dense linear algebra of a rank (an ECSW training's
eigendecompositions, its NNLS) then waits for the other ranks' busy threads: a 189-dof block's
hyper-reduced build took 37.5 s on 2 ranks of a 2-core machine, 5.4 s with one thread per rank
(4.4 s on one rank). So, when the process is one rank of several (the launcher's PMI_SIZE,
OMPI_COMM_WORLD_SIZE or MPI_LOCALNRANKS say so) and before NumPy loads OpenBLAS, the thread
counts the user left unset are set to 1; a value the user set is kept. Importing this module
does it (``lungmech/__init__.py`` imports it first).

A command of the CLI, and an ensemble's worker, goes further (:func:`cap_threads`): one thread
even as the one process of a run. On a shared machine, BLAS threads that spin for cores another
load holds cost far more than a second thread gives: the bundled lung's ECSW build (2 training
points) took 31.2 s quiet and 113.7 s (3.6×) under a background load of 4 busy processes with 2
threads (its ECSW compression 11× slower), against 33.1 s and 87.8 s (2.7×) with one
(``python benchmarks/threads.py``, 2 cores, 2026-12-05). The limit is set in the environment
too, for the libraries loaded later (DOLFINx's and PETSc's own OpenBLAS), which threadpoolctl
alone would leave at a thread per core.
"""

from __future__ import annotations

import os
import sys

_RANKS = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "MPI_LOCALNRANKS", "PMIX_SIZE")
_THREADS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def ranks_launched() -> int:
    """The number of MPI ranks the launcher started (1 outside ``mpiexec``)."""
    found = [os.environ.get(name, "") for name in _RANKS]
    return max([int(value) for value in found if value.isdigit()] + [1])


def under_launcher() -> bool:
    """Whether an MPI launcher (``mpiexec``) started this process, even as its one rank."""
    return any(name in os.environ for name in _RANKS)


def cap_threads() -> None:
    """Cap this process's BLAS and OpenMP pools to one thread (threadpoolctl: NumPy's are
    started already), unless the user set their sizes (``OPENBLAS_NUM_THREADS`` and the like):
    a CLI command's process, an engine's worker rank (see the module's doc)."""
    if any(os.environ.get(name) for name in _THREADS):
        return
    from threadpoolctl import threadpool_limits

    for name in _THREADS:  # the libraries loaded later (DOLFINx's and PETSc's own OpenBLAS) read these
        os.environ[name] = "1"
    threadpool_limits(limits=1)  # those loaded already


def one_blas_thread_per_rank() -> None:
    """Set the unset BLAS/OpenMP thread counts to 1 in a rank of several: in the environment,
    which NumPy reads when it loads, and — where a script loaded NumPy before lungmech — in the
    pools already started (threadpoolctl). Without the latter, ``import numpy`` on a script's
    first line left every rank a thread per core: the benchmarks' builds on 2 ranks took ten
    times one rank's (the moving jump's PGD 641 s against 67 s, 2026-12-07)."""
    if ranks_launched() <= 1:
        return
    chosen = any(os.environ.get(name) for name in _THREADS)
    for name in _THREADS:
        os.environ.setdefault(name, "1")
    if "numpy" in sys.modules and not chosen:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1)


one_blas_thread_per_rank()
