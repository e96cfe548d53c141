"""A patient's segmentations as the pairs :func:`lungmech.app.personalise.personalise` takes.

How the files are read is a :class:`Reading`: which values of a label image are the lung (one
label, or several taken together: a lung's lobes), the length unit of the headers, and which
lung of a segmentation that holds both (``lung``: "right", "left", or "both", a pair for each
lung: :mod:`lungmech.registration.lungs`). The command line and a cohort's workers read alike.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from lungmech.app.personalise import Pair
from lungmech.errors import ParameterError
from lungmech.registration import image
from lungmech.registration.lungs import LUNGS, lung_of
from lungmech.twin.displacement import Displacement

__all__ = ["CHOICES", "Reading"]

CHOICES = (*LUNGS, "both")


@dataclass(frozen=True)
class Reading:
    """How a patient's segmentations are read (see the module's doc); ``lung`` None: each
    segmentation is one lung, the scene's."""

    label: tuple[int, ...] | None = None
    unit: str | None = None
    lung: str | None = None

    def __post_init__(self) -> None:
        if self.lung is not None and self.lung not in CHOICES:
            raise ParameterError(f"--lung must be one of {', '.join(CHOICES)} (got {self.lung!r})")

    def pairs(
        self,
        expiration: str | Path,
        inspiration: str | Path,
        position: str = "supine",
        displacement: Displacement | None = None,
    ) -> list[Pair]:
        """The pair of images at these paths, a pair per lung asked for."""
        images = [image.read(path, label=self.label, unit=self.unit) for path in (expiration, inspiration)]
        if self.lung is None:
            return [Pair(images[0], images[1], position, displacement)]
        pairs = []
        for side in LUNGS if self.lung == "both" else (self.lung,):
            lungs = [lung_of(one, side) for one in images]
            for path, lung in zip((expiration, inspiration), lungs):
                if lung.islands > 0:
                    logging.getLogger("lungmech").info(
                        "personalise: %s: %.2f %% of its voxels lie in neither lung (small bodies), left out",
                        Path(path).name,
                        100 * lung.islands,
                    )
            pairs.append(Pair(lungs[0].image, lungs[1].image, position, displacement, side))
        return pairs
