"""Synthetic lung phantoms: the analytic shape, its voxel images, and latent-parameter cohorts."""

import math
from dataclasses import replace

from mpi4py import MPI

import numpy as np
import pytest
from fem import MESHES
from scipy.spatial.transform import Rotation

import lungmech  # noqa: F401  (orders MPI before the DOLFINx bindings)
from lungmech.errors import GeometryError, ParameterError
from lungmech.mesh import from_file, lung_phantom
from lungmech.mesh.lung_shape import LungShape
from lungmech.registration.phantom import LATENT, cohort, voxelise

# Volumes by adaptive quadrature (QUADPACK over z, relative tolerance 1e-10, of the slice area
# from a 10^5-point midpoint rule in x, itself checked against QUADPACK to 1e-9).
REFERENCE_VOLUME = {"right": 2.522092648193e-3, "left": 2.334231229591e-3}


def centroid(image) -> np.ndarray:
    return image.points(np.argwhere(image.mask)).mean(axis=0)


def touches_border(mask: np.ndarray) -> bool:
    return any(np.moveaxis(mask, axis, 0)[[0, -1]].any() for axis in range(3))


@pytest.fixture(scope="module")
def curved_left_lung():
    """The left lung (it has every primitive, the notch too) in curved quadratic cells."""
    return lung_phantom(MPI.COMM_SELF, side="left", order=2)


def test_default_shape_is_the_original_phantom():
    # The numbers the builder used before LungShape existed, to the last bit.
    right, left = LungShape(), LungShape(side="left")
    W, D, H = 0.11, 0.17, 0.24
    assert np.array_equal(right.upper_axes, [0.75 * W, 0.5 * D, H - 0.3 * H])
    assert np.array_equal(left.body_centre, [-1.0 * (W - 0.75 * W), 0.0, 0.3 * H])
    assert (right.notch_radius, left.notch_radius) == (0.0, 0.45 * W)
    assert LungShape(side="left", notch=0.0).notch_radius == 0.0
    # Without its notch, the left lung is the mirror image of the right one.
    points = np.random.default_rng(0).uniform(*right.bounds(), size=(20_000, 3))
    mirrored = points * [-1.0, 1.0, 1.0]
    assert np.array_equal(right.inside(points), LungShape(side="left", notch=0.0).inside(mirrored))
    assert LungShape(side="left").inside(mirrored).sum() < right.inside(points).sum()


@pytest.mark.parametrize("side", ["right", "left"])
def test_volume_is_accurate(side):
    shape = LungShape(side=side)
    assert shape.volume() == pytest.approx(REFERENCE_VOLUME[side], rel=2e-6)
    # The bundled linear meshes (2.51 and 2.32 litres) inscribe the convex, curved pleura and so
    # lose a little volume: h^2 / (8 R) of sagitta over most of the surface, measured 0.7 % and 0.5 %.
    linear = from_file(MESHES / f"lung_phantom_{side}.msh", MPI.COMM_SELF).volume()
    assert 0.99 * shape.volume() < linear < shape.volume()


def test_volume_matches_a_curved_mesh(curved_left_lung):
    # Quadratic cells follow the surfaces to O(h^3): measured 5e-6 at the default size.
    assert curved_left_lung.volume() == pytest.approx(LungShape(side="left").volume(), rel=2e-5)


def test_points_in_mesh_cells_are_inside(curved_left_lung):
    mesh = curved_left_lung.mesh
    cmap, nodes = mesh.geometry.cmaps[0], mesh.geometry.x[mesh.geometry.dofmaps[0]]
    # Points spread over each (curved) cell, from its centroid towards each of its corners.
    reference = [[0.25, 0.25, 0.25], [0.1, 0.1, 0.1], [0.7, 0.1, 0.1], [0.1, 0.7, 0.1], [0.1, 0.1, 0.7]]
    points = np.concatenate([cmap.push_forward(np.array(reference), cell) for cell in nodes])
    assert LungShape(side="left").inside(points).all()


