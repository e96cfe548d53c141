"""Nested uniform refinement (lungmech.mesh.refine): the same body, its names and tags, and
values per cell carried from each parent to its children, on one rank and on two."""

from mpi4py import MPI

import dolfinx.geometry
import dolfinx.mesh
import numpy as np
import pytest

from lungmech.errors import GeometryError
from lungmech.mesh import box, lung_phantom, rectangle
from lungmech.mesh.refine import refined


def midpoint_x(mesh: dolfinx.mesh.Mesh) -> np.ndarray:
    """Each global cell's midpoint x, in the mesh's input (file) order, on every rank."""
    tdim = mesh.topology.dim
    owned = mesh.topology.index_map(tdim).size_local
    x = dolfinx.mesh.compute_midpoints(mesh, tdim, np.arange(owned, dtype=np.int32))[:, 0]
    inputs = np.asarray(mesh.topology.original_cell_index[:owned])
    values = np.empty(mesh.topology.index_map(tdim).size_global)
    for where, value in mesh.comm.allgather((inputs, x)):
        values[where] = value
    return values


@pytest.mark.parametrize("times", [1, 2])
def test_a_refined_lung_is_the_same_body_with_its_boundaries(times):
    lung = lung_phantom(MPI.COMM_WORLD, mesh_size=0.04)
    fine = refined(lung, times)
    mesh = fine.geometry.mesh
    assert mesh.topology.index_map(3).size_global == 8**times * lung.mesh.topology.index_map(3).size_global
    assert fine.geometry.volume() == pytest.approx(lung.volume(), rel=1e-12)
    assert dict(fine.geometry.boundaries) == dict(lung.boundaries)
    for name in lung.boundaries:  # every boundary facet keeps its parent's tag
        assert fine.geometry.area(name) == pytest.approx(lung.area(name), rel=1e-12), name


def test_values_per_cell_pass_from_parent_to_children():
    """Each child's value is that of the coarse cell holding its midpoint, in the files' orders."""
    coarse = box(MPI.COMM_WORLD, cells=(3, 2, 2))
    fine = refined(coarse, 2)
    given = midpoint_x(coarse.mesh)
    values = fine.cell_values(given)
    mesh = fine.geometry.mesh
    owned = mesh.topology.index_map(3).size_local
    points = dolfinx.mesh.compute_midpoints(mesh, 3, np.arange(owned, dtype=np.int32))
    tree = dolfinx.geometry.bb_tree(coarse.mesh, 3)
    holding = dolfinx.geometry.compute_colliding_cells(
        coarse.mesh, dolfinx.geometry.compute_collisions_points(tree, points), points
    )
    parents = [holding.links(i) for i in range(owned)]
    assert all(len(links) == 1 for links in parents)  # a child's midpoint is inside one coarse cell, on its rank
    expected = given[np.asarray(coarse.mesh.topology.original_cell_index)[[links[0] for links in parents]]]
    assert np.array_equal(values[np.asarray(mesh.topology.original_cell_index[:owned])], expected)
    assert len(values) == 64 * len(given)


def test_cell_tags_and_a_plane_mesh_are_refined():
    plane = rectangle(MPI.COMM_WORLD, (2.0, 1.0), (4, 2))
    fine = refined(plane)
    assert fine.geometry.mesh.topology.index_map(2).size_global == 4 * 16
    for name in plane.boundaries:
        assert fine.geometry.area(name) == pytest.approx(plane.area(name), rel=1e-12)
    lung = lung_phantom(MPI.COMM_WORLD, mesh_size=0.05)
    assert lung.cell_tags is not None
    tags = refined(lung).geometry.cell_tags
    assert tags is not None
    owned = tags.indices < tags.topology.index_map(3).size_local
    assert MPI.COMM_WORLD.allreduce(int(owned.sum())) == 8 * lung.mesh.topology.index_map(3).size_global


def test_what_cannot_be_refined_is_said_in_one_line():
    with pytest.raises(GeometryError, match="hexahedron cells: only simplex meshes"):
        refined(box(MPI.COMM_WORLD, cells=(1, 1, 1), cell_type="hexahedron"))
    with pytest.raises(GeometryError, match="curved cells"):
        refined(lung_phantom(MPI.COMM_WORLD, mesh_size=0.05, order=2))
    with pytest.raises(GeometryError, match="one or more times"):
        refined(box(MPI.COMM_WORLD), 0)
    with pytest.raises(GeometryError, match="5 cell values for a mesh of 6 cells"):
        refined(box(MPI.COMM_WORLD, cells=(1, 1, 1))).cell_values(np.zeros(5))
