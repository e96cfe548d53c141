"""Piecewise-linear load ramps: the factor a load or an imposed displacement is scaled by at time t."""

from __future__ import annotations

import bisect
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lungmech import checks
from lungmech.errors import ParameterError


@dataclass(frozen=True)
class Ramp:
    """Factor(t) interpolating ``values`` at ``times`` linearly, constant outside.

    The default ramps from 0 at t = 0 to 1 at t = 1. A breathing cycle is, for instance,
    ``Ramp((0, 1, 2), (0, 1, 0))``: inspiration then expiration.
    """

    times: Sequence[float] = (0.0, 1.0)
    values: Sequence[float] = (0.0, 1.0)

    def __post_init__(self) -> None:
        for name in ("times", "values"):
            given = getattr(self, name)
            if isinstance(given, str) or not isinstance(given, Sequence):
                raise ParameterError(f"ramp {name} must be a list of numbers (got {given!r})")
        times = np.array([checks.real(f"ramp times[{i}]", t) for i, t in enumerate(self.times)])
        values = np.array([checks.real(f"ramp values[{i}]", v) for i, v in enumerate(self.values)])
        if times.size == 0:
            raise ParameterError("a ramp needs at least one (time, value) point (got empty times and values)")
        if times.shape != values.shape:
            raise ParameterError(f"a ramp needs as many times as values (got {times.size} times, {values.size} values)")
        if np.any(np.diff(times) <= 0):
            raise ParameterError(f"ramp times must increase strictly (got {list(times)})")
        object.__setattr__(self, "times", tuple(times))
        object.__setattr__(self, "values", tuple(values))

    def __call__(self, t: float) -> float:
        # np.interp's, without its arrays: a PGD's answer asks a ramp several times a point
        times, values = self.times, self.values
        if t != t:  # NaN, as np.interp gives it
            return float("nan")
        i = bisect.bisect_right(times, t)
        if i == 0 or i == len(times):
            return float(values[0] if i == 0 else values[-1])
        start, end = times[i - 1], times[i]
        return float(values[i - 1] + (values[i] - values[i - 1]) * ((t - start) / (end - start)))

    @classmethod
    def constant(cls, value: float = 1.0) -> Ramp:
        return cls((0.0,), (value,))
