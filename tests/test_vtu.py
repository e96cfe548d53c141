"""Mesh files every tool opens: lungmech's .vtu read back by meshio, pyvista and lungmech.

The references are independent of lungmech's reader: meshio's and VTK's own parsers, and the
source mesh's nodes by their input index (the partition-independent order the file promises).
"""

from pathlib import Path

from mpi4py import MPI

import meshio
import numpy as np
import pytest
import pyvista

import lungmech  # noqa: F401  (orders MPI before the DOLFINx bindings)
from lungmech.errors import GeometryError
from lungmech.mesh import Geometry, box, from_file, is_lungmech_mesh, lung_phantom, rectangle, sphere, write

# VTK's cell types (vtkCellType.h) by dimension: lines, triangles, quads, tetrahedra, hexahedra, quadratic.
_VTK_DIMENSION = {3: 1, 21: 1, 5: 2, 22: 2, 9: 2, 10: 3, 24: 3, 12: 3}

BUILDS = {
    "tetrahedra": lambda comm: box(comm, (2.0, 1.0, 1.0), (3, 2, 2)),
    "hexahedra": lambda comm: box(comm, (2.0, 1.0, 0.5), (3, 2, 2), cell_type="hexahedron"),
    "plane": lambda comm: rectangle(comm, (2.0, 1.0), (3, 2)),
    "quadratic": lambda comm: sphere(comm, order=2),
    "lung": lambda comm: lung_phantom(comm, side="left"),
}


@pytest.fixture(scope="module", params=sorted(BUILDS))
def written(request, tmp_path_factory) -> tuple[Geometry, Path]:
    """A geometry and the .vtu lungmech wrote of it (in a folder all ranks share)."""
    folder = Path(MPI.COMM_WORLD.bcast(str(tmp_path_factory.mktemp("vtu")), root=0))
    geometry = BUILDS[request.param](MPI.COMM_WORLD)
    write(geometry, folder / f"{request.param}.vtu")
    return geometry, folder / f"{request.param}.vtu"


def _nodes_by_input(geometry: Geometry) -> dict[int, np.ndarray]:
    """Every node of the mesh by its input index (gathered from all ranks)."""
    g = geometry.mesh.geometry
    owned = g.index_map().size_local
    mine = dict(zip(g.input_global_indices[:owned].tolist(), g.x[:owned]))
    return {k: v for part in geometry.mesh.comm.allgather(mine) for k, v in part.items()}


def _global_count(geometry: Geometry, tag: int) -> int:
    tags, owned = geometry.facet_tags, geometry.mesh.topology.index_map(geometry.mesh.topology.dim - 1).size_local
    return geometry.mesh.comm.allreduce(int(np.sum(tags.values[tags.indices < owned] == tag)), op=MPI.SUM)


def test_meshio_reads_nodes_in_input_order_and_the_tags(written):
    geometry, path = written
    nodes = _nodes_by_input(geometry)
    if MPI.COMM_WORLD.rank == 0:
        data = meshio.read(path)
        assert len(data.points) == len(nodes)
        order = sorted(nodes)
        np.testing.assert_array_equal(data.points, np.array([nodes[k] for k in order]))
        facet_tags = data.cell_data["tags"][-1]  # the facets are the file's last block
        for name, tag in geometry.boundaries.items():
            assert data.field_data[name].tolist() == [tag, geometry.mesh.topology.dim - 1]
    counts = {tag: _global_count(geometry, tag) for tag in sorted(set(geometry.boundaries.values()))}
    if MPI.COMM_WORLD.rank == 0:
        assert {tag: int(np.sum(facet_tags == tag)) for tag in counts} == counts


