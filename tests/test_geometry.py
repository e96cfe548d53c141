"""Geometries: exact measures of simple shapes, the lung phantom's anatomy, files, MPI."""

import math

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
import ufl
from fem import MESHES

import lungmech  # noqa: F401  (orders MPI before the DOLFINx bindings)
from lungmech.errors import GeometryError
from lungmech.mesh import Geometry, box, ellipsoid, from_file, lung_phantom, plate_with_holes, sphere, write

LUNG_NAMES = {"pleura", "diaphragm", "mediastinum", "hilum"}
OCTANT_1_2 = 4 / 3 * math.pi * (2**3 - 1**3) / 8  # an eighth of the shell 1 < r < 2
# Collective calls must come in the same order on every rank: never loop over a set of strings
# (its order depends on the per-process hash seed), loop over a sorted list.


def centroid(geometry: Geometry, name: str) -> np.ndarray:
    x = ufl.SpatialCoordinate(geometry.mesh)
    comm = geometry.mesh.comm
    moments = [
        comm.allreduce(dolfinx.fem.assemble_scalar(dolfinx.fem.form(x[i] * geometry.ds(name))), op=MPI.SUM)
        for i in range(3)
    ]
    return np.array(moments) / geometry.area(name)


@pytest.fixture(scope="module")
def lungs() -> dict[str, Geometry]:
    return {side: lung_phantom(MPI.COMM_WORLD, side=side) for side in ("right", "left")}


@pytest.mark.parametrize("cell_type", ["tetrahedron", "hexahedron"])
def test_box_measures_are_exact(cell_type):
    geometry = box(MPI.COMM_WORLD, (2.0, 3.0, 4.0), (2, 3, 4), origin=(1.0, -1.0, 0.5), cell_type=cell_type)
    assert dict(geometry.boundaries) == {"x0": 1, "x1": 2, "y0": 3, "y1": 4, "z0": 5, "z1": 6}
    assert geometry.volume() == pytest.approx(24.0, rel=1e-12)
    areas = {"x0": 12.0, "x1": 12.0, "y0": 8.0, "y1": 8.0, "z0": 6.0, "z1": 6.0}
    for name, area in areas.items():
        assert geometry.area(name) == pytest.approx(area, rel=1e-12)
    assert geometry.size == pytest.approx(math.sqrt(4 + 9 + 16), rel=1e-12)


def test_facets_lie_on_their_face():
    geometry = box(MPI.COMM_WORLD, (1.0, 2.0, 3.0), (2, 2, 2), origin=(0.5, 0.0, 0.0))
    facets = geometry.facets("x1")
    midpoints = dolfinx.mesh.compute_midpoints(geometry.mesh, 2, facets)
    assert np.allclose(midpoints[:, 0], 1.5)
    owned = np.count_nonzero(facets < geometry.mesh.topology.index_map(2).size_local)
    assert MPI.COMM_WORLD.allreduce(owned, op=MPI.SUM) == 2 * 2 * 2  # two triangles per square


def test_unknown_boundary_lists_the_names():
    geometry = box(MPI.COMM_SELF, cells=(1, 1, 1))
    listing = "unknown boundary 'nope'; this geometry has: x0, x1, y0, y1, z0, z1"
    with pytest.raises(GeometryError, match=listing):
        geometry.tag("nope")
    with pytest.raises(GeometryError, match="nope"):
        geometry.ds("nope")


def test_bad_parameters_are_geometry_errors():
    with pytest.raises(GeometryError, match="cell_type"):
        box(MPI.COMM_SELF, cell_type="prism")
    with pytest.raises(GeometryError, match="inner_radius < outer_radius"):
        sphere(MPI.COMM_SELF, 2.0, 1.0)
    with pytest.raises(GeometryError, match="order"):
        sphere(MPI.COMM_SELF, order=3)
    with pytest.raises(GeometryError, match="side"):
        lung_phantom(MPI.COMM_SELF, side="middle")


def test_thick_sphere_octant_volume_converges_faster_with_curved_cells():
    A, B = 1.0, 2.0
    exact_volume = 4 / 3 * math.pi * (B**3 - A**3) / 8
    errors = {}
    for order in (1, 2):
        geometry = sphere(MPI.COMM_WORLD, A, B, octant=True, order=order)
        assert set(geometry.boundaries) == {"inner", "outer", "x0", "y0", "z0"}
        errors[order] = abs(geometry.volume() / exact_volume - 1)
        assert geometry.area("inner") == pytest.approx(math.pi * A**2 / 2, rel=0.02 if order == 1 else 1e-3)
        assert geometry.area("outer") == pytest.approx(math.pi * B**2 / 2, rel=0.02 if order == 1 else 1e-3)
        assert geometry.area("x0") == pytest.approx(math.pi * (B**2 - A**2) / 4, rel=0.02)
    assert errors[1] < 0.02
    assert errors[2] < errors[1] / 100  # measured: 3.6e-3 vs 1.7e-6


