"""Synthetic lung images with exact ground truth, for testing shape registration.

:func:`voxelise` samples a :class:`~lungmech.mesh.lung_shape.LungShape` (optionally moved rigidly) on a
CT-like voxel grid, and :func:`cohort` makes a population of lungs whose shapes differ along a
few named latent parameters, so that a registration or shape-mode pipeline can be checked
against the answer it should find. The latent parameters are genuine shape changes, never
similarity transforms (translation, rotation, isotropic scale), which such pipelines remove;
size and pose can vary on top of them, separately.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from types import MappingProxyType

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from lungmech.errors import ParameterError
from lungmech.mesh.lung_shape import LungShape
from lungmech.registration.image import Image, from_array

__all__ = ["LATENT", "Cohort", "cohort", "voxelise"]

_SLAB_POINTS = 1 << 20  # voxel centres tested at once: ~100 MB of temporaries at most


MAX_VOXELS = 1e9  # a synthetic image larger than this is a mistake in the spacing (1 GB as bytes)


def voxelise(
    shape: LungShape,
    spacing: float | Sequence[float] = 0.002,
    margin: float = 0.015,
    offset: npt.ArrayLike = (0.0, 0.0, 0.0),
    rotation: npt.ArrayLike | None = None,
) -> Image:
    """A binary image of ``shape``, moved by ``x -> rotation @ x + offset``.

    A voxel is set when its centre lies in the (moved) solid. The grid is axis-aligned, with
    ``spacing`` in metres (one value or one per axis; CT is 1 to 2.5 mm), and covers the set
    voxels plus ``margin`` on every side, so the mask never touches the image's border.
    """
    step = np.asarray(spacing, dtype=np.float64)
    step = np.full(3, step) if step.ndim == 0 else step
    if step.shape != (3,) or not (np.isfinite(step).all() and (step > 0).all()):
        raise ParameterError(f"spacing must be positive lengths in metres, got {spacing}")
    if not (math.isfinite(margin) and margin > 0):
        raise ParameterError(f"margin must be a positive length in metres, got {margin}")
    R, t = _rigid(rotation, offset)

    # A grid over the moved corners of the shape's box, plus the margin and a voxel. That box is
    # loose (the dome carves the body's floor away, a rotated box is bigger): the result is
    # cropped below. Voxel centres sit at (i + 1/2) spacing: unmoved, the flat medial face x = 0
    # then falls on voxel faces, not through a layer of centres (half a layer too much volume).
    lo, hi = shape.bounds()
    corners = np.array(list(itertools.product(*zip(lo, hi)))) @ R.T + t
    first = np.floor((corners.min(axis=0) - margin) / step) - 1
    n = (np.ceil((corners.max(axis=0) + margin) / step) + 1 - first).astype(int)
    if np.prod(n.astype(float)) > MAX_VOXELS:
        raise ParameterError(
            f"a grid of {n[0]} x {n[1]} x {n[2]} voxels at spacing {np.round(1e3 * step, 6).tolist()} mm "
            f"is more than {MAX_VOXELS:.0e} voxels; use a coarser spacing"
        )
    origin = (first + 0.5) * step
    # Voxel centres in the shape's own frame, x = R^T (p - t) = sum over axes d of (p_d - t_d) R[d],
    # one term per grid axis, so that they add up by broadcasting.
    terms = [(origin[d] + step[d] * np.arange(n[d]) - t[d])[:, None] * R[d] for d in range(3)]
    mask = np.zeros(n, dtype=bool)
    slab = max(1, _SLAB_POINTS // (n[0] * n[1]))  # whole k-slices at a time bound the memory
    for k in range(0, n[2], slab):
        x = terms[0][:, None, None] + terms[1][None, :, None] + terms[2][None, None, k : k + slab]
        mask[:, :, k : k + slab] = shape.inside(x.reshape(-1, 3)).reshape(x.shape[:3])

    if not mask.any():
        raise ParameterError(f"the shape falls between the voxel centres at spacing {spacing}")
    # Crop to the set voxels plus the margin (whole voxels, rounded up; the grid has room for it).
    pad = np.ceil(margin / step).astype(int)
    ends = [np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != d)))[[0, -1]] for d in range(3)]
    start = [max(e[0] - p, 0) for e, p in zip(ends, pad)]
    stop = [min(e[1] + p + 1, m) for e, p, m in zip(ends, pad, n)]
    mask = mask[tuple(slice(a, b) for a, b in zip(start, stop))]
    return from_array(mask, step, origin + step * np.array(start))


def _rigid(rotation: npt.ArrayLike | None, offset: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
    t = np.asarray(offset, dtype=np.float64)
    if t.shape != (3,) or not np.isfinite(t).all():
        raise ParameterError(f"offset must be a finite 3-D vector in metres, got {t.tolist()}")
    if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
        raise ParameterError(f"rotation must be a 3x3 rotation matrix (orthogonal, det +1), got\n{R}")
    return R, t


# --- Cohorts ------------------------------------------------------------------------------


def _fraction(name: str) -> Callable[[LungShape, float], LungShape]:
    """Move a shape fraction by t, kept inside its valid range (a margin of 5 % of the range)."""
    lo, hi = LungShape.RANGES[name]
    lo, hi = lo + 0.05 * (hi - lo), hi - 0.05 * (hi - lo)
    # replace's stub cannot see that ``name`` is one of the shape's fields (RANGES' keys are)
    return lambda shape, t: replace(shape, **{name: float(np.clip(getattr(shape, name) + t, lo, hi))})  # type: ignore[arg-type]


def _stretch(height: float, width: float, depth: float) -> Callable[[LungShape, float], LungShape]:
    """Scale height, width and depth by exp(t times the given powers)."""
    return lambda shape, t: replace(
        shape,
        height=shape.height * math.exp(height * t),
        width=shape.width * math.exp(width * t),
        depth=shape.depth * math.exp(depth * t),
    )


# The latent parameters, in order: what each does to a shape, and by how much per unit of the
# latent (at spread = 1). Volume-preserving stretches and shape fractions are not similarity
# transforms. Amplitudes for the default lung: elongation +12 mm height (-3 mm width, -4 mm
# depth), dome peak +7 mm, apex (equator) +10 mm, aspect +9 mm depth (-5 mm width),
# mediastinal +5 mm in the body's x semi-axis (a broader medial face).
LATENT: Mapping[str, tuple[float, Callable[[LungShape, float], LungShape]]] = MappingProxyType(
    {
        "elongation": (0.05, _stretch(1.0, -0.5, -0.5)),  # height up, width and depth down, H W D fixed
        "dome": (0.03, _fraction("dome")),  # diaphragm dome height, fraction of the height
        "apex": (0.04, _fraction("apex")),  # equator height: the apex taper
        "aspect": (0.1, _stretch(0.0, -0.5, 0.5)),  # depth / width ratio, W D fixed
        "mediastinal": (0.04, _fraction("mediastinal")),  # mediastinal flattening
    }
)
_TRUNCATE = 3.0  # latent draws are cut at +-3 standard deviations: no freak shapes


@dataclass(frozen=True, eq=False)  # eq=False: arrays have no single truth value
class Cohort:
    """Synthetic patients and the ground truth that made them.

    Attributes:
        shapes: One lung per patient, in its own (unmoved) frame.
        latent: (N, k) latent values (standard normal, truncated at +-3); parameter
            ``names[j]`` of patient i was moved by ``spread * amplitude * latent[i, j]``
            (shape fractions then clipped into their valid range, which only large spreads need).
        names: The k latent parameters' names, keys of :data:`LATENT`.
        scales: (N,) overall size factors (all 1 without ``size_spread``), applied after the shape.
        offsets, rotations: (N, 3) and (N, 3, 3) rigid poses: patient i's lung in its image is
            ``rotations[i] @ x + offsets[i]`` (zero and identity without ``shift`` and ``tilt``).
    """

    shapes: list[LungShape]
    latent: npt.NDArray[np.float64]
    names: tuple[str, ...]
    scales: npt.NDArray[np.float64]
    offsets: npt.NDArray[np.float64]
    rotations: npt.NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.shapes)

    def images(self, spacing: float | Sequence[float] = 0.002, margin: float = 0.015) -> list[Image]:
        """Every patient's lung voxelised in its pose (see :func:`voxelise`)."""
        poses = zip(self.shapes, self.offsets, self.rotations)
        return [voxelise(shape, spacing, margin, offset, rotation) for shape, offset, rotation in poses]


