"""A right and a left lung of realistic shape, written here and not with lungmech's LungShape.

Independent targets for registration and for telling the side of a lung: each is an ellipsoidal
body narrowed towards its apex, its base carved by the diaphragm's dome, its medial face cut flat
by the mediastinal pleura, hollowed by the heart (a vertical cylinder) and pitted at the hilum; the left lung is narrower and
taller, with a deep cardiac impression and the cardiac notch cut from its anterior lower
margin. They are not mirror images. Coordinates are lungmech's: metres, x the patient's right,
y anterior, z superior.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lungmech.registration.image import Image, from_array


@dataclass(frozen=True)
class Lung:
    """One lung as an implicit solid: the body less its carvings."""

    side: str
    half_axes: tuple[float, float, float]  # body's a (x), b (y), c (z), m
    centre: tuple[float, float, float]  # body's centre, m
    dome: tuple[float, float]  # the diaphragm: radius, and how far it rises into the body (m)
    medial: float  # the mediastinal pleura, a plane x = medial (m): the body lies on its costal side
    mediastinum: tuple[float, float, float]  # vertical cylinder: x, y of its axis and radius (m)
    hilum: tuple[float, float, float, float]  # sphere: centre x, y, z and radius (m)
    notch: tuple[float, float, float, float] | None = None  # cardiac notch sphere: x, y, z, radius (m)

    def inside(self, x: np.ndarray) -> np.ndarray:
        """Whether each point (n × 3, m) lies in the lung."""
        (a, b, c), (cx, cy, cz) = self.half_axes, self.centre
        height = (x[:, 2] - cz) / c
        taper = 1.0 - 0.4 * np.clip(height, 0.0, None)  # the apex is narrower than an ellipsoid's
        body = ((x[:, 0] - cx) / (a * taper)) ** 2 + ((x[:, 1] - cy) / (b * taper)) ** 2 + height**2 <= 1.0
        radius, rise = self.dome
        base = np.array([cx, cy, cz - c + rise - radius])
        body &= np.sum((x - base) ** 2, axis=1) > radius**2
        body &= (x[:, 0] - self.medial) * (1.0 if self.side == "right" else -1.0) >= 0
        mx, my, mr = self.mediastinum
        body &= (x[:, 0] - mx) ** 2 + (x[:, 1] - my) ** 2 > mr**2
        for sphere in (self.hilum, self.notch):
            if sphere is not None:
                body &= np.sum((x - np.array(sphere[:3])) ** 2, axis=1) > sphere[3] ** 2
        return body

    def image(self, spacing: float, margin: float = 0.01) -> Image:
        """The lung voxelised at ``spacing`` (m) on an axis-aligned grid, in a margin."""
        (a, b, c), centre = self.half_axes, np.array(self.centre)
        lo, hi = centre - np.array([a, b, c]) - margin, centre + np.array([a, b, c]) + margin
        axes = [np.arange(lo[d], hi[d], spacing) for d in range(3)]
        mask = np.zeros([len(t) for t in axes], dtype=bool)
        for k, z in enumerate(axes[2]):
            x, y = np.meshgrid(axes[0], axes[1], indexing="ij")
            points = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, z)])
            mask[:, :, k] = self.inside(points).reshape(x.shape)
        return from_array(mask, spacing=(spacing,) * 3, origin=lo)


RIGHT = Lung(
    "right",
    half_axes=(0.07, 0.095, 0.12),
    centre=(0.075, 0.0, 0.0),
    dome=(0.11, 0.05),
    medial=0.025,
    mediastinum=(-0.02, 0.025, 0.05),
    hilum=(0.012, -0.005, 0.015, 0.018),
)
LEFT = Lung(
    "left",
    half_axes=(0.058, 0.085, 0.135),
    centre=(-0.07, -0.005, 0.005),
    dome=(0.1, 0.04),
    medial=-0.022,
    mediastinum=(0.025, 0.03, 0.06),
    hilum=(-0.014, -0.01, 0.025, 0.017),
    notch=(-0.02, 0.06, -0.06, 0.045),
)


def chest(spacing: float, margin: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Both lungs on one axis-aligned grid at ``spacing`` (m): a label array (0 outside, 1 the
    right lung, 2 the left) and its affine (voxel indices to metres)."""
    low = np.min([np.array(lung.centre) - lung.half_axes for lung in (RIGHT, LEFT)], axis=0) - margin
    high = np.max([np.array(lung.centre) + lung.half_axes for lung in (RIGHT, LEFT)], axis=0) + margin
    axes = [np.arange(low[d], high[d], spacing) for d in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    labels = np.zeros(len(grid), dtype=np.uint8)
    labels[RIGHT.inside(grid)] = 1
    labels[LEFT.inside(grid)] = 2
    affine = np.eye(4)
    affine[:3, :3] *= spacing
    affine[:3, 3] = low
    return labels.reshape([len(t) for t in axes]), affine
