"""How a PGD's separated terms move along the load path: τₖ(t), so that the state at μ and t is

    u(μ, t) = Q R (q(μ) ∘ τ(t)),   qₖ(μ) = Πⱼ λₖʲ(μⱼ)

(:class:`~lungmech.pgd.decomposition.Decomposition`). A linear model whose loads follow one
ramp r(t) from rest is at r(t)/r(T) of its end state T at every t, every term alike
(:class:`RampTimeline`). A PGD fitted to full solves knows each term's value at the output
times (:class:`SampledTimeline`): exact there, and between them the monotone cubic through
them and the rest at the path's start (SciPy's PCHIP: no overshoot where the ramp has a kink).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["RampTimeline", "SampledTimeline", "Timeline"]


@dataclass(frozen=True)
class RampTimeline:
    """τₖ(t) = r(t) / r(``end``) for every term: ``ramp`` r."""

    ramp: Callable[[float], float]
    end: float

    def at(self, t: float) -> float:
        return self.ramp(t) / self._at_end

    @functools.cached_property
    def _at_end(self) -> float:
        return self.ramp(self.end)


@dataclass(frozen=True)
class SampledTimeline:
    """τₖ at the output ``times`` (s) as ``values`` (terms × times), 0 at ``start`` unless the
    times begin there (an imaged body's: its start moves with μ)."""

    start: float
    times: np.ndarray
    values: np.ndarray

    @functools.cached_property
    def _curve(self) -> Callable[[float], np.ndarray]:
        from scipy.interpolate import PchipInterpolator

        times, values = self.times, self.values
        if times[0] > self.start:  # from rest
            times = np.concatenate([[self.start], times])
            values = np.column_stack([np.zeros(len(values)), values])
        return PchipInterpolator(times, values, axis=1, extrapolate=False)

    def at(self, t: float) -> np.ndarray:
        """τ(t), one value per term (exact at an output time)."""
        i = int(np.searchsorted(self.times, t))
        if i < len(self.times) and abs(self.times[i] - t) <= 1e-12 * max(abs(t), 1.0):
            return self.values[:, i]
        if i > 0 and abs(self.times[i - 1] - t) <= 1e-12 * max(abs(t), 1.0):
            return self.values[:, i - 1]
        return np.asarray(self._curve(t), dtype=float)


Timeline = RampTimeline | SampledTimeline
