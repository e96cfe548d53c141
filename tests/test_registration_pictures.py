"""Registration pictures: the geometry behind them (boundary triangles, plane sections) and the PNGs."""

from mpi4py import MPI

import matplotlib.image
import numpy as np
import pytest

from lungmech.errors import RegistrationError
from lungmech.mesh import sphere
from lungmech.registration.image import from_array
from lungmech.registration.metrics import boundary_triangles
from lungmech.registration.pictures import (
    plane_section,
    registration_slices,
    shape_spectrum,
    surface_sections,
)

R = 0.03  # ball radius (m)
H = 0.008  # mesh size (m)
VOXEL = 0.002  # image spacing (m)
# matplotlib's tab: colours, and the mask's grey
RED, BLUE, GREY = (0.839, 0.153, 0.157), (0.122, 0.467, 0.706), (0.72, 0.72, 0.72)
ORANGE, GREEN = (1.0, 0.498, 0.055), (0.173, 0.627, 0.173)


def ball(comm):
    return sphere(comm, 0.0, R, mesh_size=H, octant=False).mesh


@pytest.fixture(scope="module")
def mesh():
    return ball(MPI.COMM_SELF)


@pytest.fixture(scope="module")
def image():
    """A voxel ball of radius R at the origin, on an anisotropic grid (for the aspect ratio)."""
    spacing = np.array([VOXEL, VOXEL, 1.5 * VOXEL])
    n = (2 * np.ceil(1.2 * R / spacing) + 1).astype(int)
    index = np.indices(n).reshape(3, -1).T
    origin = -(n - 1) / 2 * spacing
    mask = (np.linalg.norm(index * spacing + origin, axis=1) < R).reshape(n)
    return from_array(mask, spacing, origin)


def area(triangles: np.ndarray) -> float:
    a, b, c = triangles.transpose(1, 0, 2)
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()


def share(picture: np.ndarray, colour) -> float:
    """Fraction of pixels within 0.03 of an RGB colour."""
    return np.mean(np.all(np.abs(picture[..., :3] - colour) < 0.03, axis=-1))


def test_boundary_triangles_cover_the_sphere(mesh):
    triangles = boundary_triangles(mesh)
    assert triangles.shape[1:] == (3, 3) and len(triangles) > 100
    assert np.linalg.norm(triangles, axis=2) == pytest.approx(R, rel=1e-6)  # vertices on the sphere
    # Inscribed flat facets: a little less than the sphere, by O((H / R)^2).
    assert 0.95 * 4 * np.pi * R**2 < area(triangles) < 4 * np.pi * R**2


def test_octahedron_cut_through_its_vertices_is_its_square_equator():
    """Four vertices lie on the plane: counted above it, they still give one clean loop."""
    e = np.eye(3)
    signs = [(sx, sy, sz) for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)]
    triangles = np.array([[sx * e[0], sy * e[1], sz * e[2]] for sx, sy, sz in signs])
    [loop] = plane_section(triangles, (0, 0, 1), 0.0)
    assert len(loop) == 5 and np.array_equal(loop[0], loop[-1])
    corners = {tuple(point) for point in loop.tolist()}
    assert corners == {(1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, -1.0, 0.0)}
    assert plane_section(triangles, (0, 0, 1), 2.0) == []  # a plane missing the surface


@pytest.mark.parametrize("normal, height", [((0, 0, 1), 0.0), ((1, 2, 3), 0.0), ((1, -1, 0.5), 0.6 * R)])
def test_sphere_cut_by_a_plane_is_one_circle(mesh, normal, height):
    """Points on the plane, at the circle's radius from its centre, one closed loop 2πρ long."""
    normal = np.array(normal, dtype=float)
    unit = normal / np.linalg.norm(normal)
    [loop] = plane_section(boundary_triangles(mesh), normal, height * np.linalg.norm(normal))
    assert np.array_equal(loop[0], loop[-1])
    assert loop @ unit == pytest.approx(height, abs=1e-12)
    # The points lie on facet edges, chords that dip inside the sphere by L^2 / (8 R) (L <~ 2 H).
    radius = np.linalg.norm(loop, axis=1)
    assert np.all(radius <= R * (1 + 1e-9)) and np.all(radius > R - (2 * H) ** 2 / (8 * R))
    rho = np.sqrt(R**2 - height**2)
    assert np.linalg.norm(loop - height * unit, axis=1) == pytest.approx(rho, rel=0.05)
    length = np.linalg.norm(np.diff(loop, axis=0), axis=1).sum()
    assert length == pytest.approx(2 * np.pi * rho, rel=0.03)


