"""Values of a distributed function at each rank's own points
(:class:`lungmech.parallel.points.PointValues`): exact for fields the element holds exactly, in
the order each rank asked, 0 and not found outside the mesh (on two ranks: tests/test_mpi.py)."""

from mpi4py import MPI

import numpy as np
from dolfinx import fem, mesh

from lungmech.parallel.points import PointValues


def asked_and_answered(comm: MPI.Comm) -> None:
    """Each rank asks at its own random points of a box (some outside it) for a linear vector
    field (P1) and a quadratic scalar one (P2): the fields' own values, 0 outside."""
    box = mesh.create_box(comm, [[0.0, 0.0, 0.0], [2.0, 1.0, 1.0]], [6, 3, 4], mesh.CellType.tetrahedron)
    linear = fem.Function(fem.functionspace(box, ("Lagrange", 1, (3,))))
    linear.interpolate(lambda x: np.array([x[0], 2.0 * x[1] - x[2], 1.0 + x[0] * 0.5]))
    quadratic = fem.Function(fem.functionspace(box, ("Lagrange", 2)))
    quadratic.interpolate(lambda x: x[0] ** 2 - x[1] * x[2] + 3.0)
    rng = np.random.default_rng(17 + comm.rank)
    points = rng.uniform([-0.5, 0.0, 0.0], [2.0, 1.0, 1.0], size=(40 + 9 * comm.rank, 3))
    points[:3] = [[2.0, 1.0, 1.0], [0.0, 0.5, 0.5], [1.0, 0.0, 1.0]]  # a corner, on faces: inside
    at = PointValues(box, points, 1e-9)
    inside = points[:, 0] >= 0.0
    assert np.array_equal(at.found, inside)
    x, y, z = points[inside].T
    vectors, scalars = at(linear), at(quadratic)
    assert np.allclose(vectors[inside], np.column_stack([x, 2 * y - z, 1 + 0.5 * x]), rtol=0, atol=1e-13)
    assert np.allclose(scalars[inside, 0], x**2 - y * z + 3.0, rtol=0, atol=1e-13)
    assert not vectors[~inside].any() and not scalars[~inside].any()


def test_each_rank_gets_the_values_at_its_own_points():
    asked_and_answered(MPI.COMM_WORLD)
