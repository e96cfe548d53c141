"""Dense linear algebra on distributed row blocks: the one Gram–Schmidt and the one POD.

A set of k vectors of length n is stored as each rank's owned rows, an (owned, k) NumPy array; a
product with a distributed PETSc matrix is one MatMatMult (:func:`apply`) and an inner product
is a local product and an Allreduce (:func:`gram`). Replicated data (every rank holds all rows)
uses ``MPI.COMM_SELF``. A weight W (a mass or energy inner product) is a PETSc matrix, a
callable V ↦ W V, or None for the Euclidean product.

All functions are collective on ``comm``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
from dolfinx import la

__all__ = ["POD", "LocalCSR", "NotPositive", "Weight", "apply", "gram", "gram_schmidt", "pod"]

Weight = PETSc.Mat | Callable[[np.ndarray], np.ndarray] | None

# Method of snapshots: σ² comes from an eigensolve of Sᵀ W S, whose round-off is ε σ₁², so σ below
# about √ε σ₁ is noise. 1e-7 keeps a margin above √ε ≈ 1.5e-8.
NOISE = 1e-7
# A weight is positive definite on the vectors at hand if no vᵀ W v falls below −INDEFINITE of the
# scale its round-off has (‖v‖ ‖W v‖, or the largest eigenvalue of Sᵀ W S).
INDEFINITE = 1e-8


class NotPositive(ArithmeticError):
    """The weight W is not positive definite on the vectors given: vᵀ W v < 0 for some v."""


def apply(W: Weight, vectors: np.ndarray, comm: MPI.Comm) -> np.ndarray:
    """W · V for owned rows V: one MatMatMult for a PETSc matrix, V itself for W = None."""
    if W is None:
        return vectors
    if callable(W) and not isinstance(W, PETSc.Mat):
        return W(vectors)
    rows, k = vectors.shape
    # petsc4py's stubs want sizes of ints and a sequence; PETSc takes None (decide) and a NumPy array
    dense = PETSc.Mat().createDense(((rows, None), (None, k)), array=np.ascontiguousarray(vectors), comm=comm)  # type: ignore[arg-type]
    product = W.matMult(dense)
    result = product.getDenseArray().copy()
    product.destroy()
    dense.destroy()
    return result


def gram(left: np.ndarray, right: np.ndarray, comm: MPI.Comm) -> np.ndarray:
    """Lᵀ R summed over all ranks."""
    local = np.ascontiguousarray(left.T @ right)
    total = np.empty_like(local)
    comm.Allreduce(local, total, op=MPI.SUM)
    return total


def norms(vectors: np.ndarray, W: Weight, comm: MPI.Comm) -> np.ndarray:
    """‖v_j‖_W = √(v_jᵀ W v_j) of each column of the owned rows ``vectors`` (the columns' own
    products only, not the whole Gram matrix), summed over all ranks."""
    local = np.einsum("ij,ij->j", vectors, apply(W, vectors, comm))
    total = np.empty_like(local)
    comm.Allreduce(local, total, op=MPI.SUM)
    return np.sqrt(np.abs(total))


def gram_schmidt(
    vectors: np.ndarray, W: Weight, comm: MPI.Comm, tolerance: float = 1e-10
) -> tuple[np.ndarray, np.ndarray]:
    """W-orthonormal vectors spanning the columns of ``vectors``, in order (Gram–Schmidt, twice).

    For each column v: v ← v − Q (W Q)ᵀ v, twice ("twice is enough", Kahan–Parlett), then
    v / ‖v‖_W. A column whose remainder is below ``tolerance`` × its own W-norm adds nothing new
    and is dropped. Returns the vectors and the indices of the columns that were kept. Raises
    :class:`NotPositive` when vᵀ W v < 0 for a column (W is no inner product there).
    """
    kept = []
    result, weighted = np.zeros((vectors.shape[0], 0)), np.zeros((vectors.shape[0], 0))  # Q and W·Q
    for j in range(vectors.shape[1]):
        v = np.array(vectors[:, [j]], dtype=float)
        wv = apply(W, v, comm)
        square = gram(v, wv, comm)[0, 0]
        if square < -INDEFINITE * np.sqrt(gram(v, v, comm)[0, 0] * gram(wv, wv, comm)[0, 0]):
            raise NotPositive(f"vᵀ W v = {square:.3g} < 0 for column {j}")
        norm0 = np.sqrt(max(square, 0.0))
        if not norm0 > 0:
            continue
        for _ in range(2):
            v -= result @ gram(weighted, v, comm)
        wv = apply(W, v, comm)
        norm = np.sqrt(max(gram(v, wv, comm)[0, 0], 0.0))
        if norm > tolerance * norm0:
            result, weighted = np.hstack([result, v / norm]), np.hstack([weighted, wv / norm])
            kept.append(j)
    return result, np.array(kept, dtype=int)


@dataclass(frozen=True)
class POD:
    """Modes Φ (owned rows, m), W-orthonormal; singular values σ (m,), decreasing; and the
    snapshots' coordinates C (N, m), so that snapshot j ≈ Φ C[j] (exactly, up to the noise cut-off);
    and the whole spectrum (N,), the noise included."""

    modes: np.ndarray
    values: np.ndarray
    coefficients: np.ndarray
    spectrum: np.ndarray


def pod(data: np.ndarray, W: Weight, comm: MPI.Comm) -> POD:
    """The proper orthogonal decomposition of the snapshot columns ``data`` (owned rows, N).

    Method of snapshots: C = Sᵀ W S = Q Σ² Qᵀ, modes Φ = S Q Σ⁻¹ (re-orthonormalised against
    round-off by :func:`gram_schmidt`), coefficients Q Σ. Directions with σ ≤ 1e-7 σ₁ are noise
    of C and are dropped. All-zero data give no modes. Raises :class:`NotPositive` when W is not
    positive definite on the snapshots' span.
    """
    correlation = gram(data, apply(W, data, comm), comm)
    eigenvalues, vectors = np.linalg.eigh(correlation)
    order = np.argsort(eigenvalues)[::-1]
    eigenvalues, vectors = eigenvalues[order], vectors[:, order]
    if eigenvalues.size and eigenvalues[-1] < -INDEFINITE * max(eigenvalues[0], 0.0):
        raise NotPositive(f"Sᵀ W S has the eigenvalue {eigenvalues[-1]:.3g} < 0")
    singular = np.sqrt(np.clip(eigenvalues, 0.0, None))
    keep = singular > NOISE * singular[0] if singular.size and singular[0] > 0 else np.zeros(len(singular), bool)
    modes, kept = gram_schmidt(data @ vectors[:, keep] / singular[keep], W, comm)
    values = singular[keep][kept]
    return POD(modes, values, vectors[:, keep][:, kept] * values, singular)


class LocalCSR:
    """A rank's rows of a DOLFINx ``MatrixCSR`` (ghost rows too, block size 1), as y = A x over
    its local and ghost columns, sharing the matrix's values (an assembly into the matrix is
    seen). SciPy's compiled CSR product: on the bundled lung's reduced mesh (73k entries, 28
    columns) 0.6 ms against 10 ms for NumPy's gather and ``reduceat``; ``scipy.sparse`` is
    imported with the first matrix (60 ms), not with lungmech."""

    def __init__(self, matrix: la.MatrixCSR) -> None:
        import scipy.sparse  # (see the class's doc)

        columns = matrix.index_map(1)
        shape = (len(matrix.indptr) - 1, columns.size_local + columns.num_ghosts)
        self.data = matrix.data
        self._matrix = scipy.sparse.csr_array((self.data, matrix.indices, matrix.indptr), shape=shape, copy=False)
        # (a dtype SciPy converts would copy; a rank holding none of the entries has nothing to share)
        if self.data.size and not np.shares_memory(self._matrix.data, self.data):
            raise TypeError("LocalCSR: SciPy copied the matrix's values; they would not follow its assemblies")

    def __abs__(self) -> LocalCSR:
        """|A| entrywise (a copy of the values now: not updated by later assemblies)."""
        copy = LocalCSR.__new__(LocalCSR)
        copy._matrix = abs(self._matrix)
        copy.data = copy._matrix.data
        return copy

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        """A x for a vector or the columns of a matrix x (its rows: the columns of A)."""
        return np.asarray(self._matrix @ x)
