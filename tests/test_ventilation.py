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


def test_interior_points_are_inside_apart_and_alike_on_any_partition():
    """A box's interior vertices thinned to 0.06 m: none on the boundary, none closer than the
    spacing, every interior vertex within it of one kept; the same list on every rank."""
    from lungmech.errors import ParameterError
    from lungmech.twin.displacement import Displacement, interior_points

    mesh = box(MPI.COMM_WORLD, (0.3, 0.2, 0.2), (6, 4, 4)).mesh  # interior vertices: 5 × 3 × 3
    every = interior_points(mesh, 1e-6)
    assert len(every) == 5 * 3 * 3
    assert np.all((every > 1e-9) & (every < np.array([0.3, 0.2, 0.2]) - 1e-9))
    kept = interior_points(mesh, 0.06)
    distances = np.linalg.norm(kept[:, None] - kept[None, :], axis=-1) + np.eye(len(kept))
    assert distances.min() >= 0.06 and len(kept) < len(every)
    assert np.linalg.norm(every[:, None] - kept[None, :], axis=-1).min(axis=1).max() < 0.06
    gathered = MPI.COMM_WORLD.allgather(kept)
    assert all(np.array_equal(points, gathered[0]) for points in gathered)
    with pytest.raises(ParameterError, match="smoothing is a positive length"):
        Displacement(None, 0.0)
