"""The analytic lung shape behind :func:`lungmech.mesh.lung_phantom`.

A :class:`LungShape` holds a handful of anatomical parameters and derives from them the
primitives the lung is carved from: an egg-like body (two half-ellipsoids sharing an equator),
the mediastinal plane x = 0, a sphere carving the diaphragmatic dome, a sphere carving the
cardiac notch, and the hilum ellipse on the medial face. The gmsh builder and the analytic
:meth:`LungShape.inside` test read the same numbers, so a mesh, a voxel image and the exact
solid of one shape agree (up to their discretisation errors).

Axes as for the phantom: metres, x towards the patient's right, y anterior, z superior; the
right lung lies at x > 0, the left at x < 0, and z = 0 is near the base.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from fractions import Fraction
from types import MappingProxyType
from typing import ClassVar

import numpy as np
import numpy.typing as npt

from lungmech.errors import GeometryError

__all__ = ["LungShape"]


@dataclass(frozen=True)
class LungShape:
    """A generic lung, described by its size and four shape fractions.

    Args:
        height, width, depth: Extent along z, x and y, in metres.
        side: ``"right"`` (x > 0) or ``"left"`` (x < 0, the mirror image).
        apex: Height of the body's equator as a fraction of ``height``. Below it the body is a
            half-ellipsoid of semi-axis ``height / 2``, above it a taller one reaching the apex:
            lower values give a longer, more tapered upper lobe.
        dome: Height of the diaphragmatic dome's peak as a fraction of ``height``.
        mediastinal: Fraction of the body's x-extent cut off by the mediastinal plane x = 0;
            more cut off gives a broader, flatter medial face.
        notch: Radius of the cardiac notch as a fraction of ``width``, 0 for none; ``None``
            means the anatomical default, a notch (0.45) in the left lung only.
    """

    height: float = 0.24
    width: float = 0.11
    depth: float = 0.17
    side: str = "right"
    apex: float = 0.3
    dome: float = 0.2
    mediastinal: float = 1 / 3
    notch: float | None = None

    # Open ranges of the fractions (the notch's is half-open, 0 meaning none). Inside them the
    # default lung with any one fraction changed is one solid with the hilum on its medial face,
    # and gmsh meshes it; beyond them it breaks: apex 0.12 and dome 0.38 leave the solid in
    # pieces, mediastinal 0.1 leaves too small a medial face for the hilum.
    RANGES: ClassVar[Mapping[str, tuple[float, float]]] = MappingProxyType(
        {"apex": (0.15, 0.5), "dome": (0.0, 0.35), "mediastinal": (0.15, 0.5), "notch": (0.0, 0.6)}
    )

    def __post_init__(self) -> None:
        if self.side not in ("right", "left"):
            raise GeometryError(f"side must be 'right' or 'left', got {self.side!r}")
        H, W, D = self.height, self.width, self.depth
        if not all(math.isfinite(n) and n > 0 for n in (H, W, D)):
            raise GeometryError(f"lung dimensions must be positive, got height={H}, width={W}, depth={D}")
        for name in ("apex", "dome", "mediastinal"):
            lo, hi = self.RANGES[name]
            if not lo < (value := getattr(self, name)) < hi:
                raise GeometryError(f"{name} must lie strictly between {lo} and {hi}, got {value}")
        lo, hi = self.RANGES["notch"]
        if self.notch is not None and not lo <= self.notch < hi:
            raise GeometryError(f"notch must be None or between {lo} and {hi} (0: none), got {self.notch}")

    # --- Derived primitives (the formulas of the original lung_phantom, operation for operation,
    # so that the default shape is the very same double-precision geometry) ---------------------

    @property
    def sign(self) -> float:
        """+1 for the right lung, -1 for the left one (its mirror image in x = 0)."""
        return 1.0 if self.side == "right" else -1.0

    @property
    def body_centre(self) -> npt.NDArray[np.float64]:
        """Centre of the body's equator; its outer side reaches x = +-width."""
        return np.array([self.sign * (self.width - self._a), 0.0, self.apex * self.height])

    @property
    def upper_axes(self) -> npt.NDArray[np.float64]:
        """Semi-axes of the half-ellipsoid above the equator (reaching the apex at z = height)."""
        return np.array([self._a, self._b, self.height - self.body_centre[2]])

    @property
    def lower_axes(self) -> npt.NDArray[np.float64]:
        """Semi-axes of the half-ellipsoid below the equator."""
        return np.array([self._a, self._b, 0.5 * self.height])

    @property
    def dome_radius(self) -> float:
        """Radius of the sphere carving the diaphragm. It peaks at ``dome * height`` and crosses
        z = 0 at 80 % of the body's smaller horizontal semi-axis from the body's axis: for the
        default apex, where the body's floor crosses z = 0 too (the costophrenic recess)."""
        rim, peak = 0.8 * min(self._a, self._b), self.dome * self.height
        return (rim**2 + peak**2) / (2 * peak)

    @property
    def dome_centre(self) -> npt.NDArray[np.float64]:
        """Centre of the diaphragm sphere, below the body's axis."""
        return np.array([self.body_centre[0], 0.0, self.dome * self.height - self.dome_radius])

    @property
    def notch_radius(self) -> float:
        """Radius of the cardiac notch sphere; 0 when there is none."""
        notch = self.notch if self.notch is not None else (0.45 if self.side == "left" else 0.0)
        return notch * self.width

    @property
    def notch_centre(self) -> npt.NDArray[np.float64]:
        """Centre of the cardiac notch sphere, just across the medial plane, anterior, low."""
        s, W, D, H = self.sign, self.width, self.depth, self.height
        return np.array([-s * 0.05 * W, 0.32 * D, 0.35 * H])

    @property
    def hilum_centre(self) -> npt.NDArray[np.float64]:
        """Centre of the hilum ellipse on the medial plane, at 60 % of the height."""
        return np.array([0.0, -0.05 * self.depth, 0.6 * self.height])

    @property
    def hilum_radii(self) -> npt.NDArray[np.float64]:
        """Semi-axes of the hilum ellipse along z and y."""
        return np.array([0.08 * self.height, 0.09 * self.depth])

    @property
    def _a(self) -> float:
        # Exact arithmetic: for mediastinal = 1/3 this gives exactly 0.75 width, as the original
        # phantom had (in floating point, 1 / (2 (1 - 1/3)) = 0.7499999999999999).
        return float(Fraction(1, 2) / (1 - Fraction(self.mediastinal))) * self.width

    @property
    def _b(self) -> float:
        return 0.5 * self.depth

    # --- The solid ----------------------------------------------------------------------------

    def bounds(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Lower and upper corners of a box around the solid: the box of the body on the lung's
        side of x = 0 (it is loose below, where the dome carves the body's floor away)."""
        lo = np.array([0.0, -self._b, self.body_centre[2] - self.lower_axes[2]])
        hi = np.array([self.width, self._b, self.height])
        if self.side == "left":
            lo[0], hi[0] = -hi[0], -lo[0]
        return lo, hi

    def inside(self, points: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """Which of the points, shape (n, 3), lie in the solid (its surface counts as inside)."""
        x = np.asarray(points, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != 3:
            raise GeometryError(f"points must have shape (n, 3), got {x.shape}")
        d = x - self.body_centre
        c = np.where(d[:, 2] >= 0, self.upper_axes[2], self.lower_axes[2])
        body = (d[:, 0] / self._a) ** 2 + (d[:, 1] / self._b) ** 2 + (d[:, 2] / c) ** 2 <= 1.0
        solid = body & (self.sign * x[:, 0] >= 0) & _outside(x, self.dome_centre, self.dome_radius)
        if self.notch_radius > 0:
            solid &= _outside(x, self.notch_centre, self.notch_radius)
        return solid

    def volume(self) -> float:
        """Volume of the solid in cubic metres (relative error ~1e-6; computed once per shape)."""
        return _volume(self)

    def _chord(self, x: npt.NDArray[np.float64], z: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """Length of the solid's section along the lines through (x, ., z) parallel to y.

        Every primitive cuts such a line in one interval: the body and the dome in intervals
        centred on y = 0, the notch in one centred on its own y. So the length is exact, and a
        volume integral only has to integrate over x and z. ``x`` and ``z`` broadcast.
        """
        centre = self.body_centre
        dz = z - centre[2]
        c = np.where(dz >= 0, self.upper_axes[2], self.lower_axes[2])
        body = self._b * np.sqrt(np.clip(1.0 - ((x - centre[0]) / self._a) ** 2 - (dz / c) ** 2, 0.0, None))
        body = np.where(self.sign * x >= 0, body, 0.0)
        dome = np.minimum(_half_chord(x, z, self.dome_centre, self.dome_radius), body)
        length = 2.0 * (body - dome)  # the body's interval less the dome's: two pieces
        if self.notch_radius > 0:
            notch = _half_chord(x, z, self.notch_centre, self.notch_radius)
            lo, hi = self.notch_centre[1] - notch, self.notch_centre[1] + notch
            for a, b in ((-body, -dome), (dome, body)):
                length -= np.clip(np.minimum(b, hi) - np.maximum(a, lo), 0.0, None)
        return length


def _half_chord(x: npt.ArrayLike, z: npt.ArrayLike, centre: np.ndarray, radius: float) -> np.ndarray:
    """Half the length of a sphere's chord along y through (x, ., z); 0 where the line misses it."""
    return np.sqrt(np.clip(radius**2 - (x - centre[0]) ** 2 - (z - centre[2]) ** 2, 0.0, None))


def _outside(x: npt.NDArray[np.float64], centre: npt.NDArray[np.float64], radius: float) -> np.ndarray:
    return np.sum((x - centre) ** 2, axis=1) >= radius**2


@functools.lru_cache(maxsize=4096)  # cohorts make many shapes; each costs ~0.1 s
def _volume(shape: LungShape, n: int = 1024) -> float:
    """Volume as the midpoint rule on an n x n grid in (x, z) of the exact chord length along y.

    The cell edges fall on the medial plane, where the chord jumps; elsewhere it is continuous,
    and only the square-root edges where primitives meet limit the accuracy (error ~ n^-1.5).
    Against adaptive quadrature to 1e-10, n = 1024 is off by 7e-7 (right and left lungs).
    """
    lo, hi = shape.bounds()
    (x0, z0), (x1, z1) = lo[[0, 2]], hi[[0, 2]]
    hx, hz = (x1 - x0) / n, (z1 - z0) / n
    x = x0 + hx * (np.arange(n) + 0.5)
    z = z0 + hz * (np.arange(n) + 0.5)
    total = sum(float(shape._chord(x, rows[:, None]).sum()) for rows in np.array_split(z, 16))
    return total * hx * hz
