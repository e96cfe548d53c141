"""One lung out of a segmentation that holds both.

A chest CT segmented by a lung tool gives both lungs in one image: as two labels (or a label per
lobe: ``--label`` takes several), or as one binary mask of two bodies. The lung on the
patient's right is the body whose centroid lies further along +x of the patient frame (RAS+:
x grows to the patient's right), so only an image whose header orients it can be split.

The bodies are the mask's face-connected components. Two lungs are the two largest when the
smaller holds at least a quarter of the larger's voxels (a left lung is about 45 % of the
lungs) and they lie side by side (their extents along x overlap by at most a fifth of the
narrower's: lobes of one lung lie above and in front of each other). Lungs that touch at a thin
junction (the anterior junction line, a few voxels) form one body: it is opened by erosion, one
voxel at a time up to :data:`JUNCTION`, until two such bodies appear, and each voxel of the mask
then goes to the nearer of them. Smaller islands (a stray voxel, a piece of trachea) are left
out, and how much they held is said. A mask of one body that does not split is one lung: it is
kept when its shape says it is of the side asked for (:mod:`lungmech.registration.side`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from lungmech.errors import ImageError
from lungmech.registration import side as sides
from lungmech.registration.image import Image

__all__ = ["LUNGS", "Lung", "lung_of"]

LUNGS = ("right", "left")
PAIRED = 0.25  # the smaller body of two lungs holds at least this fraction of the larger's voxels
BESIDE = 0.2  # two lungs' extents along x overlap by at most this fraction of the narrower's
JUNCTION = 3  # voxels of erosion tried to part lungs that touch


@dataclass(frozen=True)
class Lung:
    """The lung on ``side`` of a segmentation (``image``: the same grid, that body only), and
    the fraction of the segmentation's voxels left out with the other lung's
    (``islands``: in bodies too small to be a lung)."""

    image: Image
    side: str
    islands: float


def lung_of(image: Image, side: str) -> Lung:
    """The lung on the patient's ``side`` ("right" or "left") of ``image`` (see the module's
    doc), or one line on why it cannot be told apart."""
    if side not in LUNGS:
        raise ImageError(f"a lung is 'right' or 'left' (got {side!r})")
    name = f"'{image.source.name}'" if image.source is not None else "the segmentation"
    bodies, count = ndimage.label(image.mask)
    sizes = np.bincount(bodies.ravel(), minlength=count + 1)[1:]
    order = np.argsort(sizes)[::-1]
    total = int(sizes.sum())
    if (pair := _two_lungs(image, bodies)) is not None:
        if not image.oriented:
            raise ImageError(
                f"{name} has no orientation in its header: which of its two lungs is the right one cannot be read"
            )
        x = [float(image.points(np.argwhere(lung))[:, 0].mean()) for lung in pair]
        kept = pair[int(np.argmax(x))] if side == "right" else pair[int(np.argmin(x))]
        islands = 1.0 - (int(pair[0].sum()) + int(pair[1].sum())) / total
        return Lung(replace(image, mask=kept), side, islands)
    largest = bodies == order[0] + 1
    found = sides.of_image(replace(image, mask=largest))
    if found.side != side:
        said = f"a {found.side} lung" if found.side else f"a lung of no clear side ({found.reason})"
        raise ImageError(
            f"{name} holds one body, {said}, where the {side} lung was asked for: if the lungs touch, "
            "give a label image and choose with --label"
        )
    return Lung(replace(image, mask=largest), side, float(1.0 - sizes[order[0]] / total))


def _two_lungs(image: Image, bodies: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The masks of the two lungs of ``image`` whose mask's components are ``bodies`` (see the
    module's doc), or None when it holds one."""
    mask = image.mask
    for depth in range(JUNCTION + 1):
        opened = mask if depth == 0 else ndimage.binary_erosion(mask, iterations=depth)
        opened_bodies, count = ndimage.label(opened)
        if count < 2:
            continue
        sizes = np.bincount(opened_bodies.ravel(), minlength=count + 1)[1:]
        first, second = np.argsort(sizes)[::-1][:2] + 1
        if sizes[second - 1] < PAIRED * sizes[first - 1]:
            continue
        extents = [image.points(np.argwhere(opened_bodies == label))[:, 0] for label in (first, second)]
        overlap = min(e.max() for e in extents) - max(e.min() for e in extents)
        if overlap > BESIDE * min(float(np.ptp(e)) for e in extents):
            return None  # (parts of one lung: eroding further would not make them lungs)
        if depth == 0:
            return opened_bodies == first, opened_bodies == second
        seeds = np.where(opened_bodies == first, 1, np.where(opened_bodies == second, 2, 0))
        nearest = ndimage.distance_transform_edt(
            seeds == 0, sampling=image.spacing, return_distances=False, return_indices=True
        )
        grown = seeds[tuple(nearest)]
        parted = np.isin(bodies, np.unique(bodies[seeds > 0]))  # the body they were parted from, not islands
        return parted & (grown == 1), parted & (grown == 2)
    return None
