"""The separated terms a PGD has found so far, as both of its greedy algorithms keep them:

    u(μ) = Q R q(μ),   qₖ(μ) = Πⱼ λₖʲ(μⱼ),

Q the space modes (owned entries × m, orthonormal in the energy inner product W), R the terms'
space coefficients (m × n) and X[j] the terms' splines on axis j (n × its size), with K Q kept
for each operator matrix K of the problem. A new term's space part enters Q only by its part
outside span Q (:data:`SPAN`); its coefficients go to R either way.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import cast

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import scipy.linalg

from lungmech.errors import ParameterError
from lungmech.fem.linear import factorised
from lungmech.parallel.linalg import apply, gram, norms
from lungmech.pgd.axes import Axis
from lungmech.pgd.decomposition import Decomposition

__all__ = ["SPAN", "Modes", "combined_solve", "kron_sum", "rms", "solve_small"]

SPAN = 1e-8  # a new term's space part outside span Q below this fraction of it: no new space mode


class Modes:
    """Q, R, X[j] (module docstring) and KQ[i] = K_i Q for the ``matrices`` K_i, none yet."""

    def __init__(self, axes: Sequence[Axis], matrices: Sequence[PETSc.Mat], owned: int, comm: MPI.Comm) -> None:
        self.axes, self.matrices, self.comm = tuple(axes), list(matrices), comm
        self.Q = np.zeros((owned, 0))
        self.R = np.zeros((0, 0))
        self.X = [np.zeros((0, axis.size)) for axis in self.axes]
        self.KQ = [np.zeros((owned, 0)) for _ in self.matrices]
        self._reduced: list[np.ndarray] | None = None  # Qᵀ K_i Q, made when asked for, until Q grows

    @property
    def count(self) -> int:
        """The number of separated terms n."""
        return self.R.shape[1]

    def copy(self) -> Modes:
        """The terms as they are now, apart from these (the matrices shared)."""
        found = Modes(self.axes, self.matrices, len(self.Q), self.comm)
        found.Q, found.R, found.X, found.KQ = self.Q.copy(), self.R.copy(), [X.copy() for X in self.X], list(self.KQ)
        return found

    def decomposition(self) -> Decomposition:
        return Decomposition(self.axes, self.Q.copy(), self.R.copy(), [X.copy() for X in self.X])

    def values(self) -> list[np.ndarray]:
        """Each axis's splines at its nodes (terms × nodes)."""
        return [Xj @ axis.basis.T for axis, Xj in zip(self.axes, self.X)]

    def reduced_operators(self) -> list[np.ndarray]:
        """Qᵀ K_i Q for each matrix."""
        if self._reduced is None:
            self._reduced = [gram(self.Q, KQ, self.comm) for KQ in self.KQ]
        return self._reduced

    def reduced(self, vectors: np.ndarray) -> np.ndarray:
        """Qᵀ V for owned ``vectors`` (owned entries × k)."""
        return gram(self.Q, vectors, self.comm)

    def add(self, u: np.ndarray, x: Sequence[np.ndarray], W: PETSc.Mat) -> bool:
        """Add the term ū Πⱼ λʲ (splines ``x``); True if its space part brought a new mode."""
        r = gram(self.Q, apply(W, u[:, None], self.comm), self.comm)[:, 0]
        remainder = u - self.Q @ r
        length = float(norms(remainder[:, None], W, self.comm)[0])
        new = length > SPAN * float(norms(u[:, None], W, self.comm)[0])
        if new:
            q = remainder - self.Q @ gram(self.Q, apply(W, remainder[:, None], self.comm), self.comm)[:, 0]
            q /= float(norms(q[:, None], W, self.comm)[0])  # twice is enough
            self.Q = np.column_stack([self.Q, q])
            self._reduced = None
            self.KQ = [np.column_stack([KQ, apply(K, q[:, None], self.comm)]) for KQ, K in zip(self.KQ, self.matrices)]
            r = np.append(r, float(gram(q[:, None], apply(W, u[:, None], self.comm), self.comm)[0, 0]))
            self.R = np.vstack([self.R, np.zeros((1, self.count))])
        self.R = np.column_stack([self.R, r])
        self.X = [np.vstack([Xj, xj]) for Xj, xj in zip(self.X, x)]
        return new


def rms(axis: Axis, x: np.ndarray) -> float:
    """The root mean square over ``axis`` of the spline of coefficients ``x``."""
    values = axis.basis @ x
    return float(np.sqrt(axis.weights @ values**2))


def solve_small(M: np.ndarray, rhs: np.ndarray, symmetric: bool = False) -> np.ndarray:
    """M x = rhs: by Cholesky where M is ``symmetric`` (a symmetric problem's Galerkin matrix:
    half LU's work) and positive definite, else LU; in the least-squares sense where terms
    share a space part and M is singular."""
    if symmetric:
        try:
            return scipy.linalg.cho_solve(scipy.linalg.cho_factor(M, check_finite=False), rhs, check_finite=False)
        except np.linalg.LinAlgError:
            pass  # not definite: LU
    try:
        return np.linalg.solve(M, rhs)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(M, rhs, rcond=None)[0]


def kron_sum(left: Sequence[np.ndarray] | np.ndarray, right: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
    """Σ_T left_T ⊗ right_T (:func:`numpy.kron`'s layout) as one matrix product over the terms T:
    a sum of Kronecker products costs a term's worth of memory traffic each, this one BLAS call."""
    L, Rt = np.asarray(left), np.asarray(right)
    (count, n, _), m = L.shape, Rt.shape[1]
    M = L.reshape(count, n * n).T @ Rt.reshape(count, m * m)  # [k l, a b]
    return M.reshape(n, n, m, m).transpose(0, 2, 1, 3).reshape(n * m, n * m)


def combined_solve(matrices: Sequence[PETSc.Mat], coefficients: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """(Σᵢ αᵢ Kᵢ) u = rhs (owned entries) by a direct factorisation: a PGD's space step, the
    matrices one form's assemblies (one pattern). Collective."""
    A = matrices[0].duplicate()
    made: list = [A]
    try:
        A.zeroEntries()
        for K, a in zip(matrices, coefficients):
            A.axpy(float(a), K, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)  # type: ignore[arg-type]  # an enum member; the stubs say int
        solver = factorised(A)
        made.append(solver)
        u, b = cast(tuple[PETSc.Vec, PETSc.Vec], A.createVecs())  # (right, left)
        made += [u, b]
        b.array[:] = rhs
        solver.solve(b, u)
        reason = int(solver.getConvergedReason())  # type: ignore[call-overload]  # an int at run time; the stubs say a class
        solution = u.array.copy()
    finally:
        for thing in made:
            thing.destroy()
    if reason < 0:
        raise ParameterError(f"PGD: the space step's linear solve failed (PETSc reason {reason})")
    return solution
