"""The PGD of a linear problem whose right-hand side is known at a sample of the box only: the
step of a nonlinear model's Newton–PGD (:mod:`lungmech.pgd.newton`).

The problem is the Galerkin one over space and the sample μ_q (weights w_q, summing to 1: the
axes' tensor Gauss rule, or equal weights at a Sobol' sample):

    Σ_q w_q ⟨K(μ_q) u(μ_q) − b_q, δu(μ_q)⟩ = 0   for every δu,   K(μ) = Σᵢ κᵢ(μ) Kᵢ,

the box's integral taken as the sample's weighted sum; K(μ) separated (:class:`Operator`), the
b_q any vectors. The answer is kept as the a priori greedy's (:class:`~lungmech.pgd.modes.Modes`:
u(μ) = Q R q(μ), Q orthonormal in W), and its steps are that greedy's (:mod:`lungmech.pgd.greedy`)
with the sample's sums where the axes' products were, Λₖ_q = qₖ(μ_q):

- **space**: (Σᵢ αᵢ Kᵢ) ū = Σ_q w_q λ_q b_q − Σᵢ Kᵢ U γᵢ, αᵢ = Σ_q w_q κᵢ_q λ_q²,
  γᵢₖ = Σ_q w_q κᵢ_q λ_q Λₖ_q;
- **axis j**: λ_q = Bʲ_q xʲ p_q (Bʲ_q the axis's splines at μ_qj, p_q the other axes' product):
  [Σ_q w_q p_q² (Σᵢ κᵢ_q ūᵀKᵢū) Bʲ_q Bʲ_qᵀ] xʲ = Σ_q w_q p_q Bʲ_q (ūᵀb_q − Σᵢ κᵢ_q ūᵀKᵢ U Λ_q);
- **update** of every term, ``sweeps`` times: R from Σᵢ Pᵢ ⊗ (QᵀKᵢQ), Pᵢ = Λ diag(w κᵢ) Λᵀ;
  then each axis's splines of every term at once.

A solve starts from the terms it is given (a Newton iteration's, so that the next needs only
its change): they are first updated for the new b, then terms are added while a new one's
amplitude is above ``tolerance`` of the whole's. An :class:`Operator` with a correction D_q on
the first m₀ modes has its updates take K(μ_q) + (W Q₀) D_q (W Q₀)ᵀ (a Newton–PGD's tangent at
each point's state on the modes' span), T_q = QᵀK(μ_q)Q + D_q on the span, and Qᵀb_q its
shift, c_q: with T_q not symmetric they minimise the sampled residual on the span,
Σ_q w_q ‖T_q z_q − c_q‖², by alternating least squares — R from Σ_q w_q Λ_q Λ_qᵀ ⊗ T_qᵀT_q,
then each axis's splines — where a Galerkin update's matrices, not symmetric, came near
singular (condition numbers of 10¹⁵) and its sweeps diverged (:func:`_least_squares_update`);
a new term then takes b plus what the
corrected updates left on that span, W Q₀ (s_q − D_q z_q).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np

from lungmech.parallel.linalg import apply, gram, norms
from lungmech.pgd.axes import Axis
from lungmech.pgd.greedy import Options, Round, change
from lungmech.pgd.modes import Modes, combined_solve, kron_sum, rms, solve_small

__all__ = ["Operator", "Sample", "solve"]

RIDGE = 1e-12  # an axis's Galerkin matrix: this fraction of its mean diagonal added (a spline no sample sees)


@dataclass(frozen=True)
class Sample:
    """The box's points μ_q as unit coordinates ``units`` (N × axes), their ``weights`` w_q
    (summing to 1) and each axis's splines there, ``bases[j]`` (N × axis j's size)."""

    axes: tuple[Axis, ...]
    units: np.ndarray
    weights: np.ndarray
    bases: tuple[np.ndarray, ...]

    @classmethod
    def of(cls, axes: Sequence[Axis], units: np.ndarray) -> Sample:
        """Equal weights at the points ``units`` (a Sobol' sample's)."""
        units = np.asarray(units, dtype=float)
        bases = tuple(axis.at(units[:, j]) for j, axis in enumerate(axes))
        return cls(tuple(axes), units, np.full(len(units), 1.0 / len(units)), bases)

    @classmethod
    def tensor(cls, axes: Sequence[Axis]) -> Sample:
        """The tensor product of the axes' Gauss rules (:mod:`lungmech.pgd.axes`): the box's
        integral of products of the splines, exact, as the a priori greedy's."""
        units = np.array(list(itertools.product(*(axis.nodes for axis in axes))))
        weights = np.array([np.prod(w) for w in itertools.product(*(axis.weights for axis in axes))])
        bases = tuple(axis.at(units[:, j]) for j, axis in enumerate(axes))
        return cls(tuple(axes), units, weights, bases)

    def values(self, found: Modes) -> list[np.ndarray]:
        """Each axis's splines of the terms at the points (terms × N)."""
        return [X @ B.T for X, B in zip(found.X, self.bases)]

    def products(self, found: Modes) -> np.ndarray:
        """Λₖ_q = qₖ(μ_q) (terms × N)."""
        return np.multiply.reduce(self.values(found), axis=0) if self.axes else np.ones((found.count, 1))


