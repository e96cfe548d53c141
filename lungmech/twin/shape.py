"""A patient's shape on a population's modes, from the segmentation's surface.

A population's template moves with the shape coefficients a: its surface nodes x̂_i go to
χ_a(x̂_i) = x̂_i + Σ_k a_k m_k(x̂_i) (:mod:`lungmech.fem.shape`). A patient's end-expiration
segmentation locates its lung's surface, in the scanner's frame; so the patient's coefficients
and pose are those that put the template's surface on it:

    min over a, θ, t of  Σ_i A_i d(R(θ) χ_a(x̂_i) + t)²,   a inside the model's box,

d the signed distance to the segmentation's surface, A_i the nodes' lumped areas, R(θ) the
rotation of vector θ. The mapping's projection on the modes (a registration's, which also
places the interior nodes, and slides them along the surface as its regulariser says) is where
the fit starts; the fit judges the surface alone, the only part of the shape the image holds.
Bounded least squares ('trf', SciPy) with the Jacobian ∂r_i/∂a_k = ∇d · R m_k(x̂_i),
∂r_i/∂t = ∇d, ∂r_i/∂θ = (R χ_a(x̂_i)) × ∇d (a small turn δθ moves y by δθ × y: exact at θ = 0,
to first order in θ elsewhere; the turns are small).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from lungmech.errors import ParameterError
from lungmech.twin.surface import Surface

__all__ = ["ShapeFit", "fit_shape"]


@dataclass(frozen=True)
class ShapeFit:
    """The patient's ``coefficients`` a, its pose x ↦ ``rotation`` x + ``translation`` (the
    template's frame into the scanner's), and the surface's distance left, ``rms``
    (area-weighted) and ``largest`` (m)."""

    coefficients: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    rms: float
    largest: float


def fit_shape(
    points: np.ndarray,
    areas: np.ndarray,
    modes: np.ndarray,
    data: Surface,
    start: np.ndarray,
    bounds: tuple[np.ndarray, np.ndarray],
    rotation: np.ndarray | None = None,
    translation: np.ndarray | None = None,
) -> ShapeFit:
    """The coefficients and pose that put the template's surface nodes ``points`` (n, 3; m,
    lumped ``areas`` n) on the segmentation ``data``: ``modes`` (k, n, 3) the shape modes at
    the nodes (m per unit coefficient), from ``start`` (k) and the pose ``rotation``,
    ``translation`` (default: none), a within ``bounds`` (low, high)."""
    points, modes = np.asarray(points, dtype=float), np.asarray(modes, dtype=float)
    count = len(modes)
    if modes.shape[1:] != points.shape:
        raise ParameterError(f"the modes at the nodes must be ({count}, {len(points)}, 3), got {modes.shape}")
    low, high = (np.asarray(b, dtype=float) for b in bounds)
    a0 = np.clip(np.asarray(start, dtype=float), low, high)
    R0 = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
    t0 = np.zeros(3) if translation is None else np.asarray(translation, dtype=float)
    weights = np.sqrt(np.asarray(areas, dtype=float) / np.sum(areas))

    def unpacked(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a, theta, t = z[:count], z[count : count + 3], z[count + 3 :]
        return a, Rotation.from_rotvec(theta).as_matrix() @ R0, t0 + t

    def placed(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        a, R, t = unpacked(z)
        y = (points + np.einsum("k,knd->nd", a, modes)) @ R.T
        distance, gradient = data.distance(y + t)
        return distance, gradient, y, R

    def residual(z: np.ndarray) -> np.ndarray:
        return weights * placed(z)[0]

    def jacobian(z: np.ndarray) -> np.ndarray:
        _, gradient, y, R = placed(z)
        along_modes = np.einsum("nd,knd->nk", gradient, modes @ R.T)
        turning = np.cross(y, gradient)
        return weights[:, None] * np.hstack([along_modes, turning, gradient])

    z0 = np.concatenate([a0, np.zeros(6)])
    infinite = np.full(6, np.inf)
    found = least_squares(
        residual,
        z0,
        jac=jacobian,
        bounds=(np.concatenate([low, -infinite]), np.concatenate([high, infinite])),
        method="trf",
        x_scale="jac",
    )
    a, R, t = unpacked(found.x)
    distance = placed(found.x)[0]
    rms = float(np.sqrt(np.sum(weights**2 * distance**2)))
    return ShapeFit(a, R, t, rms, float(np.abs(distance).max(initial=0.0)))