def cohort(
    size: int,
    latent: int = 2,
    *,
    seed: int = 0,
    spread: float = 1.0,
    side: str | None = None,
    base: LungShape | None = None,
    size_spread: float = 0.0,
    shift: float = 0.0,
    tilt: float = 0.0,
) -> Cohort:
    """``size`` synthetic lungs driven by the first ``latent`` parameters of :data:`LATENT`.

    Args:
        size: Number of patients N.
        latent: Number k of latent parameters, 1 to 5: elongation, dome, apex, aspect,
            mediastinal, in that order.
        seed: Seed of ``numpy.random.default_rng``. The draws do not depend on k or on the
            other spreads, so a patient keeps its elongation when k or ``tilt`` change.
        spread: Multiplies every latent parameter's amplitude. Shape fractions stay within
            their valid ranges whatever the spread (they are clipped).
        side: ``"right"`` or ``"left"``; by default the base's side, else right.
        base: The mean shape; by default the generic lung of that side.
        size_spread: Standard deviation of the log of an overall scale factor (e.g. 0.05).
        shift: Standard deviation of each component of the translation, in metres.
        tilt: Standard deviation of each component of the rotation vector, in radians.
    """
    if not (isinstance(size, int | np.integer) and size >= 1):
        raise ParameterError(f"cohort size must be a positive integer, got {size!r}")
    if not (isinstance(latent, int | np.integer) and 1 <= latent <= len(LATENT)):
        raise ParameterError(f"latent must be an integer from 1 to {len(LATENT)}, got {latent!r}")
    spreads = {"spread": spread, "size_spread": size_spread, "shift": shift, "tilt": tilt}
    if bad := [f"{k}={v}" for k, v in spreads.items() if not (math.isfinite(v) and v >= 0)]:
        raise ParameterError(f"spreads must be non-negative, got {', '.join(bad)}")
    if base is None:
        base = LungShape(side=side or "right")
    elif side is not None and side != base.side:
        raise ParameterError(f"side={side!r} but the base shape is a {base.side} lung")

    rng = np.random.default_rng(seed)
    z = np.clip(rng.standard_normal((size, len(LATENT))), -_TRUNCATE, _TRUNCATE)
    scales = np.exp(size_spread * np.clip(rng.standard_normal(size), -_TRUNCATE, _TRUNCATE))
    offsets = shift * rng.standard_normal((size, 3))
    rotations = Rotation.from_rotvec(tilt * rng.standard_normal((size, 3))).as_matrix()

    names = tuple(LATENT)[:latent]
    shapes = []
    for zi, scale in zip(z, scales):
        shape = base
        for name, value in zip(names, zi):
            amplitude, move = LATENT[name]
            shape = move(shape, spread * amplitude * value)
        shapes.append(replace(shape, **{n: getattr(shape, n) * scale for n in ("height", "width", "depth")}))
    return Cohort(shapes, z[:, :latent].copy(), names, scales, offsets, rotations)