def test_pyvista_measures_the_body_and_each_boundary(written):
    """VTK's reader and its own cell measures give the volume and every boundary's area."""
    geometry, path = written
    areas = {name: geometry.area(name) for name in sorted(geometry.boundaries)}
    volume = geometry.volume()
    if MPI.COMM_WORLD.rank != 0:
        return
    grid = pyvista.read(path)
    dim = geometry.mesh.topology.dim
    assert grid.n_cells == len(grid.celltypes) and set(geometry.boundaries) <= set(grid.field_data)
    sizes = grid.compute_cell_sizes(length=True, area=True, volume=True)
    dims = np.array([_VTK_DIMENSION[t] for t in grid.celltypes])
    measure, facet_measure = ("Volume", "Area") if dim == 3 else ("Area", "Length")
    # VTK measures a quadratic cell by its subdivision into straight ones (2e-3 here); a midpoint
    # in the wrong place would fold those pieces over and miss by far more.
    rel = 5e-3 if max(grid.celltypes) in (21, 22, 24) else 1e-12
    assert np.sum(sizes.cell_data[measure][dims == dim]) == pytest.approx(volume, rel=rel)
    tags = grid.cell_data["tags"]
    for name, area in areas.items():
        on = (dims == dim - 1) & (tags == geometry.boundaries[name])
        assert np.sum(sizes.cell_data[facet_measure][on]) == pytest.approx(area, rel=rel)


def test_lungmech_reads_it_back_in_the_same_order(written, tmp_path):
    geometry, path = written
    back = from_file(path, MPI.COMM_WORLD)
    assert dict(back.boundaries) == dict(geometry.boundaries)
    assert back.volume() == pytest.approx(geometry.volume(), rel=1e-12)
    for name in sorted(geometry.boundaries):
        assert back.area(name) == pytest.approx(geometry.area(name), rel=1e-12)
    before, after = _nodes_by_input(geometry), _nodes_by_input(back)
    assert sorted(after) == list(range(len(before)))  # the file's order is the new input order
    np.testing.assert_array_equal([after[i] for i in range(len(after))], [before[k] for k in sorted(before)])
    assert (back.cell_tags is None) == (geometry.cell_tags is None)

    again = tmp_path / "again.vtu"
    write(back, again)
    if MPI.COMM_WORLD.rank == 0:
        assert again.read_bytes() == path.read_bytes()  # a round trip changes nothing
        assert is_lungmech_mesh(path) and is_lungmech_mesh(again)


def test_cell_tags_survive(tmp_path):
    """Two regions of a box, tagged 2 and 7, come back on the same cells."""
    import dolfinx.mesh

    comm = MPI.COMM_WORLD
    source = box(comm, (2.0, 1.0, 1.0), (4, 2, 2))
    mesh = source.mesh
    cells = np.arange(mesh.topology.index_map(3).size_local + mesh.topology.index_map(3).num_ghosts, dtype=np.int32)
    midpoints = dolfinx.mesh.compute_midpoints(mesh, 3, cells)
    tags = dolfinx.mesh.meshtags(mesh, 3, cells, np.where(midpoints[:, 0] < 1.0, 2, 7).astype(np.int32))
    write(Geometry(mesh, source.facet_tags, source.boundaries, tags), tmp_path / "regions.vtu")
    back = from_file(tmp_path / "regions.vtu", comm)
    assert back.cell_tags is not None
    m = back.mesh
    owned = m.topology.index_map(3).size_local
    left = back.cell_tags.indices[(back.cell_tags.values == 2) & (back.cell_tags.indices < owned)]
    right = back.cell_tags.indices[(back.cell_tags.values == 7) & (back.cell_tags.indices < owned)]
    assert np.all(dolfinx.mesh.compute_midpoints(m, 3, left)[:, 0] < 1.0)
    assert np.all(dolfinx.mesh.compute_midpoints(m, 3, right)[:, 0] > 1.0)
    assert comm.allreduce(len(left) + len(right), op=MPI.SUM) == m.topology.index_map(3).size_global


