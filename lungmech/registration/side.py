"""Which lung an image or a mesh holds: the side its medial face looks to.

A lung has two faces along the patient's left–right axis: the costal face, convex, on the ribs,
and the medial (mediastinal) face, flat or hollow, around the heart and the hilum. The costal
face of a right lung looks to the patient's right (+x in lungmech's coordinates, RAS+), the
medial face to the left; a left lung is the other way round. Two cues tell them apart, both
measured along the x axis of the patient frame:

* **convexity**: in every axial slab, each face's boundary curve x(y) is compared with the chord
  between its ends. The costal face bulges out of its chord, the medial face does not (flat) or
  falls behind it (hollow). ``convexity`` = (bulge of the +x face − bulge of the −x face) / the
  x extent: > 0 when the +x face is the costal one (a right lung).
* **concavity** (images only): the hollows of the body — in each axial slice, its convex hull
  less itself: the cardiac impression, the hilum, the notch — lie medially; ``concavity`` is the offset along x of
  their centroid from the body's, over the x extent: < 0 for a right lung. A flat medial face
  leaves few hollows there, so this cue only counts when it is clear.

Each cue that is clear votes; the side is decided when the votes agree, and is otherwise
undecided, with the reason. An image whose header has no orientation has no patient frame:
undecided too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from dolfinx import mesh as dmesh
from scipy.spatial import ConvexHull, Delaunay, QhullError

from lungmech.registration.image import Image

__all__ = ["Side", "convexity", "of_image", "of_mesh", "of_points"]

CLEAR_CONVEXITY = 0.02  # of the x extent: below it the two faces bulge alike
CLEAR_CONCAVITY = 0.03  # of the x extent: below it the hollows sit in the middle


@dataclass(frozen=True)
class Side:
    """The lung's side (``"right"``, ``"left"``, or None when undecided, with the ``reason``),
    and the cues it was decided by (dimensionless, see the module's doc)."""

    side: str | None
    convexity: float
    concavity: float | None
    reason: str = ""

    def describe(self) -> dict:
        return {"side": self.side, "convexity": self.convexity, "concavity": self.concavity, "reason": self.reason}


def convexity(points: npt.ArrayLike, size: float) -> float:
    """(bulge of the +x face − bulge of the −x face) / x extent of a body given by ``points``
    (n × 3, m: voxel centres, or its boundary nodes), binned in y and z by ``size`` (m).

    In each z slab, the face's curve is the largest (smallest) x of each y bin; its bulge is the
    mean distance by which it passes its chord outwards, over the bins, weighted by their count
    over all slabs."""
    p = np.asarray(points, dtype=float)
    extent = float(np.ptp(p[:, 0]))
    if len(p) < 8 or extent <= 0:
        return 0.0
    bins = np.floor((p[:, 1:] - p[:, 1:].min(axis=0)) / size).astype(np.int64)
    key = bins[:, 1] * (bins[:, 0].max() + 1) + bins[:, 0]  # (slab, row)
    order = np.argsort(key, kind="stable")
    key, x, rows, slabs = key[order], p[order, 0], bins[order, 0], bins[order, 1]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    high, low = np.maximum.reduceat(x, starts), np.minimum.reduceat(x, starts)
    row, slab = rows[starts], slabs[starts]
    bulges, counts = np.zeros(2), 0
    for s in np.unique(slab):
        here = slab == s
        if here.sum() < 3:
            continue
        y = row[here].astype(float)
        for face, (curve, outward) in enumerate(((high[here], 1.0), (low[here], -1.0))):
            chord = curve[0] + (curve[-1] - curve[0]) * (y - y[0]) / (y[-1] - y[0])
            bulges[face] += float(np.sum(outward * (curve - chord)))
        counts += int(here.sum())
    return float((bulges[0] - bulges[1]) / max(counts, 1) / extent)


def of_points(points: npt.ArrayLike, size: float, concavity: float | None = None) -> Side:
    """The side of a body given by ``points`` (see :func:`convexity`), with the concavity cue if
    known: each clear cue votes, and the side is theirs when they agree."""
    bulge = convexity(points, size)
    votes = {}
    if abs(bulge) >= CLEAR_CONVEXITY:
        votes["its convex face"] = ("right" if bulge > 0 else "left", f"convexity {bulge:+.3f}")
    if concavity is not None and abs(concavity) >= CLEAR_CONCAVITY:
        votes["its hollows"] = ("right" if concavity < 0 else "left", f"concavity {concavity:+.3f}")
    said = {side for side, _ in votes.values()}
    if len(said) == 1:
        return Side(said.pop(), bulge, concavity)
    if not votes:
        shown = f"convexity {bulge:+.3f}" + (f", concavity {concavity:+.3f}" if concavity is not None else "")
        return Side(None, bulge, concavity, f"neither its faces nor its hollows tell its sides apart ({shown})")
    cues = "; ".join(f"{cue} says {side} ({value})" for cue, (side, value) in votes.items())
    return Side(None, bulge, concavity, f"the cues disagree: {cues}")


def of_image(image: Image) -> Side:
    """The side of the lung segmented in ``image``, in the header's patient frame; undecided
    (with the reason) when the header has no orientation or the cues are not clear."""
    side = of_points(image.points(np.argwhere(image.mask)), float(image.spacing.max()), _concavity(image))
    if not image.oriented:
        return Side(None, side.convexity, side.concavity, "the image's header has no orientation (no patient frame)")
    return side


def of_mesh(mesh: dmesh.Mesh) -> Side:
    """Collective: the side of the body a mesh fills, by the convexity of its nodes (the
    extreme x of each bin is on its boundary), binned by its cells' typical size."""
    local = mesh.geometry.x[: mesh.geometry.index_map().size_local]
    points = np.vstack(mesh.comm.allgather(local))
    cells = mesh.topology.index_map(mesh.topology.dim).size_global
    volume = float(np.prod(np.ptp(points, axis=0)))
    size = 2.0 * (volume / max(cells, 1)) ** (1 / 3)  # two cells across a bin: a node in most
    return of_points(points, size)


def _concavity(image: Image) -> float | None:
    """The x offset of the hollows' centroid from the body's, over the x extent; None when the
    body is nearly convex. The hollows are, slice by slice across the voxel axis nearest the
    patient's z, the pixels inside the convex hull of the slice's body but not in it: the
    mediastinal hollow, the hilum and the notch, which axial slices cut across (the dome, which
    they do not, is left out)."""
    axis = int(np.argmax(np.abs(image.affine[2, :3]) / image.spacing))  # the slices' normal ~ z
    moved = np.moveaxis(image.mask, axis, 0)
    hollow_x, hollow_n = 0.0, 0
    for k in np.flatnonzero(moved.any(axis=(1, 2))):
        pixels = np.argwhere(moved[k])
        lo, hi = pixels.min(axis=0), pixels.max(axis=0) + 1
        if np.any(hi - lo < 3):
            continue
        box = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"), -1).reshape(-1, 2)
        empty = box[~moved[k][tuple(box.T)]]
        if not len(empty):
            continue
        world = image.points(np.insert(pixels, axis, k, axis=1))[:, :2]
        try:
            hull = Delaunay(world[ConvexHull(world).vertices])
        except QhullError:
            continue
        candidates = image.points(np.insert(empty, axis, k, axis=1))
        hollows = candidates[hull.find_simplex(candidates[:, :2]) >= 0]
        hollow_x += float(hollows[:, 0].sum())
        hollow_n += len(hollows)
    body = image.points(np.argwhere(image.mask))
    if hollow_n < 0.01 * len(body):
        return None
    return float((hollow_x / hollow_n - body[:, 0].mean()) / np.ptp(body[:, 0]))