@dataclass(frozen=True)
class Operator:
    """K(μ_q) = Σᵢ κᵢ_q Kᵢ: the ``matrices`` Kᵢ, their factors ``kappa`` (matrices × N) and
    whether every Kᵢ is ``symmetric``. With a ``correction`` (N × m₀ × m₀), the updates take
    the operator K(μ_q) + (W Q₀) D_q (W Q₀)ᵀ instead, Q₀ the first m₀ space modes (W-orthonormal,
    so that its projection on them is Q₀ᵀ K Q₀ + D_q): a Newton–PGD's tangent at each point's
    own state on the span it has (D_q = Q₀ᵀ (J_q − K(μ_q)) Q₀), and the right-hand side
    b_q + W Q₀ s_q (``shift``, s_q = D_q z_q, m₀ × N: the linearised problem J_q (u⁺ − u) = −r_q
    on that span, written as K(μ_q) u⁺ = b_q); a new term's space part takes K, its right-hand
    side what the updates left (:func:`_left_on_span`)."""

    matrices: list[PETSc.Mat]
    kappa: np.ndarray
    symmetric: bool
    correction: np.ndarray | None = None
    shift: np.ndarray | None = None

    def apply_sampled(self, found: Modes, Z: np.ndarray) -> np.ndarray:
        """K(μ_q) Q z_q for each column z_q of ``Z`` (m × N): owned entries × N, from the K Q kept."""
        return sum((KQ @ Z) * k for KQ, k in zip(found.KQ, self.kappa))

    def corrections(self, m: int) -> np.ndarray | None:
        """D_q on all m space modes (N × m × m; 0 beyond the m₀ it was made on), or None."""
        if self.correction is None:
            return None
        n, m0, _ = self.correction.shape
        padded = np.zeros((n, m, m))
        padded[:, :m0, :m0] = self.correction
        return padded

    def reduced_rhs(self, found: Modes, b: np.ndarray) -> np.ndarray:
        """Qᵀ b_q, plus the ``shift`` on the first m₀ modes (m × N)."""
        Qb = found.reduced(b)
        if self.shift is not None:
            Qb[: len(self.shift)] += self.shift
        return Qb


def solve(
    operator: Operator,
    sample: Sample,
    b: np.ndarray,
    found: Modes,
    W: PETSc.Mat,
    options: Options,
    most: int | None = None,
) -> list[Round]:
    """Update ``found`` (its matrices ``operator.matrices``) to the sampled Galerkin PGD of
    K(μ) u = b (``b``: owned entries × N) (module docstring), adding at most ``most`` terms to
    those it has (None: as many as the tolerance asks); one :class:`Round` per term tried.
    Collective."""
    rounds: list[Round] = []
    for _ in range(options.sweeps if found.count else 0):
        _update(operator, sample, b, found)
    limit = options.max_terms if most is None else min(options.max_terms, found.count + most)
    while found.count < limit and _finite(found):  # (an update past the law's range: the caller sees it)
        u, x, iterations, converged = _new_term(
            operator, sample, _left_on_span(operator, sample, b, found, W), found, options
        )
        lam = np.multiply.reduce([B @ xj for B, xj in zip(sample.bases, x)], axis=0)
        amplitude = float(norms(u[:, None], W, found.comm)[0]) * float(np.sqrt(sample.weights @ lam**2))
        whole = float(np.sqrt(mean_square(sample, found) + amplitude**2))
        if amplitude <= options.tolerance * whole or whole == 0.0:
            potential = _potential(operator, sample, b, found)
            rounds.append(Round(amplitude / whole if whole else 0.0, iterations, converged, False, False, potential))
            break
        new = found.add(u, x, W)
        for _ in range(options.sweeps):
            _update(operator, sample, b, found)
        rounds.append(
            Round(amplitude / whole, iterations, converged, True, new, _potential(operator, sample, b, found))
        )
    return rounds


def _finite(found: Modes) -> bool:
    """Whether the terms' reduced parts and splines are finite numbers (on every rank)."""
    local = bool(np.isfinite(found.R).all() and all(np.isfinite(X).all() for X in found.X))
    return bool(found.comm.allreduce(local, op=MPI.LAND))


