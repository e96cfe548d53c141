"""The a-posteriori error indicator of a PGD: the model's own residual at the decomposition's
answer, in the dual norm of the energy inner product W,

    η(μ) = ‖R(u(μ); μ)‖_{W⁻¹} / ‖u(μ)‖_W,   ‖r‖²_{W⁻¹} = rᵀ W⁻¹ r,

on the free dofs (imposed ones hold the modes' zero). Where the tangent at μ is K(μ), the
error e = u(μ) − u_full(μ) has K(μ) e = R, so η is the relative error in the energy norm of
W times the factor by which K(μ) differs from W along e: exactly E/E₀ for a linear law whose
stiffness E scales it (E₀ W's). That factor, the indicator's effectivity, is measured where
the error is known (:func:`effectivity`). One factorisation of W serves every point.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import cast

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
from dolfinx import fem

from lungmech import jit
from lungmech.fem.linear import factorised
from lungmech.fem.model import Model
from lungmech.fem.quantities import assemble_owned
from lungmech.fem.state_dependent import StateDependent
from lungmech.parallel.linalg import norms
from lungmech.parallel.owned import owned_size
from lungmech.pgd.decomposition import Decomposition
from lungmech.pgd.march import Start
from lungmech.pgd.terms import constants, kept

__all__ = ["effectivity", "indicator"]


def indicator(
    model: Model,
    decomposition: Decomposition,
    W: PETSc.Mat,
    points: Sequence[Mapping[str, float]],
    start: Start | None = None,
) -> np.ndarray:
    """η(μ) at each of ``points`` (module docstring), from ``model``'s own residual at its
    current time, the decomposition's state added to ``start``'s (default: the rest; an imaged
    body's image on its reference ξ(μ), :mod:`lungmech.pgd.march`). The model's parameters and
    state are left as they were. Collective."""
    comm = model.geometry.mesh.comm
    owned = owned_size(model.space)
    imposed = model.constrained_dofs()
    residual = jit.form(model.residual)
    coupled = StateDependent(model)  # a state-dependent load's θ = Θ(u), from each answer's state
    work = fem.Function(model.space).x
    solver = factorised(W)
    z, r = cast(tuple[PETSc.Vec, PETSc.Vec], W.createVecs())  # (right, left)
    values = dict(model.parameter_values)
    found = []
    try:
        with model.kept_state(), kept(model, constants(model)):  # (θ too)
            model.reset()
            rest = model.state.x.array[:owned].copy()  # what the terms add to (a porosity at rest, say)
            for point in points:
                u = decomposition.state(point)
                model.set_parameters(point)
                model.state.x.array[:owned] = (rest if start is None else start(point)) + u
                model.state.x.scatter_forward()
                coupled.update()
                r.array[:] = assemble_owned(residual, work, owned)
                r.array[imposed] = 0.0
                solver.solve(r, z)
                dual = np.sqrt(max(comm.allreduce(float(r.array @ z.array), op=MPI.SUM), 0.0))
                size = float(norms(u[:, None], W, comm)[0])
                found.append(dual / size if size > 0 else np.inf)
    finally:
        model.set_parameters(values)
        for thing in (solver, z, r):
            thing.destroy()
    return np.array(found)


def effectivity(estimates: np.ndarray, errors: np.ndarray) -> tuple[float, float]:
    """(smallest, largest) ratio η / true error over points whose error is known and not 0."""
    ratios = np.asarray(estimates)[np.asarray(errors) > 0] / np.asarray(errors)[np.asarray(errors) > 0]
    return float(ratios.min()), float(ratios.max())
