"""Where a trade is measured: seeded space-filling points of the parameter box and its extremes.

A model is judged at points it was not trained on, and stability at the box's extremes is part
of the trade. :func:`validation_points` gives, in the unit box [0, 1]^d of the parameters (log ones in
log μ, :meth:`~lungmech.fem.parameters.Parameters.to_unit`):

* ``count`` interior points: a scrambled Sobol' sequence of its own ``seed``, without any point
  a model was trained on (drawn further to keep ``count``);
* the corners: all 2^d while 2^d ≤ :data:`CORNERS`, else :data:`CORNERS` distinct corners drawn
  with the same seed and the 2d face centres (one coordinate at 0 or 1, the others at ½).

With N points and none failing, the share of the box that could still fail is, with 95 %
confidence, below :func:`failure_bound` (N) = 1 − 0.05^(1/N) (≈ 3/N: the rule of three): the
largest share p whose (1 − p)^N of passing all N is still 5 %.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import qmc

from lungmech import checks
from lungmech.fem.parameters import Parameters

__all__ = ["CORNERS", "ValidationPoints", "failure_bound", "validation_points"]

CORNERS = 32  # all corners of a box up to this many (d ≤ 5); a seeded choice of them beyond
SAME = 1e-12  # two points closer than this in the unit box are one point


@dataclass(frozen=True)
class ValidationPoints:
    """The points (values by name) and what each is: "interior", "corner" or "face"."""

    points: list[dict[str, float]]
    kinds: list[str]

    def __len__(self) -> int:
        return len(self.points)


def validation_points(
    box: Parameters, count: int, seed: int = 12345, trained: Sequence[Mapping[str, float]] = ()
) -> ValidationPoints:
    """``count`` interior points of ``box`` none of ``trained`` (seeded Sobol'), then its corners
    (and face centres beyond :data:`CORNERS` corners); see the module's doc. A box without
    parameters has one point, the defaults."""
    checks.integer("test point count", count, minimum=1)
    if not len(box):
        return ValidationPoints([{}], ["interior"])
    seen = np.array([box.to_unit(point) for point in trained]).reshape(-1, len(box))
    interior = _interior(len(box), count, seed, seen)
    extremes = _extremes(len(box), seed)
    kinds = ["interior"] * len(interior) + [kind for kind, _ in extremes]
    units = [*interior, *(unit for _, unit in extremes)]
    return ValidationPoints([box.from_unit(unit) for unit in units], kinds)


def failure_bound(count: int) -> float:
    """1 − 0.05^(1/N): with N points and none failing, the share of the box that could fail,
    bounded with 95 % confidence."""
    checks.integer("test point count", count, minimum=1)
    return float(1.0 - 0.05 ** (1.0 / count))


def _interior(dimension: int, count: int, seed: int, seen: np.ndarray) -> list[np.ndarray]:
    """``count`` points of a scrambled Sobol' sequence not within :data:`SAME` of ``seen``."""
    sobol = qmc.Sobol(d=dimension, scramble=True, seed=seed)
    found: list[np.ndarray] = []
    size = 1
    while len(found) < count:
        size *= 2  # Sobol' points come in powers of two: draw the next block
        for unit in sobol.random(size):
            if not len(seen) or np.abs(seen - unit).max(axis=1).min() > SAME:
                found.append(unit)
                if len(found) == count:
                    break
    return found


def _extremes(dimension: int, seed: int) -> list[tuple[str, np.ndarray]]:
    """The corners, all of them up to :data:`CORNERS`; beyond, that many distinct ones drawn with
    ``seed`` and the 2d face centres."""
    if 2**dimension <= CORNERS:
        return [("corner", np.array(c, dtype=float)) for c in itertools.product((0.0, 1.0), repeat=dimension)]
    rng = np.random.default_rng(seed)
    chosen: set[tuple[int, ...]] = set()
    while len(chosen) < CORNERS:
        chosen.add(tuple(int(b) for b in rng.integers(0, 2, dimension)))
    corners = [("corner", np.array(c, dtype=float)) for c in sorted(chosen)]
    faces = []
    for axis, end in itertools.product(range(dimension), (0.0, 1.0)):
        centre = np.full(dimension, 0.5)
        centre[axis] = end
        faces.append(("face", centre))
    return corners + faces