@pytest.mark.parametrize("side", ["right", "left"])
def test_voxel_volume_converges(side):
    shape = LungShape(side=side)
    errors = {}
    for spacing in (0.0025, 0.001):
        image = voxelise(shape, spacing)
        assert not touches_border(image.mask)
        errors[spacing] = abs(image.volume / shape.volume() - 1)
    assert errors[0.001] < errors[0.0025] < 0.01
    assert errors[0.001] < 1e-3  # measured: 3.5e-4 at 2.5 mm, 3e-5 at 1 mm (right)


def test_voxel_grid_is_ct_like():
    image = voxelise(LungShape(), 0.002)
    assert np.allclose(image.spacing, 0.002)
    assert 60 < image.shape[0] < 90 and 90 < image.shape[1] < 120 and 120 < image.shape[2] < 160
    # The box around the set voxels, plus the 15 mm margin (whole voxels, rounded up).
    lo, hi = image.bounds()
    voxels = image.points(np.argwhere(image.mask))
    set_lo, set_hi = voxels.min(axis=0), voxels.max(axis=0)
    assert np.all(set_lo - lo >= 0.015) and np.all(set_lo - lo < 0.015 + 0.003)
    assert np.all(hi - set_hi >= 0.015) and np.all(hi - set_hi < 0.015 + 0.003)


def test_rigid_motion_moves_the_voxels():
    shape, spacing = LungShape(), 0.002
    still = voxelise(shape, spacing)
    offset = np.array([0.01, -0.02, 0.03])  # whole voxels: the same grid, shifted
    moved = voxelise(shape, spacing, offset=offset)
    assert moved.affine[:3, 3] - still.affine[:3, 3] == pytest.approx(offset, abs=1e-12)
    # The same mask but for a voxel or two whose centre lies on the surface, up to rounding.
    assert np.count_nonzero(moved.mask != still.mask) <= 4
    assert centroid(moved) - centroid(still) == pytest.approx(offset, abs=1e-5)

    rotation = Rotation.from_rotvec([0.2, -0.1, 0.3]).as_matrix()
    offset = np.array([0.0013, 0.0071, -0.0042])  # not on the grid
    turned = voxelise(shape, spacing, offset=offset, rotation=rotation)
    assert turned.volume == pytest.approx(shape.volume(), rel=1e-3)  # measured 1e-4
    # Sampling error of a centroid: a small fraction of a voxel (measured 0.02 mm).
    assert np.linalg.norm(centroid(turned) - (rotation @ centroid(still) + offset)) < 0.05 * spacing


def test_bad_input_is_refused():
    for bad in (
        {"side": "middle"},
        {"height": -0.1},
        {"width": math.nan},
        {"apex": 0.6},
        {"dome": 0.0},
        {"mediastinal": 0.1},
        {"notch": 0.7},
        {"notch": -0.1},
    ):
        with pytest.raises(GeometryError):
            LungShape(**bad)
    with pytest.raises(GeometryError, match="side"):
        lung_phantom(MPI.COMM_SELF, side="middle")
    with pytest.raises(GeometryError, match="height=0.3"):
        lung_phantom(MPI.COMM_SELF, 0.3, shape=LungShape(apex=0.25))
    with pytest.raises(GeometryError, match=r"\(n, 3\)"):
        LungShape().inside(np.zeros(3))

    for spacing in (0.0, (0.001, 0.002)):
        with pytest.raises(ParameterError, match="spacing"):
            voxelise(LungShape(), spacing)
    with pytest.raises(ParameterError, match="margin"):
        voxelise(LungShape(), margin=-0.01)
    with pytest.raises(ParameterError, match="rotation"):
        voxelise(LungShape(), rotation=np.diag([1.0, 1.0, -1.0]))  # a reflection
    with pytest.raises(ParameterError, match="offset"):
        voxelise(LungShape(), offset=(0.0, 0.0))

    for bad in (
        {"size": 0},
        {"latent": 0},
        {"latent": 6},
        {"spread": -1.0},
        {"tilt": math.inf},
        {"side": "right", "base": LungShape(side="left")},
    ):
        with pytest.raises(ParameterError):
            cohort(**{"size": 3} | bad)


