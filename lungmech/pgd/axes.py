"""A parameter's axis: the 1-D space its PGD modes λʲ(μⱼ) live in, and the rule that integrates
over it.

Each parameter μⱼ is read in its unit coordinate s = ``parameter.to_unit(μ)`` ∈ [0, 1] (linear,
or logarithmic for a log-scale parameter), so that the box's measure is the one its sampling
uses. A mode is a cubic B-spline on ``intervals`` uniform intervals of s: C² (derivatives in μ
are exact and smooth, for estimation), with ``intervals + 3`` coefficients, or ``intervals`` on
a periodic axis (a posture angle over a full turn: the spline closes on itself, C² across
s = 0 ≡ 1). Integrals over the axis are means, ∫₀¹ f(s) ds, by Gauss–Legendre's rule with four
points per interval (exact for a product of two splines times a cubic).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import BSpline

from lungmech import checks
from lungmech.errors import ParameterError
from lungmech.fem.parameters import ANGLES, Parameter

__all__ = ["Axis", "full_turn", "horner", "taylor"]

_POWERS = np.arange(4.0)  # t⁰ … t³

DEGREE = 3  # cubic: C² modes
POINTS = 4  # Gauss points per interval


def full_turn(parameter: Parameter) -> bool:
    """Whether ``parameter`` is an angle over a full turn (gravity's pitch, roll or in-plane angle
    spanning 360°): its axis is periodic."""
    low, high = parameter.range
    return parameter.target.rsplit(".", 1)[-1] in ANGLES and bool(np.isclose(high - low, 360.0))


@dataclass(frozen=True)
class Axis:
    """The cubic B-splines of ``parameter`` on ``intervals`` uniform intervals of its unit
    coordinate, periodic over a full turn (:func:`full_turn`), and the axis's Gauss rule:
    ``nodes`` (unit coordinates), ``weights`` (summing to 1: a mean) and ``basis``, the splines'
    values there (nodes × :attr:`size`)."""

    parameter: Parameter
    intervals: int
    periodic: bool = field(init=False)
    nodes: np.ndarray = field(init=False, repr=False)
    weights: np.ndarray = field(init=False, repr=False)
    basis: np.ndarray = field(init=False, repr=False)
    _knots: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        checks.integer(f"PGD axis {self.parameter.name!r}: intervals", self.intervals, minimum=1)
        periodic = full_turn(self.parameter)
        if periodic and self.intervals < DEGREE + 1:
            raise ParameterError(
                f"PGD axis {self.parameter.name!r}: a periodic axis needs at least {DEGREE + 1} intervals (got {self.intervals})"
            )
        object.__setattr__(self, "periodic", periodic)
        n, k = self.intervals, DEGREE
        uniform = np.arange(-k, n + k + 1) / n  # periodic: the knots run on past both ends
        clamped = np.concatenate([np.zeros(k), np.linspace(0.0, 1.0, n + 1), np.ones(k)])
        object.__setattr__(self, "_knots", uniform if periodic else clamped)
        x, w = np.polynomial.legendre.leggauss(POINTS)
        left = np.arange(self.intervals)[:, None] / self.intervals
        nodes = (left + (x[None, :] + 1) / (2 * self.intervals)).ravel()
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "weights", np.tile(w / (2 * self.intervals), self.intervals))
        object.__setattr__(self, "basis", self.at(nodes))

    @property
    def size(self) -> int:
        """The number of spline coefficients of a mode."""
        return self.intervals if self.periodic else self.intervals + DEGREE

    @property
    def values(self) -> np.ndarray:
        """The parameter's values μ at the nodes."""
        return np.array([self.parameter.from_unit(float(s)) for s in self.nodes])

    def at(self, s: np.ndarray, derivative: int = 0) -> np.ndarray:
        """The splines' values (or their ``derivative``-th derivative in s) at unit coordinates
        ``s``: len(s) × :attr:`size`."""
        return self.spline(np.eye(self.size), derivative)(self.unit(s))

    def spline(self, coefficients: np.ndarray, derivative: int = 0) -> BSpline:
        """The spline (or its ``derivative``-th derivative in s) of ``coefficients`` (size, ...):
        one curve per trailing index, evaluated at unit coordinates (see :meth:`unit`)."""
        c = np.asarray(coefficients, dtype=float)
        if self.periodic:  # spline i and i + n are one: the curve closes on itself
            c = c[np.arange(self.intervals + DEGREE) % self.intervals]
        curve = BSpline(self._knots, c, DEGREE)
        return curve.derivative(derivative) if derivative else curve

    def polynomials(self, coefficients: np.ndarray) -> np.ndarray:
        """The splines of ``coefficients`` (size, ...) as one cubic per interval, in powers of
        the distance t from its midpoint: (intervals, 4, ...), value Σₖ Pₖ tᵏ (their Taylor
        coefficients there: exact for a cubic; a midpoint is never a knot, where the third
        derivative jumps). What an online evaluation reads (:func:`horner`, :func:`taylor`)."""
        middle = (np.arange(self.intervals) + 0.5) / self.intervals
        return np.stack(
            [self.spline(coefficients, k)(middle) / factorial for k, factorial in enumerate((1.0, 1.0, 2.0, 6.0))],
            axis=1,
        )

    def coordinate(self, s: float) -> float:
        """One unit coordinate, already checked inside the box, as the splines read it (modulo 1
        on a periodic axis): :meth:`unit` for one point, without NumPy's per-call cost."""
        return s % 1.0 if self.periodic else min(max(s, 0.0), 1.0)

    def unit(self, s: np.ndarray) -> np.ndarray:
        """Unit coordinates as the splines read them: modulo 1 on a periodic axis; refused
        outside [0, 1] otherwise."""
        s = np.atleast_1d(np.asarray(s, dtype=float))
        if self.periodic:
            return np.mod(s, 1.0)
        if np.any((s < -1e-12) | (s > 1 + 1e-12)):
            raise ParameterError(f"PGD axis {self.parameter.name!r}: a value outside its range {self.parameter.range}")
        return np.clip(s, 0.0, 1.0)

    def fit(self, values: np.ndarray) -> np.ndarray:
        """The coefficients of the spline closest to ``values`` at the nodes in the axis's mean
        square (its L² projection)."""
        B, w = self.basis, self.weights
        return np.linalg.solve(B.T @ (w[:, None] * B), B.T @ (w * values))