@pytest.mark.mpi
def test_the_file_does_not_depend_on_the_partition(tmp_path):
    """Written from every rank, the file is byte for byte the one written from one."""
    comm = MPI.COMM_WORLD
    for name in ("hexahedra", "lung"):
        write(BUILDS[name](comm), tmp_path / f"{name}-distributed.vtu")
        if comm.rank == 0:
            write(BUILDS[name](MPI.COMM_SELF), tmp_path / f"{name}-serial.vtu")
        comm.Barrier()
        serial = (tmp_path / f"{name}-serial.vtu").read_bytes()
        assert (tmp_path / f"{name}-distributed.vtu").read_bytes() == serial


def _meshio_file(path: Path, cells: list, cell_data: dict | None = None, points=None) -> Path:
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float) if points is None else points
    meshio.write(path, meshio.Mesh(points, cells, cell_data=cell_data or {}), file_format="vtu")
    return path


TETRA, FACE = [("tetra", [[0, 1, 2, 3]])], [("triangle", [[0, 1, 2]])]


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: p.write_text("not xml"), "cannot read mesh file"),
        (lambda p: _meshio_file(p, TETRA + FACE), "has no cell data 'tags'"),
        (lambda p: _meshio_file(p, TETRA, {"tags": [np.array([0])]}), "has no tagged facets"),
        (lambda p: _meshio_file(p, TETRA + FACE, {"tags": [np.array([0.0]), np.array([1.5])]}), "not integer"),
        (
            lambda p: _meshio_file(p, [("wedge", [[0, 1, 2, 3, 0, 1]])], {"tags": [np.array([1])]}),
            "cells of type wedge",
        ),
        (
            lambda p: _meshio_file(
                p, TETRA + [("hexahedron", [[0, 1, 2, 3, 0, 1, 2, 3]])], {"tags": [np.array([0]), np.array([0])]}
            ),
            "must hold one kind of 2-D or 3-D cell",
        ),
        (
            lambda p: _meshio_file(
                p,
                [("triangle", [[0, 1, 2]]), ("line", [[0, 1]])],
                {"tags": [np.array([0]), np.array([1])]},
                np.array([[0, 0, 0], [1, 0, 0], [0, 1, 1.0]]),
            ),
            "does not lie in z = 0",
        ),
    ],
)
def test_bad_files_are_one_line(tmp_path, make, message):
    path = tmp_path / "bad.vtu"
    if MPI.COMM_WORLD.rank == 0:
        make(path)
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(GeometryError, match=message) as error:
        from_file(path, MPI.COMM_SELF)
    assert "bad.vtu" in str(error.value) and "\n" not in str(error.value)
    assert not is_lungmech_mesh(path)


def test_a_changed_file_is_no_longer_lungmechs(tmp_path):
    write(box(MPI.COMM_WORLD, (1.0, 1.0, 1.0), (1, 1, 1)), tmp_path / "cube.vtu")
    assert is_lungmech_mesh(tmp_path / "cube.vtu")
    MPI.COMM_WORLD.Barrier()  # every rank has looked before rank 0 changes it
    if MPI.COMM_WORLD.rank == 0:
        data = meshio.read(tmp_path / "cube.vtu")
        data.points[0, 0] += 0.1
        meshio.write(tmp_path / "cube.vtu", data, file_format="vtu")  # field data, digest included, is dropped
    MPI.COMM_WORLD.Barrier()
    assert not is_lungmech_mesh(tmp_path / "cube.vtu")
    from_file(tmp_path / "cube.vtu", MPI.COMM_SELF)  # still a mesh lungmech reads (its boundaries by number)


def test_tags_must_be_positive(tmp_path):
    import dolfinx.mesh

    geometry = box(MPI.COMM_SELF, (1.0, 1.0, 1.0), (1, 1, 1))
    tags = geometry.facet_tags
    zero = dolfinx.mesh.meshtags(geometry.mesh, 2, tags.indices, np.where(tags.values == 1, 0, tags.values))
    with pytest.raises(GeometryError, match="tag 0 is not a positive integer"):
        write(Geometry(geometry.mesh, zero, {"x1": 2}), tmp_path / "zero.vtu")
