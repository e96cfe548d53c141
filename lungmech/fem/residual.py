"""Newton's residual, lifted only where a Dirichlet condition does not hold yet.

DOLFINx's SNES residual (:func:`dolfinx.fem.petsc.assemble_residual`) assembles F(x), then
lifts it by the tangent's columns of the constrained dofs D,

    b = F(x) + J[:, D] (g − x_D),    b_D = x_D − g,

so that a Newton step also moves x_D onto g. Once every condition holds (x_D = g: a clamp or a
symmetry plane after the first iterate, any condition after a step's first), the lifting adds
exactly zero, yet it computes the tangent's element matrix of every cell that touches D: on a
body held on three symmetry planes, a third of an iteration's time. :func:`residual` skips it
then, and is DOLFINx's own otherwise: the same vector to the bit.
"""

from __future__ import annotations

from typing import Any

from petsc4py import PETSc

from dolfinx import fem
from dolfinx.fem.petsc import assemble_residual, assemble_vector, assign, set_bc

__all__ = ["residual"]

_ADD, _INSERT = PETSc.InsertMode.ADD, PETSc.InsertMode.INSERT
_REVERSE, _FORWARD = PETSc.ScatterMode.REVERSE, PETSc.ScatterMode.FORWARD


def residual(
    snes: PETSc.SNES,
    x: PETSc.Vec,
    b: PETSc.Vec,
    u: fem.Function,
    residual: fem.Form,
    jacobian: fem.Form,
    bcs: list[fem.DirichletBC],
    **blocks: Any,
) -> None:
    """The residual at ``x`` into ``b``, as :func:`dolfinx.fem.petsc.assemble_residual` (a
    ``SNES.setFunction`` callback with the same arguments) with the lifting left out where
    x_D − g = 0 on every rank (exactly: the lifting adds zero then). Collective."""
    if blocks:  # (a blocked or nested problem: not lungmech's)
        assemble_residual(snes, x, b, u, residual, jacobian, bcs, **blocks)
        return
    x.ghostUpdate(addv=_INSERT, mode=_FORWARD)  # type: ignore[arg-type]  # petsc4py's stubs type the enums as int
    _zero(b)
    set_bc(b, bcs, x0=x, alpha=-1.0)  # b_D = x_D − g, 0 elsewhere
    if b.norm(PETSc.NormType.NORM_INFINITY) != 0.0:  # type: ignore[arg-type]  # (an int at run time; the stub says NormType)
        assemble_residual(snes, x, b, u, residual, jacobian, bcs)
        return
    assign(x, u)  # type: ignore[arg-type]  # DOLFINx's vector-to-function overload (singledispatch) is not in its hints
    _zero(b)
    assemble_vector(b, residual)  # type: ignore[arg-type]
    b.ghostUpdate(addv=_ADD, mode=_REVERSE)  # type: ignore[arg-type]
    set_bc(b, bcs, x0=x, alpha=-1.0)
    b.ghostUpdate(addv=_INSERT, mode=_FORWARD)  # type: ignore[arg-type]


def _zero(b: PETSc.Vec) -> None:
    """Every entry of ``b`` 0, its ghosts too."""
    with b.localForm() as local:
        local.set(0.0)