def mean_square(sample: Sample, found: Modes) -> float:
    """Σ_q w_q ‖Q R Λ_q‖²_W (Q W-orthonormal: ‖R Λ_q‖²)."""
    if not found.count:
        return 0.0
    Z = found.R @ sample.products(found)
    return float(sample.weights @ np.sum(Z**2, axis=0))


def _left_on_span(operator: Operator, sample: Sample, b: np.ndarray, found: Modes, W: PETSc.Mat) -> np.ndarray:
    """The right-hand side a new term takes: ``b``, plus under a correction W Q₀ (s_q − D_q z⁺_q),
    z⁺ the terms' coordinates now, so that its K residual on the span of Q₀ is what the
    corrected updates left (not their gap to K's own step there)."""
    if operator.correction is None or operator.shift is None:
        return b
    m0 = len(operator.shift)
    Z = (found.R @ sample.products(found))[:m0]
    gap = operator.shift - np.einsum("qab,bq->aq", operator.correction, Z)
    return b + apply(W, found.Q[:, :m0], found.comm) @ gap


def _new_term(
    operator: Operator, sample: Sample, b: np.ndarray, found: Modes, options: Options
) -> tuple[np.ndarray, list[np.ndarray], int, bool]:
    """(ū, its splines per axis, iterations, converged): alternating directions for one term,
    the others fixed."""
    comm, w, kappa = found.comm, sample.weights, operator.kappa
    old = sample.products(found)  # Λ (terms × N)
    KU = [KQ @ found.R for KQ in found.KQ]  # Kᵢ U (owned × terms)
    rng = np.random.default_rng(found.count)  # the same on every rank
    x = [rng.uniform(0.5, 1.5, axis.size) for axis in sample.axes]
    parts = [B @ xj for B, xj in zip(sample.bases, x)]
    before = None
    for iteration in range(1, options.iterations + 1):
        lam = np.multiply.reduce(parts, axis=0)
        rhs = b @ (w * lam)
        for KUi, k in zip(KU, kappa):
            rhs -= KUi @ (old @ (w * k * lam))
        u = combined_solve(operator.matrices, kappa @ (w * lam**2), rhs)
        Ku = np.column_stack([apply(K, u[:, None], comm)[:, 0] for K in operator.matrices])
        uKu = gram(u[:, None], Ku, comm)[0]  # ūᵀKᵢū
        uKU = gram(u[:, None], np.hstack(KU), comm)[0].reshape(len(KU), found.count) if found.count else None
        alpha = uKu @ kappa  # ūᵀK(μ_q)ū
        beta = gram(u[:, None], b, comm)[0]  # ūᵀb_q
        if uKU is not None:
            beta = beta - np.sum(kappa * (uKU @ old), axis=0)
        for j, (axis, B) in enumerate(zip(sample.axes, sample.bases)):
            p = np.multiply.reduce([v for i, v in enumerate(parts) if i != j], axis=0) if len(parts) > 1 else 1.0
            M = B.T @ ((w * p**2 * alpha)[:, None] * B)
            x[j] = solve_small(_ridged(M), B.T @ (w * p * beta), True)
            if j < len(sample.axes) - 1:  # unit mean square: the amplitude is the space part's and the last axis's
                x[j] /= max(rms(axis, x[j]), 1e-300)
            parts[j] = B @ x[j]
        now = (u, [xj.copy() for xj in x])
        if before is not None and change(sample.axes, comm, before, now) <= options.fixed_point:
            return u, x, iteration, True
        before = now
    return u, x, options.iterations, False