def test_cohort_is_reproducible():
    a, b = cohort(12, 3, seed=4), cohort(12, 3, seed=4)
    assert a.latent.shape == (12, 3) and a.names == tuple(LATENT)[:3] == ("elongation", "dome", "apex")
    assert len(a) == 12
    assert np.array_equal(a.latent, b.latent) and a.shapes == b.shapes
    assert not np.array_equal(a.latent, cohort(12, 3, seed=5).latent)
    # A patient keeps its first latent values when more are asked for, or a pose is added.
    more = cohort(12, 5, seed=4, shift=0.01, tilt=0.1)
    assert np.array_equal(more.latent[:, :3], a.latent)
    assert [s.height for s in more.shapes] == [s.height for s in a.shapes]
    assert np.all(np.abs(a.latent) <= 3.0)


def test_latent_parameters_change_only_their_own_feature():
    features = {
        "elongation": lambda s: s.height / math.sqrt(s.width * s.depth),
        "aspect": lambda s: s.depth / s.width,
        "box volume": lambda s: s.height * s.width * s.depth,  # kept by both stretches
        "dome": lambda s: s.dome,
        "apex": lambda s: s.apex,
        "mediastinal": lambda s: s.mediastinal,
    }

    def changed(shapes: list[LungShape]) -> set[str]:
        values = {name: [feature(s) for s in shapes] for name, feature in features.items()}
        return {name for name, v in values.items() if not np.allclose(v, v[0], rtol=1e-12, atol=0)}

    for k in range(1, len(LATENT) + 1):
        shapes = cohort(8, k, seed=2).shapes
        assert changed(shapes) == set(tuple(LATENT)[:k])
        assert all(s.side == "right" and s.notch is None for s in shapes)


def test_elongation_keeps_the_volume():
    base = LungShape().volume()
    shapes = cohort(6, 1, seed=3).shapes
    heights = np.array([s.height for s in shapes])
    assert np.ptp(heights) > 0.01  # the amplitude is a centimetre or so per standard deviation
    # Not exactly: the dome is a sphere, which does not stretch with the body (measured: at most
    # 0.8 % over 200 patients, 0.6 % here at 2 standard deviations).
    assert [s.volume() for s in shapes] == pytest.approx([base] * len(shapes), rel=0.01)


def test_shapes_stay_valid_and_sizes_and_poses_vary_apart():
    wild = cohort(50, 5, seed=0, spread=10.0, side="left")  # fractions clipped into their ranges
    assert all(s.side == "left" for s in wild.shapes)
    assert max(s.apex for s in wild.shapes) < LungShape.RANGES["apex"][1]

    plain = cohort(4, 2, seed=7)
    scaled = cohort(4, 2, seed=7, size_spread=0.05)
    assert np.all(plain.scales == 1.0) and np.ptp(scaled.scales) > 0
    for s, t, scale in zip(plain.shapes, scaled.shapes, scaled.scales):
        assert t == replace(s, height=s.height * scale, width=s.width * scale, depth=s.depth * scale)

    posed = cohort(2, 2, seed=7, shift=0.01, tilt=0.1)
    assert np.allclose(posed.rotations @ posed.rotations.transpose(0, 2, 1), np.eye(3))
    poses = zip(posed.images(0.0025), posed.shapes, posed.offsets, posed.rotations)
    for image, shape, offset, rotation in poses:
        still = voxelise(shape, 0.0025)
        assert np.linalg.norm(centroid(image) - (rotation @ centroid(still) + offset)) < 1e-4  # measured 3e-5
