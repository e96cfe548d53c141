"""The iterative linear solver's preconditioners for a model's tangent: smoothed-aggregation AMG
on the displacement (with its rigid-body near-nullspace, :mod:`lungmech.fem.nullspace`), and
block layouts where the state holds other fields (the lung's Φs condensed exactly; Taylor–Hood's
Schur complement)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, cast

from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx.fem.petsc import assemble_matrix

from lungmech import jit
from lungmech.errors import ParameterError
from lungmech.fem.formulations import incompressible
from lungmech.fem.materials import VolumetricSplit, shear_modulus
from lungmech.fem.nullspace import rigid_body_modes
from lungmech.parallel.owned import owned_size

if TYPE_CHECKING:
    from lungmech.fem.model import Model

__all__ = ["AMG", "available_layout", "iterative_layout"]


AMG = {  # smoothed aggregation, Chebyshev–Jacobi smoothing: for an elastic displacement block
    "pc_type": "gamg",
    "pc_gamg_type": "agg",
    "mg_levels_ksp_type": "chebyshev",
    "mg_levels_pc_type": "jacobi",
}


def _prefixed(prefix: str, options: dict) -> dict:
    return {prefix + key: value for key, value in options.items()}


def iterative_layout(model: Model) -> tuple[dict, Callable[[PETSc.KSP, PETSc.Mat], None]]:
    """The Krylov preconditioner of ``model``'s tangent: PETSc options, and a function of the KSP
    and the tangent matrix that gives them what the options need (the index sets of the fields,
    the rigid-body near-nullspace).

    - Displacement only: AMG with the rigid-body modes.
    - The lung (u, Φs): Φs is cell-local — its equation holds cell by cell, and K_ΦΦ is
      diagonal (DG0) — so it is condensed exactly: a Schur-complement field split with Φs first,
      its block solved by Jacobi (exact for a diagonal), and S = K_uu − K_uΦ K_ΦΦ⁻¹ K_Φu formed
      exactly by ``selfp`` (which uses diag(K_ΦΦ), K_ΦΦ itself), solved with AMG.
    - Taylor–Hood (u, p): a Schur-complement field split with u first, K_uu by AMG with the
      rigid-body modes, and the Schur complement S = −M/κ − B K_uu⁻¹ Bᵀ preconditioned by the
      pressure mass matrix it is spectrally equivalent to (Elman, Silvester & Wathen),
      S_p = −∫ (1/μ₀ + 1/κ) p q dX, μ₀ the law's shear modulus where it is (a field for a
      heterogeneous law; 1/κ = 0 when incompressible), reassembled before each solve so that
      it follows the parameters. ``selfp`` (diag(K_uu)⁻¹) with AMG did not converge on a nearly
      incompressible block.
    """
    fields = ("u", *model.formulation.fields)
    if len(fields) == 1:
        space = model.space
        return dict(AMG), lambda ksp, A: A.setNearNullSpace(rigid_body_modes(space))
    if fields == ("u", "phi_s") or fields == ("u", "thickness_stretch") and model.degree == 1:
        local = fields[1]
        order = (local, "u")  # the cell-local field first: A00, inverted exactly
        options = {
            "pc_type": "fieldsplit",
            "pc_fieldsplit_type": "schur",
            "pc_fieldsplit_schur_fact_type": "full",
            "pc_fieldsplit_schur_precondition": "selfp",
            f"fieldsplit_{local}_ksp_type": "preonly",
            f"fieldsplit_{local}_pc_type": "jacobi",
            "fieldsplit_u_ksp_type": "preonly",
        } | _prefixed("fieldsplit_u_", AMG)
    elif fields == ("u", "p"):
        return _taylor_hood_layout(model)
    else:
        raise ParameterError(
            f"the iterative linear solver has no preconditioner for the fields {', '.join(fields)} yet "
            "(plane stress above degree 1); use linear_solver = 'direct'"
        )

    def set_splits(ksp: PETSc.KSP, A: PETSc.Mat) -> None:
        pc = ksp.getPC()
        sets = _field_index_sets(model)
        pc.setFieldSplitIS(*[(name, sets[name]) for name in order])
        modes = rigid_body_modes(model.space.sub(0).collapse()[0])  # in the u block's row order

        def give_modes(ksp: PETSc.KSP, b: PETSc.Vec, x: PETSc.Vec) -> None:
            """Before each solve: AMG on the Schur complement gets the rigid-body modes (its matrix
            is made when the field split is set up, and kept for the next tangents)."""
            pc = ksp.getPC()  # not captured: PETSc holds this function, and would hold the PC
            pc.setUp()  # a no-op once set up for this tangent
            schur = pc.getFieldSplitSubKSP()[-1]  # the u block's solver: its matrices are S, S_p
            S_p = schur.getOperators()[1]
            if S_p.getNearNullSpace().handle == 0:  # before AMG is built on it, at its first use
                S_p.setNearNullSpace(modes)

        ksp.setPreSolve(give_modes)

    return options, set_splits


def _taylor_hood_layout(model: Model) -> tuple[dict, Callable[[PETSc.KSP, PETSc.Mat], None]]:
    """The (u, p) field split of :func:`iterative_layout`: options, and what the KSP needs."""
    options = {
        "pc_type": "fieldsplit",
        "pc_fieldsplit_type": "schur",
        "pc_fieldsplit_schur_fact_type": "upper",
        "pc_fieldsplit_schur_precondition": "user",
        "fieldsplit_u_ksp_type": "preonly",
        "fieldsplit_p_ksp_type": "preonly",
        "fieldsplit_p_pc_type": "jacobi",  # a P_k mass matrix: diagonal up to a bounded factor
    } | _prefixed("fieldsplit_u_", AMG)

    def set_splits(ksp: PETSc.KSP, A: PETSc.Mat) -> None:
        # compiled here, when the iterative solver is set up, not for every mixed model's solver
        pressures = model.space.sub(1).collapse()[0]
        p, q = ufl.TrialFunction(pressures), ufl.TestFunction(pressures)
        compliance = 1 / shear_modulus(model.material, model.geometry.mesh)
        if not incompressible(model.material):
            compliance += 1 / cast(VolumetricSplit, model.material).bulk  # Taylor–Hood took a split law only
        mass = jit.form(-compliance * p * q * model.dx)
        sets = _field_index_sets(model)
        sets["u"].compose("nearnullspace", rigid_body_modes(model.space.sub(0).collapse()[0]))
        S_p = assemble_matrix(mass)
        S_p.assemble()
        pc = ksp.getPC()
        pc.setFieldSplitIS(("u", sets["u"]), ("p", sets["p"]))
        pc.setFieldSplitSchurPreType(PETSc.PC.FieldSplitSchurPreType.USER, S_p)  # type: ignore[arg-type]  # petsc4py's stubs type the enums as int

        def reassemble(ksp: PETSc.KSP, b: PETSc.Vec, x: PETSc.Vec) -> None:
            """Before each solve: S_p at the current parameters (μ₀ and κ may have changed)."""
            S_p.zeroEntries()
            assemble_matrix(S_p, mass)
            S_p.assemble()

        ksp.setPreSolve(reassemble)

    return options, set_splits


def available_layout(model: Model) -> tuple[dict, Callable[[PETSc.KSP, PETSc.Mat], None]] | None:
    """:func:`iterative_layout`, or None where no preconditioner fits the formulation."""
    try:
        return iterative_layout(model)
    except ParameterError:
        return None


def _field_index_sets(model: Model) -> dict[str, PETSc.IS]:
    """Global rows of each field, owned by this rank, in the order of the field's own collapsed
    space (so the u block's rows follow its rigid-body modes)."""
    space = model.space
    first = space.dofmap.index_map.local_range[0] * space.dofmap.index_map_bs
    sets = {}
    for i, name in enumerate(("u", *model.formulation.fields)):
        collapsed, parent = space.sub(i).collapse()
        owned = owned_size(collapsed)
        rows = np.asarray(parent).ravel()[:owned]
        sets[name] = PETSc.IS().createGeneral((rows + first).astype(PETSc.IntType), comm=space.mesh.comm)
    return sets
