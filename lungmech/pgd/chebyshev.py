"""A value the residual is not affine in — the position s of a stiffness jump, inside
χ = ½(1 − tanh((n·x − s)/w)) — as a Chebyshev series in the one parameter that moves it.

An operator K(σ), σ ∈ [0, 1] that parameter's unit coordinate, is assembled at the P
Chebyshev–Lobatto points σₚ = ½(1 − cos(π p / (P − 1))) and written as the series of its
interpolant,

    K(σ) ≈ Σₖ Tₖ(2σ − 1) Aₖ,   Aₖ = Σₚ Cₖₚ K(σₚ)   (k < P),

C the inverse of the Chebyshev–Vandermonde matrix at the points. A smooth K(σ) has
coefficients that fall geometrically: the last ones measure the interpolant's error
(:func:`tail`), and those below a tolerance are dropped. Each Tₖ is a polynomial known, with
its derivative, at every σ — not only at the PGD's quadrature nodes — so an answer's strain
energy and its derivatives in μ come from the same series. The points are nested (P = 2ⁱ + 1),
so refining keeps every assembly already made.

Several such parameters (a population's shape coefficients: the map's det G and G⁻¹ are rational
in each) give the tensor product: K(σ₁, …, σ_d) ≈ Σ_k Π_i T_{k_i}(2σ_i − 1) A_k over the
multi-indices k, their coefficients those of the interpolant on the points' tensor grid, one
axis after the other (:func:`coefficients` with ``axis``); :func:`tensor` gives the products at
a point, flattened in C order (the last parameter's k fastest).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.polynomial import chebyshev

__all__ = ["coefficients", "lobatto", "polynomials", "tail", "tensor"]


def lobatto(points: int) -> np.ndarray:
    """σₚ, the ``points`` Chebyshev–Lobatto points of [0, 1], from 0 to 1."""
    return 0.5 * (1.0 - np.cos(np.pi * np.arange(points) / (points - 1)))


def coefficients(samples: np.ndarray, axis: int = 0) -> np.ndarray:
    """The Chebyshev coefficients of the interpolant through ``samples`` along ``axis`` (its
    values at :func:`lobatto` (P) there): C applied along that axis, the shape kept."""
    points = samples.shape[axis]
    vandermonde = chebyshev.chebvander(2.0 * lobatto(points) - 1.0, points - 1)  # well conditioned here
    return np.moveaxis(np.tensordot(np.linalg.inv(vandermonde), np.moveaxis(samples, axis, 0), axes=1), 0, axis)


def polynomials(sigma: float | np.ndarray, count: int, derivative: int = 0) -> np.ndarray:
    """Tₖ(2σ − 1), k < ``count`` (or their ``derivative``-th derivative in σ), at each
    ``sigma``: len(σ) × count."""
    if not derivative and isinstance(sigma, float):  # one σ, an answer's: Tₖ(cos θ) = cos kθ, one array call
        return np.cos(math.acos(min(max(2.0 * sigma - 1.0, -1.0), 1.0)) * np.arange(count))[None, :]
    x = 2.0 * np.atleast_1d(np.asarray(sigma, dtype=float)) - 1.0
    if not derivative:  # Tₖ(cos θ) = cos kθ: two array calls, an answer's microseconds (a recurrence's loop took 35)
        return np.cos(np.outer(np.arccos(np.clip(x, -1.0, 1.0)), np.arange(count)))
    slopes = chebyshev.chebder(np.eye(count), derivative, scl=2.0, axis=0)  # d/dσ = 2 d/dx
    return chebyshev.chebval(x, slopes).T if len(slopes) else np.zeros((len(x), count))


def tail(sizes: np.ndarray) -> float:
    """The interpolant's relative error, estimated by its last two coefficients' ``sizes``
    (norms, in order of k) against the largest."""
    largest = float(np.max(sizes))
    return float(np.max(sizes[-2:])) / largest if largest > 0 else 0.0


def tensor(sigmas: Sequence[float], counts: Sequence[int], along: int | None = None) -> np.ndarray:
    """Π_i T_{k_i}(2σ_i − 1) for every multi-index k < ``counts`` (C order, flattened), or its
    derivative in σ of parameter number ``along``; one 1 for no parameter."""
    found = None
    for i, (sigma, count) in enumerate(zip(sigmas, counts)):
        factor = polynomials(float(sigma), count, int(i == along))[0]
        found = factor if found is None else np.multiply.outer(found, factor).ravel()
    return np.ones(1) if found is None else found
