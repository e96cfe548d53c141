"""The canonical dof layout on one rank: what its order is, what its fingerprint notices, and
that canonical arrays go to rank 0 and back. ``tests/test_mpi.py`` compares 1 and 2 ranks."""

from mpi4py import MPI

import dolfinx.mesh
import numpy as np
import pytest
from basix.ufl import element, mixed_element
from dolfinx import fem

from lungmech.mesh import box
from lungmech.parallel.layout import layout

COMM = MPI.COMM_SELF


def _cube(diagonal: tuple[int, int]) -> dolfinx.mesh.Mesh:
    """The unit cube as 6 tetrahedra around one of its main diagonals: same nodes, other cells."""
    x = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=np.float64)
    start, end = diagonal
    paths = []
    for first in range(3):  # monotone paths from start to end, one axis at a time (Kuhn's split)
        for second in set(range(3)) - {first}:
            path = [start]
            for axis in (first, second):
                path.append(path[-1] ^ (1 << axis))
            paths.append([*path, end])
    cells = np.array(paths, dtype=np.int64)
    domain = element("Lagrange", "tetrahedron", 1, shape=(3,))
    return dolfinx.mesh.create_mesh(COMM, cells, domain, x)


def test_canonical_order_is_by_field_component_and_first_cell():
    """Dofs of a vector field: all x components, then y, then z, each in the same node order;
    within a component the first node of input cell 0 comes first."""
    mesh = box(COMM, cells=(2, 2, 1)).mesh
    space = fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    where = layout(space)
    assert where.size == 3 * 18 and np.array_equal(np.sort(where.index), np.arange(where.size))
    f = fem.Function(space)
    f.interpolate(lambda x: np.array([x[0] + 10 * x[1] + 100 * x[2], 1000 + 0 * x[0], 2000 + 0 * x[0]]))
    canonical = where.gather(f.x.array[: len(where.index)])
    x, y, z = canonical.reshape(3, -1)
    assert np.all(y == 1000) and np.all(z == 2000)
    first = mesh.geometry.x[mesh.geometry.dofmaps[0][np.argmin(mesh.topology.original_cell_index)][0]]
    assert x[0] == pytest.approx(first @ [1, 10, 100])


def test_the_order_survives_moving_the_nodes_and_the_fingerprint_does_not():
    mesh = box(COMM, cells=(3, 2, 2)).mesh
    space = fem.functionspace(mesh, ("Lagrange", 2, (3,)))
    before = layout(space)
    mesh.geometry.x[:, 1] += 1e-3 * np.sin(mesh.geometry.x[:, 0])
    moved = layout(space)
    assert np.array_equal(moved.index, before.index) and moved.fingerprint != before.fingerprint
    mesh.geometry.x[:] *= 2.0  # the same shape, twice the size
    assert layout(space).fingerprint not in (before.fingerprint, moved.fingerprint)


def test_the_fingerprint_tells_elements_and_connectivity_apart():
    one, other = _cube((0, 7)), _cube((1, 6))
    prints = {
        layout(fem.functionspace(mesh, (family, degree, (3,)))).fingerprint
        for mesh in (one, other)
        for family, degree in (("Lagrange", 1), ("Lagrange", 2))
    }
    assert len(prints) == 4
    again = layout(fem.functionspace(_cube((0, 7)), ("Lagrange", 1, (3,))))
    assert again.fingerprint == layout(fem.functionspace(one, ("Lagrange", 1, (3,)))).fingerprint
    assert len(again.fingerprint) == 16 and int(again.fingerprint, 16) >= 0


def test_mixed_space_fields_come_one_after_the_other():
    mesh = box(COMM, cells=(2, 1, 1)).mesh
    mixed = fem.functionspace(
        mesh, mixed_element([element("Lagrange", "tetrahedron", 2, shape=(3,)), element("DG", "tetrahedron", 0)])
    )
    where = layout(mixed)
    state = fem.Function(mixed)
    state.sub(0).interpolate(lambda x: np.array([1.0 + 0 * x[0], 2.0 + 0 * x[0], 3.0 + 0 * x[0]]))
    state.sub(1).interpolate(lambda x: 4.0 + 0 * x[0])
    canonical = where.gather(state.x.array[: len(where.index)])
    cells = mesh.topology.index_map(3).size_local
    nodes = (where.size - cells) // 3
    assert np.array_equal(canonical, np.repeat([1.0, 2.0, 3.0, 4.0], [nodes, nodes, nodes, cells]))


def test_scatter_refuses_an_array_of_another_length():
    where = layout(fem.functionspace(box(COMM, cells=(1, 1, 1)).mesh, ("Lagrange", 1)))
    with pytest.raises(ValueError, match="8 rows"):
        where.scatter(np.zeros(7))
    assert np.array_equal(where.scatter(np.arange(8.0))[np.argsort(where.index)], np.arange(8.0))