def test_ball_and_ellipsoids():
    ball = sphere(MPI.COMM_WORLD, 0.0, 1.5, octant=False)
    assert set(ball.boundaries) == {"outer"}
    assert ball.volume() == pytest.approx(4 / 3 * math.pi * 1.5**3, rel=0.03)

    shell = ellipsoid(MPI.COMM_WORLD, (1.0, 0.8, 0.6), (0.5, 0.4, 0.3), octant=True, order=2)
    assert set(shell.boundaries) == {"inner", "outer", "x0", "y0", "z0"}
    assert shell.volume() == pytest.approx(4 / 3 * math.pi * (0.48 - 0.06) / 8, rel=1e-4)
    assert shell.area("z0") == pytest.approx(math.pi * (1.0 * 0.8 - 0.5 * 0.4) / 4, rel=1e-3)


def test_a_plate_with_holes_has_its_area_edges_and_holes():
    """NeuROM's anchor plate (10 × 10, three holes): the area and the holes' perimeter (a 2-D
    facet's "area" is its length) converge on the exact ones, curved cells faster; the edges
    are named; a hole outside the plate or two that overlap are refused in one line."""
    holes = ((2.5, 2.5, 1.0), (5.0, 7.5, 5.0 / 3.0), (7.5, 2.5, 0.5))
    area = 100.0 - math.pi * sum(r**2 for _, _, r in holes)
    perimeter = 2 * math.pi * sum(r for _, _, r in holes)
    errors = {}
    for order in (1, 2):
        plate = plate_with_holes(MPI.COMM_WORLD, mesh_size=0.5, order=order)
        assert set(plate.boundaries) == {"x0", "x1", "y0", "y1", "holes"}
        assert plate.mesh.geometry.dim == 2 and plate.area("y1") == pytest.approx(10.0, rel=1e-12)
        errors[order] = abs(plate.volume() / area - 1)
        assert plate.area("holes") == pytest.approx(perimeter, rel=2e-2 if order == 1 else 1e-3)
    assert errors[1] < 1e-2 and errors[2] < errors[1] / 100  # measured: 4.0e-3
    with pytest.raises(GeometryError, match=r"hole 1 \(9, 5, r = 2\) is not inside the plate"):
        plate_with_holes(MPI.COMM_WORLD, holes=((9.0, 5.0, 2.0),))
    with pytest.raises(GeometryError, match="holes 1 and 2 overlap"):
        plate_with_holes(MPI.COMM_WORLD, holes=((3.0, 3.0, 1.0), (4.5, 3.0, 1.0)))


def test_gmsh_meshes_are_reproducible_and_leave_gmsh_alone(tmp_path):
    import gmsh

    folder = tmp_path
    gmsh.initialize()
    gmsh.model.add("mine")
    try:
        for name in ("a.msh", "b.msh"):
            sphere(MPI.COMM_WORLD, 1.0, 2.0, mesh_size=0.5, msh_file=folder / name)
        assert gmsh.isInitialized() and gmsh.model.getCurrent() == "mine"
    finally:
        gmsh.finalize()
    assert (folder / "a.msh").read_bytes() == (folder / "b.msh").read_bytes()


def test_lung_phantom_anatomy(lungs):
    right, left = lungs["right"], lungs["left"]
    for geometry in (right, left):
        assert set(geometry.boundaries) == LUNG_NAMES
        assert 1.5e-3 < geometry.volume() < 3e-3  # an adult lung holds 1.5 to 3 litres
        areas = {name: geometry.area(name) for name in sorted(LUNG_NAMES)}
        assert all(area > 0 for area in areas.values())
        assert areas["hilum"] < areas["mediastinum"] / 10
        assert areas["pleura"] > areas["mediastinum"] > areas["hilum"]
        assert geometry.cell_tags is not None and set(np.unique(geometry.cell_tags.values)) <= {1}
        # The hilum sits on the medial plane x = 0 near mid-height, the diaphragm at the bottom.
        hilum = centroid(geometry, "hilum")
        assert abs(hilum[0]) < 1e-9 and 0.45 * 0.24 < hilum[2] < 0.75 * 0.24
        assert centroid(geometry, "diaphragm")[2] < 0.25 * 0.24 < centroid(geometry, "pleura")[2]
    assert left.volume() < 0.97 * right.volume()  # the cardiac notch
    assert centroid(right, "pleura")[0] > 0 > centroid(left, "pleura")[0]  # mirror images


