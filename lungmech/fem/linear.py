"""Direct linear solves with MUMPS: the one configuration every factorisation here uses, and
what one would cost in memory before it is tried."""

from __future__ import annotations

import itertools
from pathlib import Path

from mpi4py import MPI
from petsc4py import PETSc

__all__ = ["available_memory", "factorisation_memory", "factorised", "use_lu"]

_prefixes = itertools.count()
_MEGABYTE, _MEBIBYTE = 1e6, 2.0**20


def use_lu(ksp: PETSc.KSP) -> PETSc.KSP:
    """Make ``ksp`` one MUMPS LU factorisation and solve (preonly); returns it."""
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")
    return ksp


def factorised(A: PETSc.Mat) -> PETSc.KSP:
    """A KSP that solves with ``A`` by MUMPS LU (collective on A's communicator; destroy it after)."""
    ksp = PETSc.KSP().create(A.getComm())
    ksp.setOperators(A)
    return use_lu(ksp)


def factorisation_memory(A: PETSc.Mat, options: dict | None = None) -> float | None:
    """MUMPS's own estimate of the memory its LU factorisation of ``A`` needs on the rank that
    needs most, in MiB (INFOG(16), from its analysis; collective), with the MUMPS ``options``
    the solve would use (e.g. ``{"mat_mumps_icntl_14": 200}``). Only the analysis runs: the
    factorisation is capped at 1 MB (ICNTL(23)), so MUMPS stops before it starts. None if
    MUMPS gave no estimate."""
    prefix = f"lungmech_memory_{next(_prefixes)}_"
    database = PETSc.Options()
    chosen = {**(options or {}), "mat_mumps_icntl_23": 1}
    for key, value in chosen.items():
        database.setValue(prefix + key, value)
    ksp = factorised(A)
    try:
        ksp.setOptionsPrefix(prefix)
        ksp.setFromOptions()
        try:
            ksp.setUp()  # fails by design: the cap is below any factorisation
        except PETSc.Error:
            pass
        estimate = ksp.getPC().getFactorMatrix().getMumpsInfog(16)
    finally:
        ksp.destroy()
        for key in chosen:
            database.delValue(prefix + key)
    return estimate * _MEGABYTE / _MEBIBYTE if estimate > 0 else None


def available_memory(comm: MPI.Comm) -> float | None:
    """The memory a rank of ``comm`` may count on, in MiB: the operating system's available
    memory (Linux MemAvailable) shared among the ranks of its node, the least over the nodes
    (collective). None where the system does not say."""
    local = None
    meminfo = Path("/proc/meminfo")
    if meminfo.exists():
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                local = float(line.split()[1]) * 1024 / _MEBIBYTE  # kB
    node = comm.Split_type(MPI.COMM_TYPE_SHARED)
    sharing = node.Get_size()
    node.Free()
    per_rank = -1.0 if local is None else local / sharing
    least = comm.allreduce(per_rank, op=MPI.MIN)
    return None if least < 0 else least
