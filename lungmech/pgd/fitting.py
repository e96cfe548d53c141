"""The a posteriori PGD's fit: separated terms closest to sampled solutions, in least squares.

The data are a solution's coordinates c(μₛ, tᵢ) ∈ ℝʳ at N sampled points μₛ of the box (unit
coordinates sₛ, weights wₛ summing to 1) and nt output times tᵢ of the load path — coordinates
in an orthonormal basis, so that the Euclidean norm is the solution's (the energy norm, for
the POD coordinates of :mod:`lungmech.pgd.fitted`). The fit is

    c(μ, tᵢ) ≈ Σₖ aₖ qₖ(μ) τₖ(tᵢ),   qₖ(μ) = Πⱼ λₖʲ(μⱼ),

each λₖʲ a cubic spline on axis j (:mod:`lungmech.pgd.axes`) and τₖ a value per output time,
minimising J = Σₛ wₛ Σᵢ ‖c(μₛ, tᵢ) − Σₖ aₖ qₖ(μₛ) τₖ(tᵢ)‖². Each factor enters J
quadratically with the others fixed, so the PGD's greedy is alternating least squares:

- **a new term** a q τ against the residual of the terms so far, each of a, λʲ (one axis at a
  time) and τ in turn its least-squares answer, the others fixed, until the term changes by
  less than ``fixed_point`` of itself (from a start of splines ≈ 1, the same on every rank);
- **an update of all terms** after each new one, pass after pass until one gains little: all
  aₖ at once, then every term's splines on each axis at once, then all τₖ.

The splines' roughness ∫ λ'' ² ds is penalised slightly (:data:`SMOOTHING`), so that a spline
cannot spike where samples are few. The greedy stops when J falls below ``tolerance``² of the
data's, or at ``max_terms``. How many terms to keep, and on how many intervals, is not read
from the training's error, which falls with every coefficient: a spline fitted through too few
samples oscillates between them. So :func:`fit` trains first on all but a held-out quarter of
the samples, for each choice of axes, measures the fit of each number of terms on the held-out
ones, keeps the (axes, terms) whose error there is smallest (of those within 10 % of it, the
fewest numbers), and fits again on every sample.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from lungmech.errors import ParameterError
from lungmech.pgd.axes import Axis
from lungmech.pgd.greedy import Options

__all__ = ["FIT", "Fit", "Separated", "fit", "roughness", "separated_fit"]

HELD_OUT = 4  # every HELD_OUT-th sample (in a seeded order) is held out to choose the rank
SLACK = 1.1  # the fewest terms whose held-out error is within this factor of the smallest
STALL = 1e-3  # the update stops when a pass lowers the error by less than this fraction of it
SMOOTHING = 1e-6  # the splines' roughness penalty ε, relative to the samples' share of the system
CUTOFF = 1e-12  # a normal system's eigenvalues below this fraction of its largest: directions the samples leave free


FIT = Options(max_terms=40, tolerance=1e-6, fixed_point=1e-6, iterations=50, sweeps=100)
"""The fit's defaults: ``sweeps`` bounds the update's passes after each new term, which stop
sooner when a pass gains little (:data:`STALL`)."""


@dataclass(frozen=True)
class Separated:
    """Σₖ aₖ qₖ(μ) τₖ(tᵢ): ``amplitudes`` a (r × n), ``coefficients[j]`` the splines on axis
    j (n × its size), ``timeline`` τ (n × nt)."""

    amplitudes: np.ndarray
    coefficients: list[np.ndarray]
    timeline: np.ndarray

    @property
    def terms(self) -> int:
        return self.amplitudes.shape[1]

    def at(self, bases: Sequence[np.ndarray]) -> np.ndarray:
        """The fit at the points whose splines' values per axis are ``bases`` (points × size):
        r × points × nt."""
        q = _products(bases, self.coefficients, self.terms, len(bases[0]) if bases else 1)
        return np.tensordot(self.amplitudes, q.T[:, :, None] * self.timeline[:, None, :], axes=(1, 0))


@dataclass(frozen=True)
class Fit:
    """A :func:`fit`: the ``separated`` terms on every sample, on the chosen ``axes``; the
    held-out error (relative, the largest over the held-out samples of ‖error‖/‖c‖ along their
    path) against the number of terms, ``held_out[n - 1]`` with n terms trained on the other
    samples, for the chosen axes and (``curves``) for every choice of axes, by their intervals;
    the ``training`` error (relative, all samples) against the number of terms of the final
    fit."""

    separated: Separated
    axes: tuple[Axis, ...]
    held_out: list[float]
    curves: dict[str, list[float]]
    training: list[float]


def fit(
    data: np.ndarray, units: np.ndarray, choices: Sequence[Sequence[Axis]], options: Options = FIT, seed: int = 0
) -> Fit:
    """The separated fit of ``data`` (r × N × nt) at the samples of unit coordinates ``units``
    (N × axes) on one of the ``choices`` of axes (the parameters' axes at some intervals,
    fewest coefficients first), which and how many terms chosen on held-out samples (module
    docstring): the smallest held-out error, or the fewest coefficients within 10 % of it.
    Every rank given the same data finds the same fit."""
    data = np.asarray(data, dtype=float)
    units = np.atleast_2d(np.asarray(units, dtype=float))
    if not choices:
        raise ParameterError("PGD fit: give at least one choice of axes")
    for axes in choices:
        if data.ndim != 3 or units.shape != (data.shape[1], len(axes)):
            raise ParameterError(
                f"PGD fit: data {data.shape} and units {units.shape} for {len(axes)} axes do not agree"
            )
    count = data.shape[1]
    if count < 2 * HELD_OUT:
        raise ParameterError(f"PGD fit: at least {2 * HELD_OUT} samples are needed to hold some out (got {count})")
    if not np.any(data):  # nothing moves (an imaged body that rests as imaged: ξ = 0): no term
        axes = tuple(choices[0])
        empty = Separated(
            np.zeros((data.shape[0], 0)), [np.zeros((0, a.size)) for a in axes], np.zeros((0, data.shape[2]))
        )
        return Fit(empty, axes, [0.0], {_named(axes): [0.0]}, [0.0])
    order = np.random.default_rng(seed).permutation(count)
    held = np.sort(order[::HELD_OUT])
    kept = np.setdiff1d(np.arange(count), held)
    curves: dict[str, list[float]] = {}
    trials = []  # (held-out error, coefficients, the axes, terms)
    for axes in choices:
        bases = [axis.at(units[:, j]) for j, axis in enumerate(axes)]
        checked = [B[held] for B in bases]
        curve: list[float] = []  # the fit of n terms (not the first n of more: the update moves them all)
        rough = [roughness(axis) for axis in axes]
        separated_fit(
            data[:, kept],
            [B[kept] for B in bases],
            options,
            rough,
            lambda found, c=checked, k=curve: k.append(_worst(data[:, held], found.at(c))),  # type: ignore[misc]
        )
        curves[_named(axes)] = curve
        size = sum(axis.size for axis in axes) + data.shape[0] + data.shape[2]  # a term's numbers
        trials += [(error, n * size, tuple(axes), n) for n, error in enumerate(curve, 1)]
    best = min(error for error, *_ in trials)
    _, _, axes, terms = min((t for t in trials if t[0] <= SLACK * best), key=lambda t: (t[1], t[0]))
    bases = [axis.at(units[:, j]) for j, axis in enumerate(axes)]
    rough = [roughness(axis) for axis in axes]
    final, training = separated_fit(data, bases, replace(options, max_terms=terms), rough)
    return Fit(final, axes, curves[_named(axes)], curves, training)


def _named(axes: Sequence[Axis]) -> str:
    """A choice of axes by their intervals, "2,2,4"."""
    return ",".join(str(axis.intervals) for axis in axes)


def roughness(axis: Axis) -> np.ndarray:
    """P = ∫₀¹ B''(s)ᵀ B''(s) ds, the splines' roughness λᵀ P λ = ∫ λ''² ds (the axis's rule is
    exact for it)."""
    curvature = axis.at(axis.nodes, 2)
    return curvature.T @ (axis.weights[:, None] * curvature)


def separated_fit(
    data: np.ndarray,
    bases: Sequence[np.ndarray],
    options: Options,
    roughness: Sequence[np.ndarray] | None = None,
    each: Callable[[Separated], None] | None = None,
) -> tuple[Separated, list[float]]:
    """The greedy fit of ``data`` (r × N × nt) at the points whose splines' values per axis are
    ``bases`` (N × size): the terms and the relative error after each; ``each`` sees the fit
    after each new term and its update. ``roughness``: each axis's penalty matrix
    (:func:`roughness`; default none). Each sample weighs
    wₛ ∝ 1/‖c(μₛ)‖² (its path's), so that J is the mean square of the samples' relative
    errors, the measure the rank is chosen by, and a stiff corner of the box, whose
    displacements are small, is fitted as well as a soft one."""
    r, count, times = data.shape
    roughness = roughness if roughness is not None else [np.zeros((B.shape[1],) * 2) for B in bases]
    size = np.einsum("rsi,rsi->s", data, data)
    w = np.where(size > 0, 1.0 / np.where(size > 0, size, 1.0), 0.0)
    w /= max(float(w.sum()), 1e-300)
    total = float(np.einsum("s,rsi,rsi->", w, data, data))
    found = Separated(np.zeros((r, 0)), [np.zeros((0, B.shape[1])) for B in bases], np.zeros((0, times)))
    errors: list[float] = []
    if total == 0.0:
        return found, errors
    while found.terms < options.max_terms:
        residual = data - found.at(bases) if found.terms else data
        a, x, tau = _new_term(residual, bases, roughness, w, options, seed=found.terms)
        found = Separated(
            np.column_stack([found.amplitudes, a]),
            [np.vstack([X, xj]) for X, xj in zip(found.coefficients, x)],
            np.vstack([found.timeline, tau]),
        )
        error = _error(data, bases, w, found, total)
        for _ in range(options.sweeps):  # until a pass gains less than STALL of the error
            found = _update(data, bases, roughness, w, found)
            error, before = _error(data, bases, w, found, total), error
            if before - error <= STALL * error:
                break
        errors.append(error)
        if each is not None:
            each(found)
        if errors[-1] <= options.tolerance:
            break
    return found, errors


def _error(data: np.ndarray, bases: Sequence[np.ndarray], w: np.ndarray, found: Separated, total: float) -> float:
    """√(J / the data's J): the fit's relative least-squares error."""
    error = data - found.at(bases)
    return float(np.sqrt(np.einsum("s,rsi,rsi->", w, error, error) / total))


def _products(bases: Sequence[np.ndarray], coefficients: Sequence[np.ndarray], terms: int, count: int) -> np.ndarray:
    """qₖ(μₛ) = Πⱼ λₖʲ(μₛⱼ) (N × n)."""
    q = np.ones((count, terms))
    for B, X in zip(bases, coefficients):
        q = q * (B @ X.T)
    return q


def _new_term(
    residual: np.ndarray,
    bases: Sequence[np.ndarray],
    roughness: Sequence[np.ndarray],
    w: np.ndarray,
    options: Options,
    seed: int,
) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """One term a q τ against ``residual`` by alternating least squares."""
    rng = np.random.default_rng(seed)
    x: list[np.ndarray] = [
        np.asarray(rng.uniform(0.9, 1.1, B.shape[1])) for B in bases
    ]  # splines ≈ 1: a start every term sees
    lam = [B @ xj for B, xj in zip(bases, x)]
    tau = np.ones(residual.shape[2])
    before = None
    for _ in range(options.iterations):
        q = np.prod(lam, axis=0) if lam else np.ones(residual.shape[1])
        a = np.einsum("rsi,s,s,i->r", residual, w, q, tau) / max(float(w @ q**2) * float(tau @ tau), 1e-300)
        projected = np.einsum("r,rsi->si", a, residual)  # aᵀ c(μₛ, tᵢ)
        aa = float(a @ a)
        for j, B in enumerate(bases):
            others = np.prod([l for i, l in enumerate(lam) if i != j], axis=0) if len(lam) > 1 else 1.0
            M = aa * float(tau @ tau) * (B.T @ ((w * others**2)[:, None] * B))
            rhs = B.T @ (w * others * (projected @ tau))
            x[j] = _solve(_smoothed(M, roughness[j]), rhs)
            lam[j] = B @ x[j]
            scale = np.sqrt(float(w @ lam[j] ** 2))  # unit mean square: the amplitude is a's
            if scale > 0:
                x[j], lam[j] = x[j] / scale, lam[j] / scale
        q = np.prod(lam, axis=0) if lam else np.ones(residual.shape[1])
        tau = (projected.T @ (w * q)) / max(aa * float(w @ q**2), 1e-300)
        size = float(np.linalg.norm(tau))
        if size == 0.0:
            break
        tau = tau / size
        term = (a * size, q, tau)
        if before is not None and _change(before, term, w) <= options.fixed_point:
            break
        before = term
    q = np.prod(lam, axis=0) if lam else np.ones(residual.shape[1])
    a = np.einsum("rsi,s,s,i->r", residual, w, q, tau) / max(float(w @ q**2) * float(tau @ tau), 1e-300)
    return a, x, tau


def _change(before: tuple, now: tuple, w: np.ndarray) -> float:
    """‖t − t'‖ / ‖t'‖ of two rank-one terms t = a q τ (the fit's weighted norm)."""

    def product(one: tuple, other: tuple) -> float:
        return float(one[0] @ other[0]) * float(w @ (one[1] * other[1])) * float(one[2] @ other[2])

    new = product(now, now)
    return float(np.sqrt(max(product(before, before) + new - 2 * product(before, now), 0.0) / new)) if new else 0.0


def _update(
    data: np.ndarray, bases: Sequence[np.ndarray], roughness: Sequence[np.ndarray], w: np.ndarray, found: Separated
) -> Separated:
    """One pass updating every term: the amplitudes, each axis's splines, the timeline."""
    A, X, T = found.amplitudes, [X.copy() for X in found.coefficients], found.timeline
    n = found.terms
    q = _products(bases, X, n, data.shape[1])
    # amplitudes: Σₛᵢ wₛ (qₖ τₖ)(qₗ τₗ) aₗ = Σₛᵢ wₛ c qₖ τₖ
    TT = T @ T.T
    rhs = np.einsum("rsi,ki->rsk", data, T)  # Σᵢ c τₖ
    A = _solve((q.T @ (w[:, None] * q)) * TT, np.einsum("rsk,sk->kr", rhs, w[:, None] * q)).T
    AA = A.T @ A
    projected = np.tensordot(A, data, axes=(0, 0))  # aₖᵀ c(μₛ, tᵢ): n × N × nt
    h = np.einsum("ksi,ki->sk", projected, T)  # Σᵢ τₖᵢ aₖᵀ c
    for j, B in enumerate(bases):
        others = _products(
            [b for i, b in enumerate(bases) if i != j], [x for i, x in enumerate(X) if i != j], n, len(B)
        )
        # Σₛ wₛ (aₖᵀ aₗ)(τₖ·τₗ) gₖ(s) gₗ(s) Bₛᵀ Bₛ xₗ = Σₛ wₛ gₖ(s) hₖ(s) Bₛᵀ
        g = w[:, None] * others
        coupling = (g[:, :, None] * others[:, None, :]) * (AA * TT)[None]  # N × n × n
        outer = B[:, :, None] * B[:, None, :]  # N × size × size
        size = B.shape[1]
        M = np.tensordot(coupling, outer, axes=(0, 0)).transpose(0, 2, 1, 3).reshape(n * size, n * size)
        X[j] = _solve(_smoothed(M, np.kron(np.eye(n), roughness[j])), ((g * h).T @ B).reshape(n * size)).reshape(
            n, size
        )
    q = _products(bases, X, n, data.shape[1])
    # timeline: per output time, Σₛ wₛ (aₖᵀ aₗ) qₖ qₗ τₗᵢ = Σₛ wₛ qₖ aₖᵀ cᵢ
    T = _solve((q.T @ (w[:, None] * q)) * AA, np.einsum("ksi,sk->ki", projected, w[:, None] * q))
    return _normalised(Separated(A, X, T), bases, w)


def _normalised(found: Separated, bases: Sequence[np.ndarray], w: np.ndarray) -> Separated:
    """Each term's splines of unit mean square over the samples and its timeline of unit norm,
    their scale in its amplitude (the same terms)."""
    A, X, T = found.amplitudes.copy(), [X.copy() for X in found.coefficients], found.timeline.copy()
    for j, B in enumerate(bases):
        scale = np.sqrt(w @ (B @ X[j].T) ** 2)
        scale[scale == 0] = 1.0
        X[j] /= scale[:, None]
        A *= scale[None, :]
    scale = np.linalg.norm(T, axis=1)
    scale[scale == 0] = 1.0
    return Separated(A * scale[None, :], X, T / scale[:, None])


def _smoothed(M: np.ndarray, roughness: np.ndarray) -> np.ndarray:
    """M + ε (tr M / tr P) P: the spline system with its roughness ∫ λ''² ds penalised."""
    scale = float(np.trace(roughness))
    return M + SMOOTHING * float(np.trace(M)) / scale * roughness if scale > 0 else M


def _solve(M: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """M x = rhs for a symmetric positive semi-definite normal matrix M, without the directions
    whose eigenvalue is below :data:`CUTOFF` of the largest: where the samples leave a spline
    coefficient free, or two terms nearly alike would otherwise grow without bound and cancel."""
    values, vectors = np.linalg.eigh(M)
    kept = values > CUTOFF * max(float(values[-1]), 0.0) if values.size else values.astype(bool)
    if not kept.any():
        return np.zeros(rhs.shape)
    return vectors[:, kept] @ ((vectors[:, kept].T @ rhs) / (values[kept] if rhs.ndim == 1 else values[kept, None]))


def _worst(data: np.ndarray, fitted: np.ndarray) -> float:
    """The largest relative error over the samples, each along its path (r × N × nt)."""
    error = np.sqrt(np.einsum("rsi,rsi->s", data - fitted, data - fitted))
    size = np.sqrt(np.einsum("rsi,rsi->s", data, data))
    return float(np.max(error / np.maximum(size, 1e-300)))
