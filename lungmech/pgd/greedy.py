"""The a priori PGD of a separated linear problem: its terms, greedily, with no snapshot.

The problem is the Galerkin one over space and the box B together: find u(x, μ) with

    ∫_B ⟨R(u(μ); μ), δu(μ)⟩ dμ = 0   for every δu,   R(u; μ) = Σ_T κ_T(μ) K_T u − Σ_S φ_S(μ) f_S

(:mod:`lungmech.pgd.terms`; for a symmetric K, the minimum of the potential integrated over
B). Every integral over B is a product of integrals over the axes, so no point of the box is
ever solved for. The answer is kept as u(μ) = Q R q(μ), qₖ(μ) = Πⱼ λₖʲ(μⱼ): Q the space modes,
orthonormal in the energy inner product W, and the k-th separated term's space part Q Rₖ (its
coefficients folded into R). A new term ū Πⱼ λʲ is found by alternating directions, the others
fixed:

- **space**: (Σ_T α_T K_T) ū = Σ_S β_S f_S − Σ_T K_T U γ_T, U = Q R, with α_T = Πⱼ ⟨κ_Tʲ λʲ, λʲ⟩,
  β_S = Πⱼ ⟨φ_Sʲ, λʲ⟩, γ_Tₖ = Πⱼ ⟨κ_Tʲ λʲ, λₖʲ⟩ (⟨·,·⟩ the axis's mean);
- **axis j**: the Galerkin equations of λʲ on its splines, ū and the other axes fixed,

until ū Πⱼ λʲ changes by less than ``fixed_point`` of itself (from a random start, the same on
every rank). Its part outside span Q becomes a new space mode; a term (nearly) in the span
adds none, only its coefficients. Then **every term is updated**, ``sweeps`` times: all
terms' space coefficients R at once (a Galerkin system of terms × modes), then for each axis
all terms' splines at once (terms × the axis's size). The greedy stops when a new term's
amplitude ‖ū Πⱼ λʲ‖ (W, and the box's mean square) falls below ``tolerance`` of the whole's,
or at ``max_terms``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np

from lungmech import checks
from lungmech.parallel.linalg import apply, gram, norms
from lungmech.pgd.axes import Axis
from lungmech.pgd.decomposition import Decomposition
from lungmech.pgd.modes import Modes, combined_solve, kron_sum, rms, solve_small
from lungmech.pgd.terms import Terms

__all__ = ["Options", "Round", "change", "pgd"]


@dataclass(frozen=True)
class Options:
    """``max_terms``: the separated terms at most; ``tolerance``: a new term's amplitude,
    relative to the whole's, at which the greedy stops; ``fixed_point``: the alternating
    directions' relative change at which a term has converged (at most ``iterations``);
    ``sweeps``: the update's passes after each new term."""

    max_terms: int = 20
    tolerance: float = 1e-6
    fixed_point: float = 1e-5
    iterations: int = 30
    sweeps: int = 5

    def __post_init__(self) -> None:
        checks.integer("PGD max_terms", self.max_terms, minimum=1)
        checks.real("PGD tolerance", self.tolerance, positive=True)
        checks.real("PGD fixed_point", self.fixed_point, positive=True)
        checks.integer("PGD iterations", self.iterations, minimum=1)
        checks.integer("PGD sweeps", self.sweeps, minimum=0)


@dataclass(frozen=True)
class Round:
    """One enrichment: the new term's ``amplitude`` relative to the whole's, its alternating
    directions' ``iterations`` and whether they ``converged``, whether it was ``added`` (not
    below the tolerance) and added a space mode (``new_mode``), and after the update the
    box-integrated potential ``potential`` (J: the mean of ½ ⟨K u, u⟩ − ⟨f, u⟩; meaningful
    for a symmetric K)."""

    amplitude: float
    iterations: int
    converged: bool
    added: bool
    new_mode: bool
    potential: float


def pgd(terms: Terms, W: PETSc.Mat, options: Options = Options()) -> tuple[Decomposition, list[Round]]:
    """The PGD of ``terms`` (module docstring), its space modes orthonormal in ``W``: the
    decomposition and one :class:`Round` per enrichment tried. Collective."""
    found = Modes(terms.axes, [t.matrix for t in terms.operator], len(terms.load[0].vector), terms.comm)
    rounds: list[Round] = []
    while found.count < options.max_terms:
        u, x, iterations, converged = _new_term(terms, found, options)
        amplitude = float(norms(u[:, None], W, terms.comm)[0]) * float(
            np.prod([rms(a, xj) for a, xj in zip(terms.axes, x)])
        )
        whole = float(np.sqrt(_mean_square(found) + amplitude**2))
        if amplitude <= options.tolerance * whole or whole == 0.0:
            rounds.append(
                Round(
                    amplitude / whole if whole else 0.0, iterations, converged, False, False, _potential(terms, found)
                )
            )
            break
        new = found.add(u, x, W)
        for _ in range(options.sweeps):
            found.R = _update_space(terms, found)
            for j in range(len(terms.axes)):
                found.X[j] = _update_axis(terms, found, j)
        rounds.append(Round(amplitude / whole, iterations, converged, True, new, _potential(terms, found)))
    return found.decomposition(), rounds


