"""The reference's own error: the observed order of convergence of three nested levels.

A trade measures every model against a full model finer than all of them, so the reference's
own discretisation error must be known, not assumed zero. From a quantity on three nested
meshes of sizes h, h/r, h/r² (q₁, q₂, q₃; r the refinement ratio) and its differences
d₁ = q₂ − q₁, d₂ = q₃ − q₂,

    p = ln(‖d₁‖ / ‖d₂‖) / ln r                (the observed order),
    ε₃ ≈ ‖d₂‖ / (r^p − 1)                     (Richardson's estimate of q₃'s error),

‖·‖ the largest entry's magnitude (a curve's worst time). The estimate is trusted — and given —
only where the convergence is asymptotic: p within :data:`AGREEMENT` of the order the
discretisation should have, and the differences of one sign entrywise (an oscillating sequence
has no Richardson limit). Otherwise the reference's accuracy is unknown, and a trade says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lungmech import checks
from lungmech.errors import ParameterError

__all__ = ["AGREEMENT", "Convergence", "observed_order", "order_of_differences"]

AGREEMENT = 0.5  # |p − expected| at most this: the levels are in the asymptotic range


@dataclass(frozen=True)
class Convergence:
    """Three nested levels of a quantity: the ``observed`` order p (inf where the finest two
    agree exactly, nan where all three do), the ``expected`` one, whether they ``agree``
    (within :data:`AGREEMENT`, the differences of one sign), and Richardson's ``estimate`` of
    the finest level's error (in the quantity's unit; None unless they agree)."""

    observed: float
    expected: float
    agree: bool
    estimate: float | None


def observed_order(coarse: object, middle: object, fine: object, expected: float, ratio: float = 2.0) -> Convergence:
    """The observed order of the quantity ``coarse``, ``middle``, ``fine`` (numbers, or arrays of
    one shape: a curve over the output times) on meshes refined by ``ratio`` each time, against
    the ``expected`` order (see the module's doc)."""
    levels = [np.atleast_1d(np.asarray(q, dtype=float)) for q in (coarse, middle, fine)]
    if len({level.shape for level in levels}) != 1:
        raise ParameterError(f"the three levels have different shapes ({', '.join(str(q.shape) for q in levels)})")
    if not all(np.all(np.isfinite(level)) for level in levels):
        raise ParameterError("a level of the quantity is not finite (a failed solve?)")
    first, second = levels[1] - levels[0], levels[2] - levels[1]
    one_sign = bool(np.all(first * second >= 0.0))
    return order_of_differences(float(np.abs(first).max()), float(np.abs(second).max()), expected, ratio, one_sign)


def order_of_differences(
    large: float, small: float, expected: float, ratio: float = 2.0, one_sign: bool = True
) -> Convergence:
    """The observed order from the sizes of the two differences, ‖d₁‖ = ``large`` and ‖d₂‖ =
    ``small`` (of numbers, or norms of fields: ‖x_h/r − x_h‖, ‖x_h/r² − x_h/r‖), against the
    ``expected`` order; ``one_sign``: the differences did not oscillate (see the module's doc)."""
    checks.real("refinement ratio", ratio)
    checks.real("expected order", expected)
    if not ratio > 1:
        raise ParameterError(f"the refinement ratio must be > 1 (got {ratio!r})")
    if not expected > 0:
        raise ParameterError(f"the expected order must be > 0 (got {expected!r})")
    if not (math.isfinite(large) and math.isfinite(small) and large >= 0 and small >= 0):
        raise ParameterError(f"the differences of the levels must be finite sizes ≥ 0 (got {large!r}, {small!r})")
    if small == 0.0:
        return Convergence(math.inf if large > 0 else math.nan, expected, False, None)
    if large == 0.0:  # the finest two differ where the coarsest two did not: no convergence seen
        return Convergence(-math.inf, expected, False, None)
    observed = math.log(large / small) / math.log(ratio)
    agree = one_sign and abs(observed - expected) <= AGREEMENT
    return Convergence(observed, expected, agree, small / (ratio**observed - 1.0) if agree else None)
