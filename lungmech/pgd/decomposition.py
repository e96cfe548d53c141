"""A separated representation of a model's solution over its parameter box:

    u(x, μ) = Σₖ ūₖ(x) Πⱼ λₖʲ(μⱼ),   ūₖ = Q Rₖ,

its space modes the columns of Q (owned entries of the model's state, orthonormal in the energy
inner product), each separated term's space part ūₖ = Q Rₖ (terms may share modes) and its
parameter modes λₖʲ cubic splines on each parameter's axis (:mod:`lungmech.pgd.axes`).
Evaluation is a product of spline values and two small matrix–vector products; the
derivatives in μ come from the splines' own.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from lungmech.errors import ParameterError
from lungmech.pgd.axes import Axis, taylor

__all__ = ["Decomposition"]


@dataclass
class Decomposition:
    """Σₖ Q Rₖ Πⱼ λₖʲ(μⱼ): ``modes`` Q (owned entries × m), ``reduced`` R (m × terms) and
    ``coefficients[j]`` (terms × axis j's size) the splines of axis j, one row per term."""

    axes: tuple[Axis, ...]
    modes: np.ndarray
    reduced: np.ndarray
    coefficients: list[np.ndarray]

    @property
    def size(self) -> int:
        """The number of space modes m."""
        return self.modes.shape[1]

    @property
    def terms(self) -> int:
        """The number of separated terms."""
        return self.reduced.shape[1]

    def units(self, mu: Mapping[str, float]) -> np.ndarray:
        """The point's unit coordinates s_j, one per axis (a parameter not given: its default);
        refused outside the box."""
        s = []
        for axis in self.axes:
            parameter = axis.parameter
            value = float(mu.get(parameter.name, parameter.default))
            low, high = parameter.range
            if not low - 1e-12 * abs(high - low) <= value <= high + 1e-12 * abs(high - low):
                raise ParameterError(f"{parameter.name} = {value:g} is outside the PGD's box [{low:g}, {high:g}]")
            s.append(parameter.to_unit(value))
        return np.array(s)

    @functools.cached_property
    def _polynomials(self) -> list[np.ndarray]:
        """Each axis's splines as cubics per interval (intervals × 4 × terms)."""
        return [axis.polynomials(X.T) for axis, X in zip(self.axes, self.coefficients)]

    def _at(self, mu: Mapping[str, float], derivative: int = 0, units: np.ndarray | None = None) -> np.ndarray:
        """λₖʲ(sⱼ) (or its ``derivative`` in s), axes × terms; ``units`` the point's
        :meth:`units` where already known. Every axis's cubic at once, on the axes' intervals
        stacked (:func:`~lungmech.pgd.axes.taylor`): an answer's microseconds."""
        if not self.axes:
            return np.zeros((0, self.terms))
        stacked, first, counts = self._stacked
        rows, t = [], []
        for axis, s, start, n in zip(self.axes, self.units(mu) if units is None else units, first, counts):
            s = axis.coordinate(float(s))
            i = min(int(s * n), n - 1)
            rows.append(start + i)
            t.append(s - (i + 0.5) / n)
        return taylor(stacked[rows], np.array(t), derivative)

    def products(self, mu: Mapping[str, float], units: np.ndarray | None = None) -> np.ndarray:
        """qₖ(μ) = Πⱼ λₖʲ(μⱼ), one per separated term; ``units`` the point's :meth:`units` where
        already known."""
        return np.multiply.reduce(self._at(mu, units=units), axis=0) if self.axes else np.ones(self.terms)

    @functools.cached_property
    def _stacked(self) -> tuple[np.ndarray, list[int], list[int]]:
        """Every axis's :attr:`_polynomials` one after the other (intervals × 4 × terms), where
        each axis's begin and how many intervals it has."""
        counts = [len(P) for P in self._polynomials]
        return np.concatenate(self._polynomials), np.cumsum([0, *counts[:-1]]).tolist(), counts

    def factors(self, mu: Mapping[str, float], tau: float | np.ndarray = 1.0) -> np.ndarray:
        """The space modes' coefficients at ``mu``: R (q(μ) ∘ τ) (m), ``tau`` the terms' factors
        at a time of the load path (:mod:`lungmech.pgd.timeline`; 1: the decomposition's own)."""
        return self.reduced @ (self.products(mu) * tau)

    def product_derivatives(self, mu: Mapping[str, float]) -> np.ndarray:
        """∂qₖ/∂μⱼ at ``mu`` (terms × parameters): λₖʲ'(sⱼ) dsⱼ/dμⱼ Π_{i≠j} λₖⁱ(sᵢ)."""
        s, values, slopes = self.units(mu), self._at(mu), self._at(mu, 1)
        columns = []
        for j, axis in enumerate(self.axes):
            others = np.prod([v for i, v in enumerate(values) if i != j], axis=0) if len(values) > 1 else 1.0
            value = axis.parameter.from_unit(float(s[j]))
            columns.append(slopes[j] * others / axis.parameter.unit_derivative(value))  # ds/dμ = 1/(dμ/ds)
        return np.column_stack(columns) if columns else np.zeros((self.terms, 0))

    def factor_derivatives(self, mu: Mapping[str, float], tau: float | np.ndarray = 1.0) -> np.ndarray:
        """∂(R (q ∘ τ))/∂μⱼ at ``mu`` (m × parameters)."""
        return self.reduced @ (self.product_derivatives(mu) * np.reshape(tau, (-1, 1)))

    def state(self, mu: Mapping[str, float]) -> np.ndarray:
        """u(μ) on the owned entries of the model's state."""
        return self.modes @ self.factors(mu)

    def at_nodes(self, j: int) -> np.ndarray:
        """λₖʲ at axis j's nodes (terms × nodes)."""
        return self.coefficients[j] @ self.axes[j].basis.T