def _new_term(problem: Terms, found: Modes, options: Options) -> tuple[np.ndarray, list[np.ndarray], int, bool]:
    """(ū, its splines per axis, iterations, converged): alternating directions for one term,
    the others fixed."""
    comm = found.comm
    axes = problem.axes
    old = found.values()
    KU = np.hstack([KQ @ found.R for KQ in found.KQ])  # K_T U, U = Q R, side by side (owned × terms·n)
    # a random start (the same on every rank): from λʲ = 1, a load whose factor has mean 0
    # over an axis (the sine of a roll over ±30°) would be missed by every iteration
    rng = np.random.default_rng(found.count)
    x = [rng.uniform(0.5, 1.5, axis.size) for axis in axes]
    before = None
    for iteration in range(1, options.iterations + 1):
        lam = [axis.basis @ xj for axis, xj in zip(axes, x)]
        u = _space(problem, KU, lam, old)
        uKU = gram(u[:, None], KU, comm)[0].reshape(len(problem.operator), found.count)  # ūᵀ K_T Uₖ
        Ku = np.column_stack([apply(t.matrix, u[:, None], comm)[:, 0] for t in problem.operator])
        uKu = gram(u[:, None], Ku, comm)[0]
        uf = gram(u[:, None], problem.loads, comm)[0]
        for j, axis in enumerate(axes):
            x[j] = _axis(problem, j, lam, old, uKu, uKU, uf)
            if j < len(axes) - 1:  # unit mean square: the amplitude is the space part's and the last axis's
                x[j] /= max(rms(axis, x[j]), 1e-300)
            lam[j] = axis.basis @ x[j]
        now = (u, [xj.copy() for xj in x])
        if before is not None and change(axes, comm, before, now) <= options.fixed_point:
            return u, x, iteration, True
        before = now
    return u, x, options.iterations, False


def _means(
    axes: Sequence[Axis], factors: Sequence[np.ndarray], lam: Sequence[np.ndarray], skip: int | None = None
) -> np.ndarray:
    """Πⱼ ⟨κ_Tʲ, λʲ⟩ for every term T (``factors[j]``: terms × axis j's nodes; ``lam[j]`` any
    function at the nodes), over the axes but ``skip``."""
    found = np.ones(len(factors[0]))
    for j, (axis, k, l) in enumerate(zip(axes, factors, lam)):
        if j != skip:
            found = found * (k @ (axis.weights * l))
    return found


def _crossed(
    axes: Sequence[Axis],
    factors: Sequence[np.ndarray],
    lam: Sequence[np.ndarray],
    old: Sequence[np.ndarray],
    skip: int | None = None,
) -> np.ndarray:
    """Πⱼ ⟨κ_Tʲ λʲ, λₖʲ⟩ for every term T and old term k (terms × k), over the axes but ``skip``."""
    found = np.ones((len(factors[0]), len(old[0])))
    for j, (axis, k, l, o) in enumerate(zip(axes, factors, lam, old)):
        if j != skip:
            found = found * ((k * (axis.weights * l)) @ o.T)
    return found


def _space(problem: Terms, KU: np.ndarray, lam: list[np.ndarray], old: list[np.ndarray]) -> np.ndarray:
    """The space step: (Σ_T α_T K_T) ū = Σ_S β_S f_S − Σ_T K_T U γ_T."""
    axes, F = problem.axes, problem.operator_factors
    alpha = _means(axes, F, [l * l for l in lam])
    rhs = problem.loads @ _means(axes, problem.load_factors, lam)
    if KU.shape[1]:
        rhs -= KU @ _crossed(axes, F, lam, old).ravel()
    return combined_solve([term.matrix for term in problem.operator], alpha, rhs)


def _axis(
    problem: Terms,
    j: int,
    lam: list[np.ndarray],
    old: list[np.ndarray],
    uKu: np.ndarray,
    uKU: np.ndarray,
    uf: np.ndarray,
) -> np.ndarray:
    """Axis j's step: the Galerkin equations of λʲ's splines, ū and the other axes fixed."""
    axes, F, G = problem.axes, problem.operator_factors, problem.load_factors
    B, w = axes[j].basis, axes[j].weights
    a = uKu * _means(axes, F, [l * l for l in lam], skip=j)
    M = B.T @ ((w * (a @ F[j]))[:, None] * B)
    c = uKU * _crossed(axes, F, lam, old, skip=j)  # terms × old terms
    r = B.T @ (w * ((uf * _means(axes, G, lam, skip=j)) @ G[j] - np.sum(F[j] * (c @ old[j]), axis=0)))
    return np.linalg.solve(M, r)


