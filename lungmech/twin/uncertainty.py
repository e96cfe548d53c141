"""How well the images determine a lung's parameters: intervals, bias and identifiability.

At the estimate θ̂ (unit coordinates) with residual r̂ (n rows, m) and Jacobian J = ∂r/∂θ:

* **noise**: σ̂² = ‖r̂‖² / (n − p), the Gauss–Newton (Laplace) covariance Σ = σ̂² (JᵀJ)⁻¹;
* **the model's own error** ε (per row, m: how far the model's predicted surface and volume may
  be from the full model's) is a bias, not a noise that averages away: the estimate moves by
  δθ = A δr with A = (JᵀJ)⁻¹Jᵀ, so ``abs(δθ) ≤ abs(A) ε`` row by row;
* **the interval** at level 1 − α is θ̂ ± (z Σᵢᵢ^½ + (``abs(A) ε``)ᵢ), z the normal quantile
  of 1 − α/2, mapped to physical values through the parameter's range (so a log-scaled one is asymmetric in μ); a parameter at a bound
  of its box has no Gaussian interval — the Laplace approximation assumes an interior optimum;
* **identifiability**: the correlations Σᵢⱼ/(Σᵢᵢ Σⱼⱼ)^½, and the eigenvectors of JᵀJ: a
  combination v whose standard deviation σ̂ λ^−½ is a large part of the box is one the data
  cannot determine (without gravity, a stiffer lung under a larger pressure looks alike);
* **a check by resampling**: repeated estimates from θ̂ with the surface residuals resampled
  (and the volume's drawn with σ̂), whose spread the Laplace standard deviations should match.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import norm

from lungmech.errors import ParameterError
from lungmech.twin.fit import Estimate, Fit, estimate

__all__ = ["Direction", "Interval", "Uncertainty", "laplace", "noise_level", "resampled"]

WEAK = 0.1  # a combination whose standard deviation exceeds this fraction of the box is not determined


@dataclass(frozen=True)
class Interval:
    """A parameter's interval (physical units): ``low``, ``high`` (None at an active bound,
    ``reason`` then says which), and its half-widths in unit coordinates: ``noise``
    (z σ) and ``bias`` (the model error's bound)."""

    low: float | None
    high: float | None
    noise: float
    bias: float
    reason: str | None = None


@dataclass(frozen=True)
class Direction:
    """An eigenvector of JᵀJ (unit coordinates, by parameter name) and the standard deviation
    of the estimate along it (unit box fractions); ``weak``: the data cannot determine it."""

    combination: dict[str, float]
    deviation: float
    weak: bool

    def text(self) -> str:
        """ "+0.71 stiffness − 0.70 breath"."""
        terms = [
            f"{'−' if c < 0 else '+'}{abs(c):.2f} {name}" for name, c in self.combination.items() if abs(c) >= 0.05
        ]
        return " ".join(terms).lstrip("+")


@dataclass(frozen=True)
class Uncertainty:
    """The uncertainty of an estimate: the noise level ``sigma`` (m), the ``covariance`` in
    unit coordinates, each parameter's ``interval`` at ``level``, the ``correlation`` matrix,
    the ``directions`` of JᵀJ (weakest first), and the model error's ``bias`` bound (unit)."""

    sigma: float
    covariance: np.ndarray
    intervals: dict[str, Interval]
    correlation: np.ndarray
    directions: list[Direction]
    bias: np.ndarray
    level: float


def noise_level(result: Estimate) -> float:
    """σ̂ = (‖r̂‖² / (n − p))^½ in m: the data's noise as the residual shows it."""
    n, p = result.jacobian.shape
    if n <= p:
        raise ParameterError(f"{n} data cannot determine {p} parameters with an uncertainty")
    return float(np.sqrt(result.residual @ result.residual / (n - p)))


def laplace(result: Estimate, fit: Fit, model_error: np.ndarray | None = None, level: float = 0.95) -> Uncertainty:
    """The Laplace uncertainty of ``result`` (see the module's doc); ``model_error``: ε per
    residual row (m), or None for a model taken as exact."""
    J = result.jacobian
    n = J.shape[0]
    if not 0 < level < 1:
        raise ParameterError(f"the interval's level must lie in (0, 1) (got {level})")
    sigma = noise_level(result)
    normal = J.T @ J
    try:
        inverse = np.linalg.inv(normal)
    except np.linalg.LinAlgError:
        inverse = np.linalg.pinv(normal)
    covariance = sigma**2 * inverse
    deviation = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    error = np.zeros(n) if model_error is None else np.abs(np.asarray(model_error, dtype=float))
    if error.shape != (n,):
        raise ParameterError(f"the model error needs one value per residual row ({n}; got shape {error.shape})")
    bias = np.abs(inverse @ J.T) @ error
    z = float(norm.ppf(0.5 + level / 2))
    intervals: dict[str, Interval] = {}
    reason: str | None
    for i, (name, parameter) in enumerate(zip(fit.names, fit.parameters)):
        half = z * deviation[i] + bias[i]
        side = result.active[name]
        if side is not None:
            reason = f"at the {side} bound of its range: no Gaussian interval (the optimum is not interior)"
            intervals[name] = Interval(None, None, z * deviation[i], bias[i], reason)
            continue
        low, high = (parameter.from_unit(result.unit[i] + s * half) for s in (-1.0, 1.0))
        clipped = result.unit[i] - half < 0 or result.unit[i] + half > 1
        reason = "reaches the edge of the model's range: the interval is cut there" if clipped else None
        if bounded := [other for other, side in result.active.items() if side is not None]:
            held = f"{', '.join(bounded)} at a bound of {'its' if len(bounded) == 1 else 'their'} range"
            reason = "; ".join(filter(None, [reason, f"holds with {held}, where the optimum is not interior"]))
        intervals[name] = Interval(low, high, z * deviation[i], bias[i], reason)
    scale = np.where(deviation > 0, deviation, 1.0)
    correlation = covariance / np.outer(scale, scale)
    values, vectors = np.linalg.eigh(normal)
    directions = []
    for value, vector in zip(values, vectors.T):
        spread = sigma / np.sqrt(value) if value > 0 else np.inf
        vector = vector if vector[np.argmax(np.abs(vector))] > 0 else -vector
        directions.append(Direction(dict(zip(fit.names, vector.round(4).tolist())), float(spread), bool(spread > WEAK)))
    return Uncertainty(sigma, covariance, intervals, correlation, directions, bias, level)


def resampled(fit: Fit, result: Estimate, count: int = 20, seed: int = 0) -> np.ndarray:
    """``count`` estimates (unit coordinates, count × p) from ``result`` with the noise drawn
    again: each view's surface residuals resampled with replacement (centred), each volume row
    drawn from N(0, σ̂²); each estimate starts at θ̂ (a few evaluations each)."""
    rng = np.random.default_rng(seed)
    r, n = result.residual, len(result.residual)
    sigma = noise_level(result)
    surfaces = fit.surface_rows()
    estimates = []
    for _ in range(count):
        noise = np.asarray(rng.normal(0.0, sigma, size=n), dtype=float)  # the volume rows
        for rows in surfaces:
            centred = r[rows] - r[rows].mean()
            noise[rows] = rng.choice(centred, size=len(rows), replace=True)
        # the data again: the prediction at θ̂ plus this noise (r̂ held the offset already added)
        again = estimate(fit, start=result.values, offset=result.offset + noise - r)
        estimates.append(again.unit)
    return np.array(estimates)
