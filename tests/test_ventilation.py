"""Regional ventilation: the volume ratio of a motion, cell by cell, against an affine motion's
exact one, on any partition."""

from mpi4py import MPI

import numpy as np
import pytest
from dolfinx import fem

from lungmech.mesh import box
from lungmech.twin.ventilation import volume_ratio


def test_an_affine_motions_volume_ratio_is_exact_on_every_cell():
    """w = A x on a box: J = det(I + A) on every cell (P1 represents it exactly), 1 for w = 0."""
    mesh = box(MPI.COMM_WORLD, (0.2, 0.1, 0.1), (4, 2, 2)).mesh
    A = np.array([[0.10, 0.02, 0.0], [0.0, -0.05, 0.03], [0.01, 0.0, 0.20]])
    w = fem.Function(fem.functionspace(mesh, ("Lagrange", 1, (3,))))
    w.interpolate(lambda x: A @ x)
    J = volume_ratio(w)
    assert len(J) == mesh.topology.index_map(3).size_local
    assert J == pytest.approx(np.linalg.det(np.eye(3) + A), rel=1e-12)
    w.x.array[:] = 0.0
    assert volume_ratio(w) == pytest.approx(1.0, abs=1e-14)
