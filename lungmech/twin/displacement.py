"""Interior motion as data: a displacement field computed elsewhere, from intensity images.

Between two segmentations the motion inside the lung is not in the images. A registration of
the two CT scans themselves (their intensities: vessels, airways) does see it, up to its own
smoothing: such a field, from end-expiration to end-inspiration, may be given as extra data
(:mod:`lungmech.registration.vectors`). Its values at interior points x_j of the lung as imaged
are compared with the model's motion there:

    r_j(μ) = ω (w_j(T; μ) − u_obs(x_j))          three rows a point (m),

∂r_j/∂μ = ω ∂w_j/∂μ from the model's sensitivities. A smoothed field's errors are correlated
over its smoothing length s, so the points are the mesh's interior vertices thinned to one per
s (:func:`interior_points`): about independent, as the Laplace intervals assume. The weight ω
is the surface data's noise over the field's (each from its own residual after a fit to the
surface alone), so that every row weighs as its noise says.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import dolfinx
import numpy as np

from lungmech.errors import ParameterError
from lungmech.registration.vectors import VectorImage
from lungmech.twin.surface import surface_nodes

__all__ = ["Displacement", "interior_points"]


@dataclass(frozen=True)
class Displacement:
    """A displacement field as data: its ``field`` (end-expiration → end-inspiration, m) and
    its ``smoothing``, the length over which whatever made it smoothed it (m)."""

    field: VectorImage
    smoothing: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.smoothing) and self.smoothing > 0):
            raise ParameterError(f"a displacement field's smoothing is a positive length in m (got {self.smoothing})")


def interior_points(mesh: dolfinx.mesh.Mesh, spacing: float) -> np.ndarray:
    """The vertices of ``mesh`` not on its boundary, thinned greedily (in the order of their
    coordinates) so that no two kept are closer than ``spacing`` (m); the same on every rank.
    Collective."""
    if not spacing > 0:
        raise ParameterError(f"the interior points' spacing must be a positive length in m (got {spacing})")
    x = mesh.geometry.x[:, : mesh.geometry.dim]
    gathered = np.concatenate(mesh.comm.allgather(np.round(x, 12)))
    every = np.unique(gathered, axis=0)  # sorted: the same on every rank
    boundary = {tuple(p) for p in np.round(surface_nodes(mesh).points, 12)}
    inside = np.array([p for p in every if tuple(p) not in boundary]).reshape(-1, 3)
    return np.array(list(_thinned(inside, spacing))).reshape(-1, 3)


def _thinned(points: np.ndarray, spacing: float) -> Iterator[np.ndarray]:
    """The points kept, in order, none within ``spacing`` of one kept before (a grid of cells
    of that size holds the kept ones: only the 27 around a point are looked at)."""
    kept: dict[tuple[int, ...], list[np.ndarray]] = {}
    offsets = [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)]
    for point in points:
        cell = tuple(np.floor(point / spacing).astype(int))
        near = (q for o in offsets for q in kept.get((cell[0] + o[0], cell[1] + o[1], cell[2] + o[2]), []))
        if all(np.linalg.norm(point - q) >= spacing for q in near):
            kept.setdefault(cell, []).append(point)
            yield point