def horner(polynomials: np.ndarray, s: float, derivative: int = 0) -> np.ndarray:
    """The splines of :meth:`Axis.polynomials` at one unit coordinate ``s`` (already read by
    :meth:`Axis.unit`), or their first ``derivative`` in s: a few microseconds, where a SciPy
    spline call costs tens."""
    intervals = polynomials.shape[0]
    i = min(int(s * intervals), intervals - 1)
    return taylor(polynomials[[i]], np.array([s - (i + 0.5) / intervals]), derivative)[0]


def taylor(polynomials: np.ndarray, t: np.ndarray, derivative: int = 0) -> np.ndarray:
    """Σₖ Pₖ tᵏ (or its first ``derivative`` in t) for each row: ``polynomials`` (rows × 4 × ...)
    intervals' cubics of :meth:`Axis.polynomials`, ``t`` (rows) the distance from each one's
    midpoint. One batched product for every row (several axes' intervals at once)."""
    t = np.asarray(t, dtype=float)[:, None, None]
    powers = np.concatenate([0.0 * t, t**0, 2.0 * t, 3.0 * t**2], axis=2) if derivative else t**_POWERS
    rows = polynomials.reshape(len(polynomials), 4, -1)
    return (powers @ rows)[:, 0].reshape(len(polynomials), *polynomials.shape[2:])
