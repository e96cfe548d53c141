"""Direct linear solves with MUMPS: the one configuration every factorisation here uses."""

from __future__ import annotations

from petsc4py import PETSc

__all__ = ["factorised", "use_lu"]


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