def test_plane_section_rejects_a_zero_normal():
    with pytest.raises(RegistrationError, match="normal"):
        plane_section(np.zeros((1, 3, 3)), (0, 0, 0), 0.0)


@pytest.mark.serial  # reads the picture rank 0 draws
def test_registration_slices_draw_the_mask_the_mesh_and_the_reference(mesh, image, tmp_path):
    path = tmp_path / "new" / "folder" / "slices.png"
    reference = 0.8 * boundary_triangles(mesh) + [0.004, 0.0, 0.0]  # smaller and shifted
    registration_slices(mesh, image, path, title="ball", reference=reference)
    assert path.stat().st_size > 10_000
    picture = matplotlib.image.imread(path)
    rows, columns, channels = picture.shape
    assert channels in (3, 4) and columns > 2 * rows > 600  # three panels side by side
    assert share(picture, (1.0, 1.0, 1.0)) > 0.3  # background
    assert share(picture, GREY) > 0.05  # the mask
    assert share(picture, RED) > 1e-3  # the mesh
    assert share(picture, BLUE) > 5e-4  # the reference, dashed


@pytest.mark.serial  # reads the picture rank 0 draws
def test_registration_slices_without_reference_has_no_blue(mesh, image, tmp_path):
    registration_slices(mesh, image, tmp_path / "slices.png")
    picture = matplotlib.image.imread(tmp_path / "slices.png")
    assert share(picture, RED) > 1e-3 and share(picture, BLUE) == 0.0


@pytest.mark.serial  # a one-rank picture: under mpiexec both ranks drew into one tmp_path, and one read a half-written PNG
def test_shape_spectrum_with_and_without_leave_one_out(tmp_path):
    sigma = np.array([3.0, 1.2, 0.5, 0.1, 0.02]) * 1e-3
    errors = np.array([2.1, 1.5, 1.1, 0.9, 0.85]) * 1e-3
    shape_spectrum(sigma, tmp_path / "both.png", leave_one_out=errors, title="library")
    shape_spectrum(sigma, tmp_path / "spectrum.png")
    both, alone = (matplotlib.image.imread(tmp_path / name) for name in ("both.png", "spectrum.png"))
    assert (tmp_path / "both.png").stat().st_size > 10_000
    assert both.shape[0] == alone.shape[0] and both.shape[1] == 2 * alone.shape[1]
    for colour in (BLUE, ORANGE, GREEN):
        assert share(both, colour) > 1e-4
    assert share(alone, GREEN) == 0.0
    with pytest.raises(RegistrationError):
        shape_spectrum([0.0, 0.0], tmp_path / "zero.png")


@pytest.mark.serial  # a one-rank picture, as the spectrum above
def test_surface_sections_draw_every_surface(mesh, tmp_path):
    triangles = boundary_triangles(mesh)
    path = tmp_path / "sections.png"
    surface_sections({"ball": triangles, "bigger": 1.2 * triangles, "shifted": triangles + 0.005}, path, title="t")
    pixels = matplotlib.image.imread(path)[..., :3]
    assert path.stat().st_size > 10_000 and pixels.shape[1] > 2 * pixels.shape[0]
    with pytest.raises(RegistrationError, match="no surface"):
        surface_sections({}, path)


@pytest.mark.mpi
def test_boundary_triangles_same_on_all_ranks_as_on_one(tmp_path):
    comm = MPI.COMM_WORLD
    parallel, serial = boundary_triangles(ball(comm)), boundary_triangles(ball(MPI.COMM_SELF))
    assert parallel.shape == serial.shape
    assert area(parallel) == pytest.approx(area(serial), rel=1e-12)
    # The same triangles, whatever their order.
    centroids = [np.unique(t.mean(axis=1).round(12), axis=0) for t in (parallel, serial)]
    assert np.allclose(*centroids, rtol=0.0, atol=1e-12)
    # Drawing is collective; only rank 0 writes.
    path = comm.bcast(str(tmp_path / "slices.png"), root=0)
    mask = np.zeros((20, 20, 20), dtype=bool)
    mask[5:15, 5:15, 5:15] = True
    registration_slices(ball(comm), from_array(mask, (0.004,) * 3, (-0.038,) * 3), path)
    comm.Barrier()
    if comm.rank == 0:
        assert matplotlib.image.imread(path).shape[0] > 600
