"""Modal bases (vibration modes of the tangent stiffness) and their modal derivatives."""

from __future__ import annotations

import numpy as np
import ufl
from dolfinx import fem, la
from dolfinx.fem.petsc import assemble_matrix

from lungmech import jit
from lungmech.errors import ParameterError
from lungmech.fem.linear import factorised
from lungmech.fem.modal import modal_analysis
from lungmech.fem.model import Model
from lungmech.parallel.layout import layout
from lungmech.parallel.owned import owned_size
from lungmech.rom.basis import Basis, enrich, zero_imposed


def modal_basis(model: Model, size: int, density: float = 1.0, shift: float | None = None) -> Basis:
    """The ``size`` lowest modes of K y = λ M y at the current state, orthonormal in the mass
    inner product (ρ = 1 units, so the vectors do not depend on the density); values are λ."""
    modes = modal_analysis(model, size, density=density, shift=shift)
    owned = owned_size(model.space)
    vectors = np.column_stack([v.x.array[:owned] for v in modes.vectors]) * np.sqrt(density)
    source = {"density": density, "eigenvalues": modes.eigenvalues.tolist()}
    return Basis(vectors, modes.eigenvalues.copy(), "modal", "mass", layout(model.space).fingerprint, source)


def modal_derivatives(model: Model, basis: Basis) -> np.ndarray:
    """Static modal derivatives θ_ij = −K⁻¹ (∂K/∂q_j) φ_i, i ≤ j, at the current state.

    ∂K/∂q_j φ_i is the third variation of the energy in the directions φ_i, φ_j (exact, from UFL);
    it vanishes for a linear law. Returns the owned rows, one column per pair.
    """
    if model.multi_field:
        raise ParameterError("modal derivatives need the displacement formulation (no extra fields)")
    if model.state_dependent:
        raise ParameterError("modal derivatives: state-dependent loads are not supported")
    phi_i, phi_j = fem.Function(model.space), fem.Function(model.space)
    third = jit.form(ufl.derivative(ufl.action(model.jacobian, phi_i), model.state, phi_j))
    K = assemble_matrix(jit.form(model.jacobian), bcs=model.bcs, diag=1.0)
    K.assemble()
    ksp = factorised(K)
    owned = basis.vectors.shape[0]
    rhs, solution = fem.Function(model.space), fem.Function(model.space)
    columns = []
    for i in range(basis.size):
        for j in range(i, basis.size):
            for phi, k in ((phi_i, i), (phi_j, j)):
                phi.x.array[:owned] = basis.vectors[:, k]
                phi.x.scatter_forward()
            rhs.x.array[:] = 0.0
            fem.assemble_vector(rhs.x.array, third)
            rhs.x.scatter_reverse(la.InsertMode.add)
            rhs.x.array[:] *= -1.0
            zero_imposed(model, rhs.x.array[:owned, None])
            ksp.solve(rhs.x.petsc_vec, solution.x.petsc_vec)
            columns.append(solution.x.array[:owned].copy())
    ksp.destroy()
    K.destroy()
    return np.column_stack(columns)


def with_modal_derivatives(model: Model, basis: Basis) -> Basis:
    """The modal basis enriched by its modal derivatives, re-orthonormalised (modes first)."""
    derivatives = modal_derivatives(model, basis)
    extra = Basis(derivatives, np.zeros(derivatives.shape[1]), "derivatives", basis.inner_product, basis.fingerprint)
    enriched = enrich(model, basis, extra)
    return Basis(
        enriched.vectors,
        enriched.values,
        "modal+derivatives",
        basis.inner_product,
        basis.fingerprint,
        basis.source | {"modes": basis.size},
    )