def _products(
    found: Modes, factors: tuple[np.ndarray, ...], lam: list[np.ndarray], skip: int | None = None
) -> np.ndarray:
    """P[k, l] = Πⱼ ⟨κʲ λₖʲ, λₗʲ⟩ over the axes (but ``skip``), for the factors κʲ of one term."""
    P = np.ones((found.count, found.count))
    for j, (axis, k, l) in enumerate(zip(found.axes, factors, lam)):
        if j != skip:
            P = P * ((l * (axis.weights * k)) @ l.T)
    return P


def _loads(found: Modes, factors: tuple[np.ndarray, ...], lam: list[np.ndarray], skip: int | None = None) -> np.ndarray:
    """p[k] = Πⱼ ⟨φʲ, λₖʲ⟩ over the axes (but ``skip``), for the factors φʲ of one load."""
    p = np.ones(found.count)
    for j, (axis, f, l) in enumerate(zip(found.axes, factors, lam)):
        if j != skip:
            p = p * (l @ (axis.weights * f))
    return p


def _update_space(problem: Terms, found: Modes) -> np.ndarray:
    """Every term's space coefficients R at once, the splines fixed:
    Σ_T Σₗ P_T[k, l] (Qᵀ K_T Q) Rₗ = Σ_S p_S[k] Qᵀ f_S for each term k (m × n)."""
    lam, m, n = found.values(), found.Q.shape[1], found.count
    M = kron_sum([_products(found, term.factors, lam) for term in problem.operator], found.reduced_operators())
    rhs = np.zeros(n * m)
    for load, F in zip(problem.load, _reduced_loads(problem, found)):
        rhs += np.kron(_loads(found, load.factors, lam), F)
    return solve_small(M, rhs, problem.symmetric).reshape(n, m).T


def _update_axis(problem: Terms, found: Modes, j: int) -> np.ndarray:
    """Every term's splines on axis j at once (n × size), R and the other axes fixed:
    Σ_T Σₗ (Rₖᵀ Qᵀ K_T Q Rₗ) Π_{i≠j} ⟨κ_Tⁱ λₖⁱ, λₗⁱ⟩ M_Tʲ xₗ = Σ_S (Rₖᵀ Qᵀ f_S) Π_{i≠j} ⟨φ_Sⁱ, λₖⁱ⟩ m_Sʲ."""
    axis, lam, R = found.axes[j], found.values(), found.R
    B, w = axis.basis, axis.weights
    M = kron_sum(
        [
            (R.T @ A @ R) * _products(found, t.factors, lam, skip=j)
            for t, A in zip(problem.operator, found.reduced_operators())
        ],
        [B.T @ ((w * t.factors[j])[:, None] * B) for t in problem.operator],
    )
    rhs = np.zeros(found.count * axis.size)
    for load, F in zip(problem.load, _reduced_loads(problem, found)):
        g = (R.T @ F) * _loads(found, load.factors, lam, skip=j)
        rhs += np.kron(g, B.T @ (w * load.factors[j]))
    return solve_small(M, rhs, problem.symmetric).reshape(found.count, axis.size)


def change(axes: Sequence[Axis], comm: MPI.Comm, before: tuple, now: tuple) -> float:
    """‖a − b‖ / ‖b‖ of two rank-one terms a = ū Πⱼ λʲ (l² in space, the axes' means)."""
    (ua, xa), (ub, xb) = before, now

    def product(u: np.ndarray, x: list, v: np.ndarray, y: list) -> float:
        space = float(gram(u[:, None], v[:, None], comm)[0, 0])
        return space * float(np.prod([a.weights @ ((a.basis @ p) * (a.basis @ q)) for a, p, q in zip(axes, x, y)]))

    aa, bb, ab = product(ua, xa, ua, xa), product(ub, xb, ub, xb), product(ua, xa, ub, xb)
    return float(np.sqrt(max(aa + bb - 2 * ab, 0.0) / bb)) if bb > 0 else 0.0


def _reduced_loads(problem: Terms, found: Modes) -> np.ndarray:
    """Qᵀ f_S, one row per load term."""
    return found.reduced(np.column_stack([load.vector for load in problem.load])).T


def _mean_square(found: Modes) -> float:
    """The box's mean of ‖Q R q(μ)‖²_W = Σₖₗ (Rₖᵀ Rₗ) Πⱼ ⟨λₖʲ, λₗʲ⟩."""
    if not found.count:
        return 0.0
    ones = tuple(np.ones(len(axis.nodes)) for axis in found.axes)
    return float(np.sum((found.R.T @ found.R) * _products(found, ones, found.values())))


def _potential(problem: Terms, found: Modes) -> float:
    """The box's mean of ½ ⟨K u, u⟩ − ⟨f, u⟩ of the terms so far."""
    if not found.count:
        return 0.0
    lam, R = found.values(), found.R
    total = 0.0
    for term, A in zip(problem.operator, found.reduced_operators()):
        total += 0.5 * float(np.sum((R.T @ A @ R) * _products(found, term.factors, lam)))
    for load, F in zip(problem.load, _reduced_loads(problem, found)):
        total -= float((R.T @ F) @ _loads(found, load.factors, lam))
    return total
