"""Many columns of one linear form in a single assembly, over a stacked test space.

A state-dependent load's tangent needs the columns b_k = a(e_k; ·), k = 1 … m, of a form
a(c; v) linear in a constant c ∈ Rᵐ (and in the test function v): one per unit vector e_k.
Assembled one by one, each column costs a pass over the mesh that evaluates the whole
integrand. Here the m columns are the m blocks of one vector of a test space W = Vᵐ (m copies
of the model's element, one per entry of c):

    b = Σ_k a(e_k; w_k),   w = (w_1, …, w_m) ∈ W,   b_k = the k-th copy's rows of b,

one pass whose kernel shares the integrand's common parts (the deformation, the normal, the
quadrature) between the columns, and drops each copy's terms that e_k zeroes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import basix.ufl
import numpy as np
import ufl
from dolfinx import fem, la

from lungmech.parallel.owned import owned_size

__all__ = ["StackedSpace", "stacked_form", "units"]


class StackedSpace:
    """``copies`` copies of ``space``'s element on its mesh: a test function per copy
    (:attr:`tests`, each shaped like ``space``'s), and the columns of an assembled linear form
    of them, on ``space``'s owned dofs (:meth:`columns`)."""

    def __init__(self, space: fem.FunctionSpace, copies: int) -> None:
        self.space = fem.functionspace(space.mesh, basix.ufl.mixed_element([space.ufl_element()] * copies))
        self.tests: Sequence[ufl.core.expr.Expr] = ufl.TestFunctions(self.space)
        self._vector = fem.Function(self.space).x
        # a dof of the model's space and its copies share their cell and their place in it
        owned = owned_size(space)
        model_dofs = _cell_dofs(space.dofmap)
        rows = np.full((model_dofs.max(initial=-1) + 1, copies), -1, dtype=np.int64)
        for k in range(copies):
            rows[model_dofs.ravel(), k] = _cell_dofs(self.space.sub(k).dofmap).ravel()
        self._rows = rows[:owned]
        if owned and self._rows.min() < 0:
            raise AssertionError("a dof of the model's space has no copy in its stacked space")

    def columns(self, form: fem.Form) -> np.ndarray:
        """The owned rows (of the model's space) of each copy's block of the assembled ``form``
        (a linear form in :attr:`tests`), side by side. Collective."""
        vector = self._vector
        vector.array[:] = 0.0
        fem.assemble_vector(vector.array, form)  # type: ignore[arg-type]  # DOLFINx's into-an-array overload (singledispatch) is not in its hints
        vector.scatter_reverse(la.InsertMode.add)  # ghost cells' contributions to their owners
        return vector.array[self._rows]


def units(shape: tuple[int, ...]) -> list[ufl.core.expr.Expr]:
    """The unit tensors of ``shape`` as UFL literals, in flattened order (zeros a form drops)."""
    if not shape:
        return [ufl.as_ufl(1.0)]
    size = int(np.prod(shape, dtype=int))
    return [ufl.as_tensor(unit.reshape(shape)) for unit in np.eye(size)]


def stacked_form(
    stack: StackedSpace, form_of: Callable[[ufl.core.expr.Expr, ufl.core.expr.Expr], ufl.Form], shape: tuple[int, ...]
) -> ufl.Form:
    """Σ_k a(e_k; w_k): ``form_of(e_k, w_k)`` for each unit tensor e_k of ``shape`` and the
    stacked space's k-th test function. The units are literals, so that each copy keeps only its
    own terms: ``form_of`` builds integrals that no unit zeroes as a whole (UFL refuses an
    integral of zero; a form given whole and replaced into drops such integrals instead)."""
    terms = [form_of(unit, test) for unit, test in zip(units(shape), stack.tests, strict=True)]
    return sum(terms[1:], terms[0])


def _cell_dofs(dofmap: fem.DofMap) -> np.ndarray:
    """Each cell's dofs (rows), unrolled from blocks in the element's order (node, component)."""
    cells = np.asarray(dofmap.list)
    bs = dofmap.bs
    if bs == 1:
        return cells
    return (bs * cells[:, :, None] + np.arange(bs)).reshape(len(cells), -1)
