"""Piecewise-linear load ramps: the factor a load or an imposed displacement is scaled by at time t."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lungmech.errors import ParameterError


@dataclass(frozen=True)
class Ramp:
    """Factor(t) interpolating ``values`` at ``times`` linearly, constant outside.

    The default ramps from 0 at t = 0 to 1 at t = 1. A breathing cycle is, for instance,
    ``Ramp((0, 1, 2), (0, 1, 0))``: inspiration then expiration.
    """

    times: Sequence[float] = (0.0, 1.0)
    values: Sequence[float] = (0.0, 1.0)

    def __post_init__(self):
        times = np.asarray(self.times, dtype=float)
        values = np.asarray(self.values, dtype=float)
        if times.ndim != 1 or times.size < 1 or times.shape != values.shape:
            raise ParameterError(
                f"a ramp needs as many times as values (got {times.size} times, {values.size} values)"
            )
        if not (np.all(np.isfinite(times)) and np.all(np.isfinite(values))):
            raise ParameterError("ramp times and values must be finite numbers")
        if np.any(np.diff(times) <= 0):
            raise ParameterError(f"ramp times must increase strictly (got {list(times)})")
        object.__setattr__(self, "times", tuple(times))
        object.__setattr__(self, "values", tuple(values))

    def __call__(self, t: float) -> float:
        return float(np.interp(t, self.times, self.values))

    @classmethod
    def constant(cls, value: float = 1.0) -> Ramp:
        return cls((0.0,), (value,))
