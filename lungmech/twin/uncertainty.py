"""How well the images determine a lung's parameters: intervals, bias and identifiability.

At the estimate θ̂ (unit coordinates) with residual r̂ (n rows, m) and Jacobian J = ∂r/∂θ:

* **noise**: σ̂² = ‖r̂‖² / (n − p), the Gauss–Newton (Laplace) covariance Σ = σ̂² (JᵀJ)⁻¹;
* **the box**: the parameters lie in the model's ranges, and a direction the data hardly
  determine has a Laplace deviation larger than the box (without gravity, a stiffer lung under a
  larger pressure looks alike). The posterior under a flat prior on the box is the Gaussian
  N(θ̂ − A r̂, Σ) — centred where the linearised fit would go without bounds, A = (JᵀJ)⁻¹Jᵀ —
  cut to the box; each parameter's interval at level 1 − α is its marginal's α/2 and 1 − α/2
  quantiles, drawn by sampling (seeded). Without the cut, a parameter correlated with a weakly
  determined one would be given the whole of that one's spread beyond the box, and the
  intervals would hold the truth far more often than they say;
* **the model's own error** δr_k (per row, m: the model's answer to the data less that of the
  model it stands for — the full model, the lung refined once —, at a few check points k) is a
  bias, not a noise that averages away: the estimate moves by δθ_k = A δr_k, and the interval
  is widened by b = max_k ``abs(δθ_k)`` each side. (Bounding it by ``abs(A)`` max_k ``abs(δr_k)``
  would suppose each of hundreds of surface data erred in the direction that hurts most: on the
  twin experiments' lungs that bound is 7–10 times the measured shift);
* the interval is mapped to physical values through the parameter's range (so a log-scaled one
  is asymmetric in μ); a parameter at a bound of its box has no interval — the Laplace
  approximation assumes an interior optimum —, and the others' then hold with it there;
* **identifiability**: the correlations Σᵢⱼ/(Σᵢᵢ Σⱼⱼ)^½, and the eigenvectors of JᵀJ: a
  combination v whose standard deviation σ̂ λ^−½ is a large part of the box is one the data
  cannot determine;
* **a check by resampling**: repeated estimates from θ̂ with the surface residuals resampled
  (and the volume's drawn with σ̂), whose spread the Laplace standard deviations should match.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import truncnorm

from lungmech.errors import ParameterError
from lungmech.twin.fit import Estimate, Fit, estimate

__all__ = ["Direction", "Interval", "Uncertainty", "laplace", "noise_level", "resampled"]

WEAK = 0.1  # a combination whose standard deviation exceeds this fraction of the box is not determined
FLOOR = 1e-12  # of JᵀJ's largest eigenvalue: a combination below it is not seen at all
FLAT = 10.0  # box widths: a deviation beyond it is flat over the box (the draws' spread is capped there)


@dataclass(frozen=True)
class Interval:
    """A parameter's interval (physical units): ``low``, ``high`` (None at an active bound,
    ``reason`` then says which), and its parts in unit coordinates: ``noise`` (the half-width
    the noise alone gives, in the box) and ``bias`` (the model error's shift, added each side)."""

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
    the ``directions`` of JᵀJ (weakest first), and the model error's ``bias`` (unit)."""

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


def laplace(
    result: Estimate, fit: Fit, model_errors: np.ndarray | None = None, level: float = 0.95, seed: int = 0
) -> Uncertainty:
    """The Laplace uncertainty of ``result`` in the box (see the module's doc);
    ``model_errors``: the model's error δr_k on each residual row at each check point k
    (k × rows, m), or None for a model taken as exact; ``seed``: the posterior's draws'."""
    J = result.jacobian
    n, p = J.shape
    if not 0 < level < 1:
        raise ParameterError(f"the interval's level must lie in (0, 1) (got {level})")
    sigma = noise_level(result)
    normal = J.T @ J
    values, vectors = np.linalg.eigh(normal)
    # a combination the data do not see at all (JᵀJ singular): flat in the box, no shift along it
    floor = FLOOR * max(float(values.max()), np.finfo(float).tiny)
    seen = values > floor
    covariance = sigma**2 * (vectors / np.maximum(values, floor)) @ vectors.T
    deviation = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    shifts = (vectors[:, seen] / values[seen]) @ vectors[:, seen].T @ J.T  # A
    errors = np.zeros((1, n)) if model_errors is None else np.atleast_2d(np.asarray(model_errors, dtype=float))
    if errors.shape[1:] != (n,):
        raise ParameterError(f"the model error needs one value per residual row ({n}; got shape {errors.shape})")
    bias = np.abs(errors @ shifts.T).max(axis=0)
    centre = result.unit - shifts @ result.residual
    spreads = np.minimum(sigma / np.sqrt(np.maximum(values, floor)), FLAT)
    quantiles = _in_box(centre, vectors * spreads, result.unit, level, seed)
    intervals: dict[str, Interval] = {}
    bounded = [name for name, side in result.active.items() if side is not None]
    held = f"{', '.join(bounded)} at a bound of {'its' if len(bounded) == 1 else 'their'} range" if bounded else ""
    for i, (name, parameter) in enumerate(zip(fit.names, fit.parameters)):
        low, high = quantiles[0, i] - bias[i], quantiles[1, i] + bias[i]
        noise = 0.5 * float(quantiles[1, i] - quantiles[0, i])
        if side := result.active[name]:
            reason = f"at the {side} bound of its range: no Gaussian interval (the optimum is not interior)"
            intervals[name] = Interval(None, None, noise, float(bias[i]), reason)
            continue
        notes = ["reaches the edge of the model's range: the interval is cut there"] if low < 0 or high > 1 else []
        if held:
            notes.append(f"holds with {held}, where the optimum is not interior")
        intervals[name] = Interval(
            parameter.from_unit(max(float(low), 0.0)),
            parameter.from_unit(min(float(high), 1.0)),
            noise,
            float(bias[i]),
            "; ".join(notes) or None,
        )
    scale = np.where(deviation > 0, deviation, 1.0)
    correlation = covariance / np.outer(scale, scale)
    directions = []
    for value, vector in zip(values, vectors.T):
        spread = sigma / np.sqrt(value) if value > 0 else np.inf
        vector = vector if vector[np.argmax(np.abs(vector))] > 0 else -vector
        directions.append(Direction(dict(zip(fit.names, vector.round(4).tolist())), float(spread), bool(spread > WEAK)))
    return Uncertainty(sigma, covariance, intervals, correlation, directions, bias, level)


def _in_box(centre: np.ndarray, root: np.ndarray, start: np.ndarray, level: float, seed: int) -> np.ndarray:
    """The (1 − level)/2 and (1 + level)/2 quantiles (2 × p) of each marginal of N(centre,
    root rootᵀ) cut to the unit box: from plain draws, kept when in the box (batches of 20,000,
    until 4,000 are in it); when the box holds too little of the Gaussian for that (its centre
    far outside, beyond a bound an estimate stopped at), from a Gibbs sampler started at
    ``start`` (in the box): 100 chains, each coordinate drawn in turn from its conditional
    normal cut to [0, 1], 100 sweeps to forget the start and 100 kept."""
    rng = np.random.default_rng(seed)
    p = len(centre)
    kept: list[np.ndarray] = []
    for _ in range(10):
        draws = centre + rng.standard_normal((20_000, p)) @ root.T
        kept.append(draws[np.all((draws >= 0.0) & (draws <= 1.0), axis=1)])
        if sum(len(k) for k in kept) >= 4000:
            return np.quantile(np.vstack(kept), [(1 - level) / 2, (1 + level) / 2], axis=0)
    precision = np.linalg.inv(root @ root.T)
    chains = np.tile(np.clip(start, 0.0, 1.0), (100, 1))
    sampled = []
    for sweep in range(200):
        for i in range(p):
            others = np.delete(np.arange(p), i)
            spread = 1.0 / np.sqrt(precision[i, i])
            mean = centre[i] - (chains[:, others] - centre[others]) @ precision[i, others] / precision[i, i]
            low, high = (0.0 - mean) / spread, (1.0 - mean) / spread
            chains[:, i] = mean + spread * truncnorm.rvs(low, high, random_state=rng)
        if sweep >= 100:
            sampled.append(chains.copy())
    return np.quantile(np.vstack(sampled), [(1 - level) / 2, (1 + level) / 2], axis=0)


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
