"""Linear modal analysis: K y = λ M y for the tangent stiffness at the model's current state.

K is the model's Jacobian, so the modes are those of the body at rest (state 0) or prestressed
by a converged state. Dirichlet dofs are eliminated without spurious eigenvalues: their rows
carry 1 on K's diagonal and 0 on M's, which sends their eigenvalues to infinity, far from the
shift. SLEPc solves the generalised Hermitian problem by shift-and-invert (MUMPS), so the
eigenvalues nearest the shift converge first and repeated ones (a square beam bends alike in
two planes) come out as separate M-orthonormal vectors.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix
from slepc4py import SLEPc

from lungmech import jit
from lungmech.errors import ParameterError, SolverError
from lungmech.fem.linear import use_lu

if TYPE_CHECKING:
    from lungmech.fem.model import Model


@dataclass
class Modes:
    """Eigenpairs in ascending order: λ = ω² and M-orthonormal mode shapes."""

    eigenvalues: np.ndarray
    vectors: list[fem.Function]
    scale: float  # max K_ii / max M_ii: the order of the largest eigenvalue of the mesh

    @property
    def frequencies(self) -> np.ndarray:
        """Angular frequencies ω = √λ (0 for rigid modes)."""
        return np.sqrt(np.clip(self.eigenvalues, 0.0, None))

    @property
    def rigid(self) -> np.ndarray:
        """Which modes are rigid-body motions (λ ≈ 0 on the scale of the mesh's largest eigenvalue)."""
        return np.abs(self.eigenvalues) <= 1e-8 * self.scale


def mass_matrix(model: Model, density: float) -> PETSc.Mat:
    """M = ∫ ρ u·v dX, with 0 on the diagonal of constrained rows."""
    u, v = ufl.TrialFunction(model.space), ufl.TestFunction(model.space)
    M = assemble_matrix(jit.form(density * ufl.inner(u, v) * ufl.dx), bcs=model.bcs, diag=0.0)
    M.assemble()
    return M


def modal_analysis(
    model: Model, count: int, density: float = 1.0, shift: float | None = None, tolerance: float = 1e-10
) -> Modes:
    """The ``count`` modes nearest ``shift`` (default 0, or a small negative shift for a free body).

    A free-floating body (no imposed displacement) has rigid modes at λ = 0, where the shifted
    operator would be singular, so it needs a shift below zero; they are flagged in
    :attr:`Modes.rigid`.
    """
    if model.multi_field:
        raise ParameterError("modal analysis needs the displacement formulation (no extra fields)")
    if not (isinstance(count, int) and count >= 1):
        raise ParameterError(f"modal analysis: count must be a positive integer (got {count!r})")
    if not density > 0:
        raise ParameterError(f"modal analysis: density must be > 0 (got {density})")
    if shift == 0.0 and not model.bcs:
        raise ParameterError("a free-floating body has rigid modes at 0: give a negative shift")
    K = assemble_matrix(jit.form(model.jacobian), bcs=model.bcs, diag=1.0)
    K.assemble()
    M = mass_matrix(model, density)
    scale = _largest_diagonal(K) / _largest_diagonal(M)
    if shift is None:  # a free body: just below 0 on the scale of the largest eigenvalue
        shift = 0.0 if model.bcs else -1e-6 * scale

    eps = SLEPc.EPS().create(model.geometry.mesh.comm)
    eps.setOperators(K, M)
    eps.setProblemType(SLEPc.EPS.ProblemType.GHEP)
    eps.setDimensions(count, max(2 * count, count + 20))  # room for repeated eigenvalues
    eps.setTolerances(tolerance, 200)
    eps.setTarget(shift)
    eps.setWhichEigenpairs(SLEPc.EPS.Which.TARGET_REAL)
    st = eps.getST()
    st.setType(SLEPc.ST.Type.SINVERT)
    st.setShift(shift)
    use_lu(st.getKSP())
    eps.solve()
    found = eps.getConverged()
    if found < count:
        raise SolverError(f"modal analysis: SLEPc converged {found} of the {count} modes asked for")

    pairs = []
    for i in range(count):
        vector = fem.Function(model.space, name=f"mode_{i}")
        eigenvalue = eps.getEigenpair(i, vector.x.petsc_vec).real
        vector.x.scatter_forward()
        pairs.append((eigenvalue, vector))
    eps.destroy()
    K.destroy()
    M.destroy()
    pairs.sort(key=lambda pair: pair[0])
    return Modes(np.array([p[0] for p in pairs]), [p[1] for p in pairs], scale)


def _largest_diagonal(A: PETSc.Mat) -> float:
    diagonal = A.getDiagonal()
    value = diagonal.norm(PETSc.NormType.NORM_INFINITY)  # type: ignore[arg-type]  # petsc4py's stubs type the enums as int
    diagonal.destroy()
    return cast(float, value)  # one norm, not NORM_1_AND_2's pair
