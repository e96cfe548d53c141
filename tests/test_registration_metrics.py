"""Fit metrics of a mesh against a segmented image: Dice, surface distances, the report."""

import json

from mpi4py import MPI

import numpy as np
import pytest

from lungmech.errors import RegistrationError
from lungmech.mesh import box, sphere
from lungmech.registration.image import Image, from_array
from lungmech.registration.metrics import dice, report, surface_distances, voxelise

H = 0.001  # isotropic voxel spacing (m)


def voxel_box(first, last, shape, spacing=(H, H, H), direction=None) -> Image:
    """Voxels first..last-1 set, on a grid whose voxel faces lie at multiples of the spacing."""
    mask = np.zeros(shape, dtype=bool)
    mask[tuple(slice(a, b) for a, b in zip(first, last))] = True
    rotation = np.eye(3) if direction is None else direction
    origin = rotation @ (0.5 * np.asarray(spacing))  # the centre of voxel 0
    return from_array(mask, spacing, origin, direction)


def mesh_box(first, last, spacing=(H, H, H)):
    """A tetrahedral box covering exactly the voxels first..last-1 of :func:`voxel_box`."""
    lower, upper = np.multiply(first, spacing), np.multiply(last, spacing)
    return box(MPI.COMM_WORLD, tuple(upper - lower), (5, 5, 5), tuple(lower)).mesh


def voxel_ball(radius: float, n: int) -> Image:
    """Voxels (of side H) whose centres are within ``radius`` voxels of the origin, n^3 of them."""
    centres = np.indices((n, n, n)) - (n - 1) / 2
    return from_array(np.linalg.norm(centres, axis=0) < radius, (H, H, H), (-(n - 1) / 2 * H,) * 3)


def test_box_on_voxel_faces_matches_its_voxels():
    spacing = (0.001, 0.0015, 0.002)
    first, last = (3, 4, 2), (13, 11, 9)
    image, mesh = voxel_box(first, last, (16, 15, 12), spacing), mesh_box(first, last, spacing)
    assert np.array_equal(voxelise(mesh, image), image.mask)
    result = report(mesh, image)
    assert result["dice"] == 1.0
    assert result["volume_mesh"] == pytest.approx(result["volume_image"], rel=1e-12)
    # What is left is point sampling: mesh samples vs surfel centres, at most half a face diagonal.
    assert result["mean_surface_distance"] < 0.25 * max(spacing)
    assert result["hausdorff"] <= 0.5 * np.hypot(0.0015, 0.002)


@pytest.fixture(scope="module")
def ball():
    """A linear tetrahedral ball of radius 14 voxels (~10k cells)."""
    return sphere(MPI.COMM_WORLD, 0.0, 14 * H, mesh_size=1.75 * H, octant=False).mesh


@pytest.mark.parametrize("R", [11.0, 17.0])
def test_ball_against_a_voxel_ball_of_another_radius(ball, R):
    r = 14.0
    result = report(ball, voxel_ball(R, n=2 * int(R) + 6))
    assert result["mean_surface_distance_voxels"] == pytest.approx(abs(R - r), abs=0.3)
    assert result["dice"] == pytest.approx(2 * min(r, R) ** 3 / (r**3 + R**3), rel=0.01)
    assert result["volume_mesh"] == pytest.approx(4 / 3 * np.pi * (r * H) ** 3, rel=0.01)


@pytest.mark.parametrize("axis", [0, 2])
def test_translated_box_is_as_far_as_the_translation(axis):
    first, last = (5, 5, 5), (15, 15, 15)
    image, mesh = voxel_box(first, last, (24, 24, 24)), mesh_box(first, last)
    assert report(mesh, image)["dice"] == 1.0  # before the move: the metrics must not keep stale state
    shift = np.zeros(3)
    shift[axis] = 3 * H
    mesh.geometry.x[:] += shift
    result = report(mesh, image)
    assert result["dice"] == pytest.approx(0.7, abs=1e-12)  # 7 of 10 layers overlap
    assert result["hd95"] == pytest.approx(3 * H, abs=0.15 * H)
    assert result["hausdorff"] == pytest.approx(3 * H, abs=0.15 * H)
    assert surface_distances(mesh, image) == {
        "mean": result["mean_surface_distance"],
        "hd95": result["hd95"],
        "max": result["hausdorff"],
    }


def test_oblique_image_and_mesh_turned_together_give_the_same_report():
    first, last, shape = (3, 4, 2), (12, 10, 9), (15, 14, 12)
    straight = report(mesh_box(first, last), voxel_box(first, last, shape))
    axis = np.array([1.0, 2.0, 2.0]) / 3.0  # a rotation by 0.5 rad about it (Rodrigues)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + np.sin(0.5) * cross + (1 - np.cos(0.5)) * cross @ cross
    mesh = mesh_box(first, last)
    mesh.geometry.x[:] = mesh.geometry.x @ rotation.T
    turned = report(mesh, voxel_box(first, last, shape, direction=rotation))
    assert turned["dice"] == 1.0
    assert turned == pytest.approx(straight, rel=1e-9)


def test_report_is_json_and_reuses_a_given_voxelisation():
    first, last = (2, 2, 2), (8, 9, 10)
    image, mesh = voxel_box(first, last, (12, 12, 12)), mesh_box(first, last)
    mesh.geometry.x[:, 1] += 0.4 * H
    result = report(mesh, image)
    assert set(result) == {
        "dice", "mean_surface_distance", "mean_surface_distance_voxels", "hd95", "hausdorff",
        "volume_mesh", "volume_image", "spacing",
    }  # fmt: skip
    assert all(type(value) is float for value in result.values())
    assert json.loads(json.dumps(result)) == result
    assert result["spacing"] == H
    assert report(mesh, image, dice_mask=voxelise(mesh, image)) == result
    with pytest.raises(RegistrationError, match="same shape"):
        report(mesh, image, dice_mask=np.ones((3, 3, 3), dtype=bool))


def test_dice():
    a = np.zeros((4, 4, 4), dtype=bool)
    b = a.copy()
    a[:2], b[1:3] = True, True
    assert dice(a, a) == 1.0
    assert dice(a, b) == 0.5
    assert dice(a, ~a) == 0.0
    assert dice(a, np.zeros_like(a)) == 0.0
    with pytest.raises(RegistrationError, match="empty"):
        dice(np.zeros_like(a), np.zeros_like(a))
    with pytest.raises(RegistrationError, match="same shape"):
        dice(a, a[:3])


def test_only_linear_tetrahedra():
    hexahedra = box(MPI.COMM_WORLD, (H, H, H), (1, 1, 1), cell_type="hexahedron").mesh
    with pytest.raises(RegistrationError, match="tetrahedral"):
        report(hexahedra, voxel_ball(2.0, 6))


@pytest.mark.mpi
def test_same_report_on_all_ranks_as_on_one():
    def bent_block(comm):
        mesh = box(comm, (0.024, 0.02, 0.016), (10, 8, 6), (-0.012, -0.01, -0.008)).mesh
        x = mesh.geometry.x
        x[:] += 0.002 * np.sin(x[:, ::-1] / 0.007)  # pointwise, so the same on any partition
        return mesh

    image = voxel_ball(11.5, 30)
    parallel, serial = bent_block(MPI.COMM_WORLD), bent_block(MPI.COMM_SELF)
    assert np.array_equal(voxelise(parallel, image), voxelise(serial, image))
    result = report(parallel, image)
    assert result == report(serial, image)
    assert MPI.COMM_WORLD.allgather(result) == [result] * MPI.COMM_WORLD.size
    assert 0.5 < result["dice"] < 1.0
