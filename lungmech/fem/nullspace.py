"""The near-nullspace of a displacement space: its rigid-body modes, for AMG."""

from __future__ import annotations

from typing import TYPE_CHECKING

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np

from lungmech.parallel.linalg import gram_schmidt

if TYPE_CHECKING:
    from dolfinx import fem

__all__ = ["rigid_body_modes"]


def rigid_body_modes(space: fem.FunctionSpace) -> PETSc.NullSpace:
    """The rigid-body modes of a vector space, orthonormalised: AMG's near-nullspace. Six in
    3-D (three translations, three rotations ω × x), three in a plane (two translations, the
    rotation about z: (−y, x))."""
    index_map, bs = space.dofmap.index_map, space.dofmap.index_map_bs
    n = index_map.size_local
    comm = space.mesh.comm
    x = space.tabulate_dof_coordinates()[:n]
    # Rotations about one point for all ranks (the global centre: better conditioned than the origin).
    total = comm.allreduce(np.concatenate([x.sum(axis=0), [len(x)]]), op=MPI.SUM)
    x = x - total[:3] / total[3]
    rotations = [np.cross(axis, x)[:, :bs] for axis in (np.eye(3) if bs == 3 else [(0.0, 0.0, 1.0)])]
    modes = np.array([*np.eye(bs)[:, None, :].repeat(n, axis=1), *rotations])
    orthonormal, _ = gram_schmidt(modes.reshape(len(modes), -1).T, None, comm, tolerance=0.0)
    vectors = [PETSc.Vec().createWithArray(mode.copy(), bsize=bs, comm=comm) for mode in orthonormal.T]
    return PETSc.NullSpace().create(vectors=vectors, comm=comm)
