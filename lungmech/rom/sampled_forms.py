"""Forms over an ECSW sample, on the reduced mesh of a hyper-reduced solver.

:class:`SampledForms` compiles a form over the sampled cells of a family, each cell weighted by
its ECSW weight, on the :class:`~lungmech.rom.reduced_mesh.ReducedMesh`, and gives its value as a
vector (Σ_e ξ_e ∫_e f), a reduced column Vᵀ b, or the reduced columns of a form linear in a
constant (one matrix assembly). :class:`SampledIntegration` evaluates the integrals a
state-dependent load declares (balanced gravity) with them: exactly where they are affine in
z = (q, imposed factors), over their own ECSW sample otherwise. :func:`cells_visited` counts what
an assembly of a compiled form visits.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix as assemble_petsc_matrix
from dolfinx.fem.petsc import create_matrix as create_petsc_matrix

from lungmech.errors import ParameterError
from lungmech.fem.model import Model
from lungmech.fem.quantities import vector_integral
from lungmech.fem.state_dependent import Bilinear, FullIntegration, Integral
from lungmech.parallel.linalg import gram
from lungmech.rom.ecsw import NO_CELLS, Sample, flattened, over_cells
from lungmech.rom.exact import affine
from lungmech.rom.reduced_mesh import ReducedMesh
from lungmech.rom.whole import Arrays, Whole

__all__ = ["SampledForms", "SampledIntegration", "cells_visited"]


class SampledForms:
    """Forms of ``model`` over the cells of ``sample`` with their weights (the Functions of
    ``weights``, by family), compiled on the reduced mesh ``mesh``; ``V`` the basis on its sub
    dofs; ``state()`` the object that changes with the reduced mesh's state (its q: coefficients
    are packed once per state). Collective evaluations."""

    def __init__(
        self,
        model: Model,
        mesh: ReducedMesh,
        weights: dict[str, fem.Function],
        sample: Sample,
        V: np.ndarray,
        state: Callable[[], object],
    ) -> None:
        self.model, self.mesh, self.weights, self.sample, self.V = model, mesh, weights, sample, V
        self.comm = model.geometry.mesh.comm
        self._state = state

    def vector(self, family: str, expr: ufl.core.expr.Expr, measure: ufl.Measure) -> Callable[[], np.ndarray]:
        """Σ_e ξ_e ∫_e ``expr`` over the sample of ``family`` (any value shape), at the reduced
        mesh's state."""
        flat = flattened(expr)
        size = flat.ufl_shape[0]
        space = fem.functionspace(self.mesh.mesh, ("DG", 0, (size,)))
        form = ufl.inner(self.weights[family] * flat, ufl.TestFunction(space)) * measure
        compiled = self.mesh.form(over_cells(form, self.model.geometry.mesh, self.sample.cells.get(family, NO_CELLS)))
        vector = fem.Function(space).x

        def evaluate() -> np.ndarray:
            vector.array[:] = 0.0
            fem.assemble_vector(vector.array, compiled)  # type: ignore[arg-type]  # the into-an-array overload (singledispatch) is not in the hints
            total = np.empty(size)
            self.comm.Allreduce(vector.array.reshape(-1, size).sum(axis=0), total, op=MPI.SUM)
            return total.reshape(expr.ufl_shape)

        return evaluate

    def scalars(self, forms: dict[str, ufl.Form]) -> Callable[[], dict[str, float]]:
        """The cell integrals ``forms`` (each weighted by its own family's weights, 0 off its
        sample) by name, at the reduced mesh's state: the entries of one form over the union of
        their samples, Σ_n forms_n v_n with v a test function of len(forms) components, so that
        one assembly gives them all."""
        names = list(forms)
        if not names:
            return lambda: {}
        test = ufl.TestFunction(fem.functionspace(self.mesh.mesh, ("DG", 0, (len(names),))))
        integrals = [
            integral.reconstruct(integrand=integral.integrand() * test[n])
            for n, name in enumerate(names)
            for integral in forms[name].integrals()
        ]
        cells = np.concatenate([self.sample.cells.get(name, NO_CELLS) for name in names])
        compiled = self.mesh.form(over_cells(ufl.Form(integrals), self.model.geometry.mesh, cells))
        vector = fem.Function(test.ufl_function_space()).x

        def evaluate() -> dict[str, float]:
            vector.array[:] = 0.0
            fem.assemble_vector(vector.array, compiled)  # type: ignore[arg-type]  # the into-an-array overload, as above
            totals = np.empty(len(names))
            self.comm.Allreduce(vector.array.reshape(-1, len(names)).sum(axis=0), totals, op=MPI.SUM)
            return dict(zip(names, totals.tolist()))

        return evaluate

    def column(self, form: ufl.Form, families: dict[str, str]) -> Callable[[], np.ndarray]:
        """Vᵀ b of a linear ``form`` (in the model's test function): each integral over the
        sample of ``families[its type]``, with its weights."""
        compiled = self._compiled(form, families)
        vector = fem.Function(self.mesh.space).x
        coefficients = self._packed(compiled)

        def evaluate() -> np.ndarray:
            vector.array[:] = 0.0
            fem.assemble_vector(vector.array, compiled, coeffs=coefficients())  # type: ignore[arg-type]  # the into-an-array overload, as above
            return gram(self.V, vector.array[:, None], self.comm)[:, 0]

        return evaluate

    def columns(self, form: ufl.Form, families: dict[str, str], constant: fem.Constant) -> Callable[[], np.ndarray]:
        """Vᵀ [b(e_1) … b(e_n)] of a ``form`` linear in ``constant`` (n entries), b(e_j) its
        column with ``constant`` = the j-th unit vector: one matrix assembly on the reduced mesh,
        ``constant`` replaced by a trial function τ of n components per sampled cell, whose
        columns summed per component (columns are (cell, component), unrolled) are the n columns."""
        tau = self._trial(constant.value.size)
        return self._columns(ufl.replace(form, {constant: shaped(list(tau), constant.ufl_shape)}), families)

    def bilinear_columns(
        self, form: Bilinear, families: dict[str, str], left: fem.Constant, right: fem.Constant
    ) -> Callable[[], tuple[np.ndarray, np.ndarray]]:
        """(its columns over ``right``'s entries with l = ``left``, its columns over ``left``'s
        with r = ``right``) of the form ``form(l, r)`` linear in each of two vectors, by one
        assembly (on a few cells a call's overhead outweighs its work): form(left, τ₁) +
        form(τ₂, right), τ = (τ₁, τ₂) one trial function. Nothing is replaced in a form, so a
        derivative stays unexpanded until FFCx (its signature, what a warm JIT cache checks, is
        then the small form's)."""
        n = right.value.size
        tau = list(self._trial(n + left.value.size))
        merged = form(left, shaped(tau[:n], right.ufl_shape)) + form(shaped(tau[n:], left.ufl_shape), right)
        columns = self._columns(merged, families)

        def evaluate() -> tuple[np.ndarray, np.ndarray]:
            found = columns()
            return found[:, :n], found[:, n:]

        return evaluate

    def _trial(self, n: int) -> Iterator[ufl.core.expr.Expr]:
        """The entries of a trial function of n components per cell of the reduced mesh."""
        tau = ufl.TrialFunction(fem.functionspace(self.mesh.mesh, ("DG", 0, (n,))))
        return (tau[j] for j in range(n))

    def _columns(self, form: ufl.Form, families: dict[str, str]) -> Callable[[], np.ndarray]:
        """Vᵀ of the columns of a bilinear ``form`` in a DG0 trial function of n components,
        summed per component (see :meth:`columns`)."""
        compiled = self._compiled(form, families)
        n = form.arguments()[1].ufl_shape[0]
        # PETSc's matrix: DOLFINx's own takes square blocks only (here 3 or 1 rows, n columns)
        matrix = create_petsc_matrix(compiled)
        owned = self.V[: self.mesh.owned]  # its rows: the owned sub dofs, each summed over the ranks
        coefficients = self._packed(compiled)

        def evaluate() -> np.ndarray:
            matrix.zeroEntries()
            assemble_petsc_matrix(matrix, compiled, coeffs=coefficients())  # type: ignore[arg-type]  # the into-a-matrix overload (singledispatch) is not in the hints
            matrix.assemble()
            indptr, columns, values = matrix.getValuesCSR()
            rows = len(indptr) - 1
            at = np.repeat(np.arange(rows), np.diff(indptr)) * n + columns % n
            summed = np.bincount(at, weights=values, minlength=rows * n).reshape(rows, n)  # type: ignore[arg-type]  # petsc4py's stub allows complex scalars; this build's are real
            return gram(owned, summed, self.comm)

        return evaluate

    def _compiled(self, form: ufl.Form, families: dict[str, str]) -> fem.Form:
        """``form`` compiled on the reduced mesh, each integral over the sample of
        ``families[its type]``, with its weights."""
        mesh = self.model.geometry.mesh
        weighted: dict[str, list] = {}  # by family: one restricted tag set per integral type
        for integral in form.integrals():
            family = families[integral.integral_type()]
            integrand = self.weights[family] * integral.integrand()
            weighted.setdefault(family, []).append(integral.reconstruct(integrand=integrand))
        integrals = [
            restricted
            for family, parts in weighted.items()
            for restricted in over_cells(ufl.Form(parts), mesh, self.sample.cells.get(family, NO_CELLS)).integrals()
        ]
        return self.mesh.form(ufl.Form(integrals))

    def _packed(self, compiled: fem.Form) -> Callable[[], dict[tuple[fem.IntegralType, int], np.ndarray]]:
        """The coefficients of ``compiled``, packed once per state (only Constants vary in between)."""
        packed: dict[str, Any] = {"at": None, "coefficients": None}

        def coefficients() -> dict[tuple[fem.IntegralType, int], np.ndarray]:
            state = self._state()
            if packed["at"] is not state:
                packed["at"], packed["coefficients"] = state, fem.pack_coefficients(compiled)
            return packed["coefficients"]

        return coefficients


