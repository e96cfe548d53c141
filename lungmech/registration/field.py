"""The image function I of the registration energy Ψ(ω) = ∫_ω I dx: negative inside the
segmentation, positive outside, so that Ψ is smallest when ω is the segmented shape.

Two choices, built from the binary mask:

- :func:`signed_distance` (the default): the Euclidean signed distance to the mask's surface in
  metres, Gaussian-smoothed. Far from the shape it grows linearly, so a badly placed mesh is
  still pulled in (the capture range is the whole image) and the pull is proportional to the
  gap. Gaussian smoothing leaves a linear function unchanged: it only rounds the kinks of the
  distance (medial axes, voxel staircases), which would otherwise make ∇I jump.
- :func:`binary`: the ±1 image (−1 inside), optionally blurred. Then Ψ(ω) − Ψ(S) is exactly the
  volume of the symmetric difference ω Δ S, a cheap consistency check; its gradient lives only
  in a band of the blur's width around the surface, so it captures only nearby shapes.

Values are sampled by trilinear interpolation at any physical points (the quadrature points of
the deformed mesh). Outside the image box the signed distance continues as the value at the
nearest box point plus the distance to the box (still positive, still pulling inwards); the
binary image continues as +1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from lungmech.errors import ParameterError
from lungmech.registration.image import Image

__all__ = ["ImageFunction", "binary", "signed_distance"]


@dataclass(frozen=True, eq=False)
class ImageFunction:
    """A scalar field on an image grid, sampled trilinearly with its gradient.

    Args:
        values: Samples at the voxel centres, shape (n0, n1, n2).
        affine: Voxel index -> metres (as :class:`Image`).
        distance_outside: Outside the box, add the distance to the box (a signed distance);
            otherwise continue with the constant +1 (a binary image).
    """

    values: np.ndarray
    affine: np.ndarray
    distance_outside: bool

    def __call__(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Values (n,) and physical gradients (n, 3) at physical points (n, 3)."""
        linear, shift = self.affine[:3, :3], self.affine[:3, 3]
        index = np.linalg.solve(linear, (np.asarray(points, dtype=float) - shift).T).T
        upper = np.array(self.values.shape) - 1.0
        clamped = np.clip(index, 0.0, upper)
        value, gradient_index = _trilinear(self.values, clamped)
        # Along a clamped axis the value no longer changes with the interior field.
        gradient_index[index != clamped] = 0.0
        # d/dx = A^-T d/d(index), for index = A^-1 (x - shift)
        gradient = np.linalg.solve(linear.T, gradient_index.T).T
        outside = np.any(index != clamped, axis=1)
        if np.any(outside):
            offset = (index[outside] - clamped[outside]) @ linear.T  # metres from the box
            if self.distance_outside:
                gap = np.linalg.norm(offset, axis=1)
                value[outside] += gap
                gradient[outside] += offset / gap[:, None]
            else:
                value[outside], gradient[outside] = 1.0, 0.0
        return value, gradient


def signed_distance(image: Image, smoothing: float = 1.0) -> ImageFunction:
    """The signed distance to the surface of ``image.mask`` (metres, < 0 inside), smoothed by a
    Gaussian of standard deviation ``smoothing`` voxels (0: none)."""
    _check_smoothing(smoothing)
    spacing = image.spacing
    # Distances between voxel centres. The surface lies about half a voxel short of the nearest
    # centre on the other side, half a voxel measured across the surface: with n the unit vector
    # towards that centre, ½ Σ_k h_k n_k², which is h_k / 2 for a face normal to axis k.
    outside, to_inside = ndimage.distance_transform_edt(~image.mask, sampling=spacing, return_indices=True)
    inside, to_outside = ndimage.distance_transform_edt(image.mask, sampling=spacing, return_indices=True)
    nearest = np.where(image.mask, to_outside, to_inside)
    offset = (nearest - np.indices(image.shape)) * spacing[:, None, None, None]  # metres, per axis
    length2 = np.sum(offset**2, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        half = np.where(length2 > 0, 0.5 * np.einsum("k,k...->...", spacing, offset**2) / length2, 0.0)
    values = np.where(image.mask, half - inside, outside - half)
    return ImageFunction(_smooth(values, smoothing), image.affine.copy(), distance_outside=True)


def binary(image: Image, smoothing: float = 0.0) -> ImageFunction:
    """The ±1 image (−1 inside the mask), blurred by a Gaussian of ``smoothing`` voxels."""
    _check_smoothing(smoothing)
    values = np.where(image.mask, -1.0, 1.0)
    return ImageFunction(_smooth(values, smoothing), image.affine.copy(), distance_outside=False)


def _smooth(values: np.ndarray, smoothing: float) -> np.ndarray:
    # Beyond the border the field continues with its edge values.
    return ndimage.gaussian_filter(values, smoothing, mode="nearest") if smoothing > 0 else values


def _check_smoothing(smoothing: float) -> None:
    if not (np.isfinite(smoothing) and smoothing >= 0):
        raise ParameterError(f"image smoothing must be a non-negative number of voxels, got {smoothing}")


def _trilinear(values: np.ndarray, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Trilinear interpolation at fractional indices inside the grid, and its index gradient."""
    shape = np.array(values.shape)
    base = np.minimum(np.floor(index).astype(np.int64), np.maximum(shape - 2, 0))
    t = index - base
    i, j, k = base.T
    # A grid one voxel thick along an axis has nothing to interpolate along it.
    di, dj, dk = (int(n > 1) for n in shape)
    c = {(a, b, e): values[i + a * di, j + b * dj, k + e * dk] for a in (0, 1) for b in (0, 1) for e in (0, 1)}
    tx, ty, tz = t.T
    # Interpolate along x, then y, then z; differentiate each stage for the gradient.
    c00 = c[0, 0, 0] + tx * (c[1, 0, 0] - c[0, 0, 0])
    c01 = c[0, 0, 1] + tx * (c[1, 0, 1] - c[0, 0, 1])
    c10 = c[0, 1, 0] + tx * (c[1, 1, 0] - c[0, 1, 0])
    c11 = c[0, 1, 1] + tx * (c[1, 1, 1] - c[0, 1, 1])
    c0 = c00 + ty * (c10 - c00)
    c1 = c01 + ty * (c11 - c01)
    value = c0 + tz * (c1 - c0)
    dx0 = (c[1, 0, 0] - c[0, 0, 0]) + ty * ((c[1, 1, 0] - c[0, 1, 0]) - (c[1, 0, 0] - c[0, 0, 0]))
    dx1 = (c[1, 0, 1] - c[0, 0, 1]) + ty * ((c[1, 1, 1] - c[0, 1, 1]) - (c[1, 0, 1] - c[0, 0, 1]))
    gradient = np.column_stack(
        [
            (dx0 + tz * (dx1 - dx0)) * di,
            ((c10 - c00) + tz * ((c11 - c01) - (c10 - c00))) * dj,
            (c1 - c0) * dk,
        ]
    )
    return value, gradient