def _update(operator: Operator, sample: Sample, b: np.ndarray, found: Modes) -> None:
    """Every term's space coefficients R, then each axis's splines of every term, for ``b``."""
    w, kappa, n, m = sample.weights, operator.kappa, found.count, found.Q.shape[1]
    A = found.reduced_operators()
    D = operator.corrections(m)  # the tangent at each point's state on the span it has
    if D is not None:
        _least_squares_update(operator, sample, b, found, np.einsum("iq,iab->qab", kappa, np.array(A)) + D)
        return
    Qb = operator.reduced_rhs(found, b)  # m × N
    Lam = sample.products(found)
    M = kron_sum([(Lam * (w * k)) @ Lam.T for k in kappa], A)
    rhs = ((Qb * w) @ Lam.T).T.ravel()  # [k, a]: Σ_q w_q Λₖ_q (Qᵀb_q)_a
    symmetric = operator.symmetric
    found.R = solve_small(M, rhs, symmetric).reshape(n, m).T
    Y = found.R.T @ Qb  # Rₖᵀ Qᵀ b_q (terms × N)
    C = np.array([found.R.T @ Ai @ found.R for Ai in A])  # Rₖᵀ Qᵀ Kᵢ Q Rₗ
    G = np.einsum("iq,ikl->qkl", kappa, C)
    for j, B in enumerate(sample.bases):
        values = sample.values(found)
        p = (
            np.multiply.reduce([v for i, v in enumerate(values) if i != j], axis=0)
            if len(values) > 1
            else np.ones_like(Lam)
        )
        H = w[:, None, None] * G * p.T[:, :, None] * p.T[:, None, :]  # N × terms × terms
        M = kron_sum(H, B[:, :, None] * B[:, None, :])  # Σ_q H_q ⊗ Bʲ_q Bʲ_qᵀ
        rhs = ((w * p * Y) @ B).ravel()  # [k, a]: Σ_q w_q pₖ_q Yₖ_q Bʲ_qa
        found.X[j] = solve_small(_ridged(M), rhs, symmetric).reshape(n, B.shape[1])


def _least_squares_update(operator: Operator, sample: Sample, b: np.ndarray, found: Modes, T: np.ndarray) -> None:
    """The update under a correction: every term's R, then each axis's splines of every term,
    each minimising the sampled residual on the span, Σ_q w_q ‖T_q z_q − c_q‖², z_q = R Λ_q,
    T_q = Qᵀ K(μ_q) Q + D_q the tangent at the point's state there (N × m × m) and c_q = Qᵀ b_q
    + s_q (module docstring). Its normal equations are symmetric and positive semi-definite
    (ridged, as the axes' are); the Galerkin update's, with non-symmetric T_q, are not, and
    its sweeps threw the terms off by orders of magnitude once the budget of terms filled (the
    imaged lung over its posture, ``docs/guide/pgd.md``). These are steps of alternating
    least squares, none increasing the residual."""
    w, n, m = sample.weights, found.count, found.Q.shape[1]
    c = operator.reduced_rhs(found, b)  # m × N
    Lam = sample.products(found)
    TT = np.einsum("qba,qbc->qac", T, T)  # T_qᵀ T_q
    M = kron_sum(w[:, None, None] * Lam.T[:, :, None] * Lam.T[:, None, :], TT)  # Σ_q w_q Λ_q Λ_qᵀ ⊗ T_qᵀT_q
    rhs = ((np.einsum("qba,bq->aq", T, c) * w) @ Lam.T).T.ravel()  # Σ_q w_q Λ_q ⊗ T_qᵀ c_q
    found.R = solve_small(_ridged(M), rhs, True).reshape(n, m).T
    TR = T @ found.R  # T_q Rₖ (N × m × terms)
    G = np.einsum("qan,qal->qnl", TR, TR)  # Rₖᵀ T_qᵀ T_q Rₗ
    Y = np.einsum("qan,aq->nq", TR, c)  # Rₖᵀ T_qᵀ c_q
    for j, B in enumerate(sample.bases):
        values = sample.values(found)
        p = (
            np.multiply.reduce([v for i, v in enumerate(values) if i != j], axis=0)
            if len(values) > 1
            else np.ones_like(Lam)
        )
        H = w[:, None, None] * G * p.T[:, :, None] * p.T[:, None, :]
        M = kron_sum(H, B[:, :, None] * B[:, None, :])
        rhs = ((w * p * Y) @ B).ravel()
        found.X[j] = solve_small(_ridged(M), rhs, True).reshape(n, B.shape[1])


def _ridged(M: np.ndarray) -> np.ndarray:
    """M plus :data:`RIDGE` of its mean diagonal on the diagonal."""
    return M + RIDGE * max(float(np.mean(np.abs(np.diag(M)))), 1e-300) * np.eye(len(M))


def _potential(operator: Operator, sample: Sample, b: np.ndarray, found: Modes) -> float:
    """Σ_q w_q (½ ⟨K(μ_q) u_q, u_q⟩ − ⟨b_q, u_q⟩) of the terms so far (the step's quadratic)."""
    if not found.count:
        return 0.0
    Z = found.R @ sample.products(found)  # m × N
    quadratic = sum(k * np.einsum("aq,ab,bq->q", Z, Ai, Z) for k, Ai in zip(operator.kappa, found.reduced_operators()))
    D = operator.corrections(len(Z))
    if D is not None:
        quadratic = quadratic + np.einsum("aq,qab,bq->q", Z, D, Z)
    return float(sample.weights @ (0.5 * quadratic - np.sum(operator.reduced_rhs(found, b) * Z, axis=0)))