def test_missing_and_unsupported_files():
    with pytest.raises(GeometryError, match=r"mesh file 'missing\.msh' not found"):
        from_file("missing.msh")
    with pytest.raises(GeometryError, match=r"lung\.stl': suffix '\.stl' is not \.msh, \.vtu or \.xdmf"):
        from_file("lung.stl")


def test_files_without_facet_tags_are_rejected(tmp_path):
    import gmsh

    folder = tmp_path
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 1, 1, 1)
    with dolfinx.io.XDMFFile(MPI.COMM_WORLD, str(folder / "bare.xdmf"), "w") as file:
        file.write_mesh(mesh)
    with pytest.raises(GeometryError, match=r"bare\.xdmf' has no facet tags"):
        from_file(folder / "bare.xdmf")

    if MPI.COMM_WORLD.rank == 0:  # a .msh with a volume group only
        gmsh.initialize()
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [1], 1, "solid")
        gmsh.model.mesh.generate(3)
        gmsh.write(str(folder / "bare.msh"))
        gmsh.finalize()
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(GeometryError, match=r"bare\.msh' has no facet tags"):
        from_file(folder / "bare.msh")


def test_write_and_read_back(tmp_path, lungs):
    folder = tmp_path
    geometries = {
        "hexbox": box(MPI.COMM_WORLD, (1.0, 2.0, 0.5), (2, 2, 2), cell_type="hexahedron"),
        "curved_sphere": sphere(MPI.COMM_WORLD, order=2),
        "lung": lungs["left"],
    }
    for name, original in geometries.items():
        write(original, folder / f"{name}.xdmf")
        copy = from_file(folder / f"{name}.xdmf")
        assert dict(copy.boundaries) == dict(original.boundaries)
        assert (copy.cell_tags is None) == (original.cell_tags is None)
        assert copy.volume() == pytest.approx(original.volume(), rel=1e-12)
        for boundary in original.boundaries:
            assert copy.area(boundary) == pytest.approx(original.area(boundary), rel=1e-12)

    # Without the sidecar, names come from the argument, or else are the tag numbers.
    if MPI.COMM_WORLD.rank == 0:
        (folder / "hexbox.tags.json").unlink()
    MPI.COMM_WORLD.Barrier()
    assert set(from_file(folder / "hexbox.xdmf").boundaries) == {"1", "2", "3", "4", "5", "6"}
    renamed = from_file(folder / "hexbox.xdmf", boundaries={"left": 1, "right": 2})
    assert renamed.area("right") == pytest.approx(1.0, rel=1e-12)
    with pytest.raises(GeometryError, match="boundary 'top' has tag 9, which no facet carries"):
        from_file(folder / "hexbox.xdmf", boundaries={"top": 9})


@pytest.mark.parametrize(
    ("filename", "names", "volume"),
    [
        ("lung_phantom_right.msh", LUNG_NAMES, (1.5e-3, 3e-3)),
        ("lung_phantom_left.msh", LUNG_NAMES, (1.5e-3, 3e-3)),
        ("sphere_octant.msh", {"inner", "outer", "x0", "y0", "z0"}, (0.98 * OCTANT_1_2, OCTANT_1_2)),
    ],
)
def test_bundled_meshes_load(filename, names, volume):
    geometry = from_file(MESHES / filename)
    assert set(geometry.boundaries) == names
    assert volume[0] < geometry.volume() < volume[1]
    assert min(geometry.area(name) for name in sorted(names)) > 0
    cells = geometry.mesh.topology.index_map(3).size_global
    assert 500 < cells < 10_000


@pytest.mark.mpi
def test_distributed_measures_match_serial():
    for build in (lambda comm: sphere(comm, order=2), lambda comm: lung_phantom(comm, side="left")):
        distributed, serial = build(MPI.COMM_WORLD), build(MPI.COMM_SELF)
        cells = [g.mesh.topology.index_map(3).size_global for g in (distributed, serial)]
        assert cells[0] == cells[1]
        assert distributed.volume() == pytest.approx(serial.volume(), rel=1e-12)
        assert distributed.size == pytest.approx(serial.size, rel=1e-12)
        for name in serial.boundaries:
            assert distributed.area(name) == pytest.approx(serial.area(name), rel=1e-12)
