"""The trade's answer: the cheapest model whose measured worst error meets the tolerance.

Each candidate arrives measured (:class:`Measured`): its worst error over the validation points
on the named quantity (relative, with that quantity's stated denominator), the points where it
failed, its warm online time per point and its offline cost. :func:`choose` keeps those that
failed nowhere and meet the tolerance, and picks the least cost per query,

    cost = online + offline / queries     (online alone without ``queries``),

so that a model expensive to build wins only where it is asked often enough. A tolerance at or
below the reference's own accuracy cannot be judged, and is refused with the number.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from lungmech import checks
from lungmech.errors import ParameterError

__all__ = ["Choice", "Measured", "check_tolerance", "choose"]


@dataclass(frozen=True)
class Measured:
    """A candidate as measured: its ``name``, its ``family`` ("full", "galerkin", "ecsw", …), its
    worst relative ``error`` on the quantity over the points it answered, the points where it
    ``failed``, its warm ``online`` time per point (s) and its ``offline`` cost (s; 0 for a full
    model)."""

    name: str
    family: str
    error: float
    failed: int
    online: float
    offline: float = 0.0

    def cost(self, queries: int | None) -> float:
        """Seconds per query: online, plus the offline cost shared by ``queries`` queries."""
        return self.online + (self.offline / queries if queries else 0.0)


@dataclass(frozen=True)
class Choice:
    """The chosen candidate (None where none qualifies) and why, in one line."""

    chosen: Measured | None
    reason: str


def check_tolerance(tolerance: float) -> None:
    """Refuse a tolerance that is no relative error in (0, 1), in one line."""
    checks.real("tolerance", tolerance)
    if not 0 < tolerance < 1:
        raise ParameterError(f"the tolerance (a relative error) must lie in (0, 1) (got {tolerance!r})")


def choose(
    candidates: Sequence[Measured],
    tolerance: float,
    quantity: str,
    queries: int | None = None,
    reference_accuracy: float | None = None,
) -> Choice:
    """The cheapest of ``candidates`` with no failed point and ``error`` ≤ ``tolerance`` on
    ``quantity`` (its name, for the reason), its cost over ``queries`` queries when given; see
    the module's doc. ``reference_accuracy``: the reference's own relative error on the quantity
    (Richardson's estimate), where known."""
    check_tolerance(tolerance)
    if queries is not None:
        checks.integer("queries", queries, minimum=1)
    if reference_accuracy is not None and tolerance <= reference_accuracy:
        raise ParameterError(
            f"the tolerance {tolerance:.1e} on {quantity} is below the reference's own accuracy "
            f"({reference_accuracy:.1e}): it cannot be judged; ask for more, or refine the reference"
        )
    if not candidates:
        raise ParameterError("no candidate models to choose from")
    qualified = [c for c in candidates if c.failed == 0 and math.isfinite(c.error) and c.error <= tolerance]
    per = f" over {queries} queries" if queries else ""
    if not qualified:
        answered = [c for c in candidates if c.failed == 0 and math.isfinite(c.error)]
        if not answered:
            return Choice(None, f"every candidate failed at some point; none meets {tolerance:.1e} on {quantity}")
        best = min(answered, key=lambda c: c.error)
        return Choice(
            None,
            f"none meets {tolerance:.1e} on {quantity}: the most accurate, {best.name}, is off by {best.error:.1e}",
        )
    chosen = min(qualified, key=lambda c: (c.cost(queries), c.error))
    return Choice(
        chosen,
        f"{chosen.name}: {chosen.error:.1e} ≤ {tolerance:.1e} on {quantity}, "
        f"{chosen.cost(queries) * 1e3:.3g} ms a query{per}, the cheapest of {len(qualified)} that meet it",
    )