def cells_visited(form: fem.Form, comm: MPI.Comm) -> dict[str, int]:
    """How many distinct cells one assembly of ``form`` visits, over all ranks: with its cell
    integrals ("cell"), and through its exterior-facet integrals ("exterior_facet"); compare
    :meth:`Sample.cells_per_type <lungmech.rom.ecsw.Sample.cells_per_type>`."""
    compiled = form._cpp_object
    counts = {}
    for name, kind in (("cell", fem.IntegralType.cell), ("exterior_facet", fem.IntegralType.exterior_facet)):
        cells = [np.zeros(0, np.int32)]
        if kind in compiled.integral_types:
            for i in range(compiled.num_integrals(kind, 0)):
                entities = np.asarray(compiled.domains(kind, i)).reshape(-1)
                cells.append(entities if kind == fem.IntegralType.cell else entities[::2])
        counts[name] = comm.allreduce(len(np.unique(np.concatenate(cells))), op=MPI.SUM)
    return counts


def shaped(entries: list, shape: tuple[int, ...]) -> ufl.core.expr.Expr:
    """The expressions ``entries`` (flattened order) as one of ``shape`` (a scalar for ())."""
    return ufl.as_tensor(np.reshape(entries, shape).tolist()) if shape else entries[0]


class SampledIntegration:
    """The integrals of state-dependent load ``index``
    (:class:`~lungmech.fem.state_dependent.Integration`) on a hyper-reduced solver: the affine ones exactly in z = (q, imposed factors)
    — ``affine_basis`` the (start, directions) of z, ``z()`` its current value — from k + 2 full
    evaluations offline; the others over their ECSW sample by ``forms``; columns as Vᵀ b, over the
    sample of the integral they derive from (the load's own work: the load families'). ``basis``:
    the full basis (owned rows), for the affine integrals' constant columns. What the affine
    integrals need of the whole body, ``whole`` computes or gives back (:mod:`lungmech.rom.whole`),
    each under its own name: the load's index, the integral's, the call's kind and number."""

    def __init__(
        self,
        model: Model,
        basis: np.ndarray,
        forms: SampledForms,
        affine_basis: tuple[np.ndarray, np.ndarray],
        z: Callable[[], np.ndarray],
        index: int,
        integrals: dict[str, Integral],
        whole: Whole,
    ) -> None:
        self.model, self.basis, self.forms, self.affine_basis, self.z = model, basis, forms, affine_basis, z
        self.index, self.integrals, self.whole = index, integrals, whole
        self.comm = model.geometry.mesh.comm
        self._calls: dict[str, int] = {}

    def _whole(self, kind: str, name: str, compute: Callable[[], Arrays]) -> Arrays:
        """``compute()`` through :attr:`whole`, named by this load, ``name``, ``kind`` and the call's number."""
        key = f"load{self.index}/{name}/{kind}"
        number = self._calls[key] = self._calls.get(key, -1) + 1
        return self.whole.get(f"{key}{number}", compute)

    def vector(self, name: str, expr: ufl.core.expr.Expr, measure: ufl.Measure) -> Callable[[], np.ndarray]:
        if not self.integrals[name].affine:
            return self.forms.vector(f"load{self.index}_{name}", expr, measure)
        mesh = self.model.geometry.mesh
        f0, F1 = self._whole(
            "vector", name, lambda: affine(self.model, vector_integral(expr, measure, mesh), *self.affine_basis)
        )
        return lambda: (f0 + F1 @ self.z()).reshape(expr.ufl_shape)

    def _families(self, name: str) -> dict[str, str]:
        """The sample of each integral type a column of integral ``name`` is taken over: the
        load families' for the load's own work, the integral's own otherwise."""
        if name == "residual":
            return {"cell": "cell_load", "exterior_facet": "boundary_load"}
        family = f"load{self.index}_{name}"
        return {"cell": family, "exterior_facet": family}

    def columns(self, name: str, form: ufl.Form, constant: fem.Constant) -> Callable[[], np.ndarray]:
        if name == "residual" or not self.integrals[name].affine:
            return self.forms.columns(form, self._families(name), constant)

        # an affine integral's derivative is a constant in the state: its columns once, on the whole mesh
        def compute() -> Arrays:
            return (gram(self.basis, FullIntegration(self.model).columns(name, form, constant)(), self.comm),)

        (constant_columns,) = self._whole("columns", name, compute)
        return lambda: constant_columns

    def bilinear_columns(
        self, name: str, form: Bilinear, left: fem.Constant, right: fem.Constant
    ) -> Callable[[], tuple[np.ndarray, np.ndarray]]:
        if name != "residual" and self.integrals[name].affine:
            # columns of an affine integral are computed once, and these vary with the constants
            raise ParameterError(f"bilinear columns of the affine integral {name!r} are not available (sample it)")
        return self.forms.bilinear_columns(form, self._families(name), left, right)

    def column(self, name: str, form: ufl.Form) -> Callable[[], np.ndarray]:
        if name == "residual" or not self.integrals[name].affine:
            return self.forms.column(form, self._families(name))

        # the derivative of an affine integral is a constant: once, on the whole mesh
        def compute() -> Arrays:
            full = FullIntegration(self.model).column(name, form)()[:, None]
            return (gram(self.basis, full, self.comm)[:, 0],)

        (constant,) = self._whole("column", name, compute)
        return lambda: constant
