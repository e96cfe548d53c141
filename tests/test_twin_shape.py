"""A patient's shape coefficients and pose from a segmentation's surface (lungmech.twin.shape):
an ellipsoid made by known coefficients of two stretch modes of a sphere, turned and moved,
voxelised at 2 mm, is found again from a start at the sphere (independent: the target is a
formula, the data its voxels)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lungmech.errors import ParameterError
from lungmech.registration.image import from_array
from lungmech.twin.shape import fit_shape
from lungmech.twin.surface import surface_data

RADIUS = 0.1  # m


def sphere_nodes(count=800):
    """Nearly even points on the sphere (a Fibonacci lattice) and equal areas."""
    k = np.arange(count) + 0.5
    polar, azimuth = np.arccos(1 - 2 * k / count), np.pi * (1 + 5**0.5) * k
    points = RADIUS * np.column_stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)])
    return points, np.full(count, 4 * np.pi * RADIUS**2 / count)


def test_an_ellipsoid_is_found_by_its_stretches_and_pose():
    points, areas = sphere_nodes()
    modes = np.array(
        [
            np.column_stack([points[:, 0], 0 * points[:, 1], 0 * points[:, 2]]),
            np.column_stack([0 * points[:, 0], 0 * points[:, 1], points[:, 2]]),
        ]
    )  # x and z stretches
    a = np.array([0.25, -0.15])
    R = Rotation.from_rotvec([0.0, 0.05, 0.08]).as_matrix()
    t = np.array([0.012, -0.006, 0.02])
    step = 0.002
    axes = [np.arange(-0.16, 0.16, step)] * 3
    x, y, z = np.meshgrid(*axes, indexing="ij")
    body = (np.stack([x, y, z], axis=-1) - t) @ R  # the scanner's points in the body's frame
    semi = RADIUS * np.array([1 + a[0], 1.0, 1 + a[1]])
    mask = np.sum((body / semi) ** 2, axis=-1) <= 1.0
    data = surface_data(from_array(mask, (step,) * 3, (axes[0][0],) * 3))
    found = fit_shape(points, areas, modes, data, np.zeros(2), (np.full(2, -0.5), np.full(2, 0.5)))
    assert found.coefficients == pytest.approx(a, abs=0.02)  # 2 mm of 100: a voxel
    assert np.abs(found.rotation - R).max() < 0.03 and np.abs(found.translation - t).max() < 0.002
    assert found.rms < 0.5 * step and found.largest < 2 * step
    bounded = fit_shape(points, areas, modes, data, np.zeros(2), (np.full(2, -0.1), np.full(2, 0.1)))
    assert bounded.coefficients == pytest.approx([0.1, -0.1])  # held at the box: what the report flags
    with pytest.raises(ParameterError, match="the modes at the nodes must be"):
        fit_shape(points, areas, modes[:, :10], data, np.zeros(2), (np.full(2, -0.5), np.full(2, 0.5)))
