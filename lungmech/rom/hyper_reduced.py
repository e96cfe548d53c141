"""The hyper-reduced solver: Newton in q on a reduced mesh of an ECSW sample.

:class:`HyperReducedSolver` evaluates the sampled residual and tangent of
:mod:`lungmech.rom.ecsw` on a :class:`~lungmech.rom.reduced_mesh.ReducedMesh` of the sampled
cells, iterates on the reduced coordinates q and writes the model's full state only on request:
no online operation touches the full mesh. Loads whose coefficients are global functionals of
the state (balanced gravity) evaluate the integrals they declare through a
:class:`~lungmech.rom.sampled_forms.SampledIntegration`: exactly where they are affine in (q,
imposed factors), over their own ECSW sample otherwise.
"""

from __future__ import annotations

import functools
from typing import Protocol

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx import common, fem, la

from lungmech import jit
from lungmech.errors import ParameterError
from lungmech.fem.convergence import EPS, Fields
from lungmech.fem.limits import Inversion, at_quadrature_points, quadrature_degree, smallest
from lungmech.fem.model import Model
from lungmech.fem.sensitivity import DerivativeForms, ValueDerivatives, derivative_forms
from lungmech.fem.solver import NOT_CONVERGED, NewtonOptions, NewtonResult
from lungmech.parallel.linalg import LocalCSR, gram
from lungmech.rom.basis import Basis, dual, origin, reference_state
from lungmech.rom.ecsw import Sample, WeightedForms, over_cells, sampled_residual
from lungmech.rom.galerkin import check_basis, newton
from lungmech.rom.outputs import imposed_directions
from lungmech.rom.reduced_mesh import ReducedMesh
from lungmech.rom.sampled_forms import SampledForms, SampledIntegration
from lungmech.rom.whole import OnMesh, Whole

__all__ = ["HyperReducedSolver", "Sensitivities"]


class HyperReducedSolver:
    """Reduced Newton in q with ECSW: the residual and tangent integrate over the sampled cells
    (and their exterior facets) only, with their weights, on a :class:`ReducedMesh` of them, so
    that no online operation touches the full mesh. The solver's state is q; the model's state
    is written only when asked (:meth:`update_model`). Same interface as
    :class:`~lungmech.rom.galerkin.ReducedSolver` otherwise. Its forms over the sample are
    :attr:`forms` (:class:`~lungmech.rom.sampled_forms.SampledForms`); what one assembly of its
    residual visits, ``cells_visited(solver.residual_on_sample, comm)``.

    ``start`` is the full state the basis is relative to (default: the unloaded state).
    ``enrichment`` (owned rows): directions beyond the basis, whose sampled residual and tangent
    :meth:`enriched_terms` gives (the online error indicator's; the sample must be trained on
    them too). ``whole`` gives what only the whole body can (:mod:`lungmech.rom.whole`): by
    default computed on ``model``'s mesh; a model of a body's sampled cells alone
    (:mod:`lungmech.rom.body`) gets them stored, and is its own reduced mesh."""

    def __init__(
        self,
        model: Model,
        basis: Basis,
        sample: Sample,
        options: NewtonOptions | None = None,
        start: np.ndarray | None = None,
        enrichment: np.ndarray | None = None,
        whole: Whole | None = None,
    ) -> None:
        check_basis(model, basis)
        self.model, self.basis, self.sample = model, basis, sample
        self.options = options or NewtonOptions()
        self.comm = model.geometry.mesh.comm
        forms = WeightedForms(model)
        if missing := [name for name in forms.sampled if name not in sample.cells and name not in forms.functionals]:
            raise ParameterError(
                f"the ECSW sample has no cells for {', '.join(missing)}: it was trained on another model (train it again)"
            )
        if any(term.bind is None for term in model.state_dependent):
            raise ParameterError(
                "ECSW reduces state-dependent loads that declare their integrals (bind); this one does not"
            )
        for family, weight in forms.weights.items():
            weight.x.array[:] = 0.0
            if family in sample.cells:
                weight.x.array[sample.cells[family]] = sample.weights[family]
            weight.x.scatter_forward()
        restricted = self._restricted = sampled_residual(forms, model.geometry.mesh, sample)
        self._weights = forms  # the forms reach the weights' Functions: keep them alive
        self.reference = reference_state(model) if start is None else np.array(start, dtype=float)
        self.whole = whole if whole is not None else OnMesh(imposed_directions(model, self.reference))
        cells = np.concatenate([*sample.cells.values(), np.zeros(0, np.int32)])
        self.mesh = reduced = ReducedMesh(model, cells)
        self.residual_on_sample = self._residual = reduced.form(restricted)  # (cells_visited counts it)
        self._jacobian = reduced.form(ufl.derivative(restricted, model.state, ufl.TrialFunction(model.space)))
        self._vector = fem.assemble_vector(self._residual)
        sampled = {name: form for name, form in forms.functionals.items() if name in sample.cells}
        energy = "strain_energy"  # its form on the sample: the sensitivities differentiate it
        self._energy = (
            over_cells(sampled[energy], model.geometry.mesh, sample.cells[energy]) if energy in sampled else None
        )
        self._matrix = fem.create_matrix(self._jacobian, block_mode=la.BlockMode.expanded)
        self.V = reduced.restrict_columns(np.ascontiguousarray(basis.vectors))  # sub dofs, ghosts too
        # Each rank reduces its own cells' contributions, ghost rows included, and one Allreduce
        # sums them: no ghost exchange. The matrix numbers its rows and columns its own way.
        self._rows, self._columns = (_positions(self._matrix.index_map(i), reduced.space) for i in (0, 1))
        self._row_basis, self._column_basis = self.V[self._rows], self._on_columns(self.V)
        self.W = None if enrichment is None else reduced.restrict_columns(np.ascontiguousarray(enrichment))
        # U = [V W] on the sub dofs, the matrix's rows and its columns: the enriched terms'
        U = None if self.W is None else np.hstack([self.V, self.W])
        self._enriched = None if U is None else (U, U[self._rows], self._on_columns(U))
        self.forms = SampledForms(model, reduced, forms.weights, sample, self.V, lambda: self._q)
        self._functionals = self.forms.scalars(sampled)
        self._tangent = LocalCSR(self._matrix)  # shares the matrix's values
        # x₀ = r + D a on the reduced mesh, a the imposed displacements' factors of the current loads
        start_state, imposed, self._constraints = self.whole.imposed()
        self._r, self._D = reduced.restrict(start_state), reduced.restrict(imposed)
        self._origin = self._r + self._D @ model.imposed_amplitudes()[self._constraints]
        degree = quadrature_degree(model)
        maps = None if reduced.entity_map is None else [reduced.entity_map]  # F of an image reads ξ of the mesh
        self._gradient = at_quadrature_points(reduced.expression(model.F), reduced.mesh, degree, entity_maps=maps)
        jacobians = at_quadrature_points(reduced.expression(ufl.det(model.F)), reduced.mesh, degree, entity_maps=maps)
        # J > 0 is checked where the model is evaluated: on the sampled cells
        self.inversion = Inversion(model, smallest(jacobians, self.comm))
        cell_size = self.whole.get("cell_size", lambda: (np.array(Fields(model).cell_size),))[0]
        self._magnitude = _displacement_magnitude(model, reduced, float(cell_size))
        self.coordinates = np.zeros(basis.size)  # at the start state (set_state(project()) follows a moved model)
        self._q = self.coordinates.copy()  # where the reduced mesh's state is
        self._works: list[np.ndarray] = []  # Vᵀ ∂W/∂θ of each state-dependent load, at the last tangent
        # what the residual vector and the tangent hold: the model's loading they were assembled
        # at, the q of the residual, whether there is a tangent (at the end of a Newton solve: its
        # last residual at the answer, its last tangent at the iterate before)
        self._assembled = _Assembled()
        # state-dependent loads (balanced gravity): their coefficients from affine integrals in
        # z = (q, imposed factors), exactly, and from the others' samples on the reduced mesh
        self._coupled: list[_Coupled] = []
        if model.state_dependent:
            affine_basis = start_state, np.hstack([basis.vectors, imposed[: basis.vectors.shape[0]]])
            for index, term in enumerate(model.state_dependent):
                assert term.bind is not None  # (refused above otherwise)
                integration = SampledIntegration(
                    model, basis.vectors, self.forms, affine_basis, self._z, index, term.integrals, self.whole
                )
                self._coupled.append(term.bind(integration))
        self.description = (
            f"hyper-reduced (ECSW, τ = {sample.tolerance:g}): {basis.kind} basis of {basis.size} vectors, "
            + sample.described(self.comm)
        )
        self.iterations_total = 0

    @property
    def state(self) -> np.ndarray:
        """The reduced coordinates q (the load stepping keeps and extrapolates these)."""
        return self.coordinates

    def set_state(self, state: np.ndarray) -> None:
        self.coordinates[:] = state

    def set_start(self, start: np.ndarray) -> None:
        """The basis relative to ``start`` (a full local state array) from now on, and q = 0:
        where a start found anew at every μ puts it (an imaged body's, :mod:`lungmech.rom.imaged`;
        its imposed directions D stay, r is ``start`` with the imposed dofs at 0). O(the model's
        mesh): a body's sampled cells, online."""
        self.reference = np.array(start, dtype=float)
        self._r = self.mesh.restrict(imposed_directions(self.model, self.reference)[0])
        self.coordinates[:] = 0.0
        self._assembled = _Assembled()  # the forms' coefficients may have moved (ξ), not the loading

    def reconstruct(self, q: np.ndarray) -> None:
        """Set q, and the model's state to x₀ + V q at its current time."""
        self.set_state(q)
        self.update_model()

    def update_model(self) -> None:
        """Set the model's state to x₀ + V q, and the coefficients of its state-dependent loads
        to the full model's Θ(x) (this solver sets them from its sample while it iterates), so
        that what reads the model's forms next (a reaction, a diagnosis) sees a consistent
        model. The only O(mesh) operation; collective."""
        state = self.model.state.x
        owned = self.basis.vectors.shape[0]
        state.array[:] = origin(self.model, self.reference)
        state.array[:owned] += self.basis.vectors @ self.coordinates
        state.scatter_forward()
        for term in self.model.state_dependent:
            term.update()

    def project(self) -> np.ndarray:
        """Coordinates q of the model's current state, (W V)ᵀ (x − x₀): where to start from after
        moving the model (O(mesh); collective)."""
        return _projection(self.model, self.basis, self.reference)

    def deformation_gradient(self) -> np.ndarray:
        """F at the quadrature points of the sampled cells, (cells, points, d, d)."""
        self._at(self.coordinates)
        return self._gradient()

    def start_path(self) -> None:
        """A new load path begins (each reduced solve scales its own residual)."""

    def solve(self, start: np.ndarray | None = None) -> NewtonResult:
        """One reduced Newton solve at the model's current loads from q, or from ``start`` (q)."""
        self._at_loads()
        q, converged, iterations, residuals, reason = newton(
            self, self.coordinates if start is None else np.array(start, dtype=float), self.options
        )
        self.iterations_total += iterations
        converged = converged and bool(np.all(np.isfinite(q)))
        if converged and (wrong := self.inversion()):
            converged, reason = False, f"{reason} to {wrong}"
        self.coordinates[:] = q  # a failed iterate too, as a full solver's state: the stepping restores
        return NewtonResult(converged, iterations, tuple(residuals), reason)

    def linear_step(self) -> None:
        """One reduced Newton step from q at the current loads (no line search)."""
        self._at_loads()
        r = self.reduced_residual(self.coordinates)
        try:
            step = np.linalg.solve(self.reduced_jacobian(), -r)
        except np.linalg.LinAlgError:  # a singular reduced tangent: as the full solver says it
            raise PETSc.Error(NOT_CONVERGED) from None
        self.coordinates += step

    def functionals(self, q: np.ndarray) -> dict[str, float]:
        """The sampled functionals (:attr:`lungmech.rom.ecsw.WeightedForms.functionals`: the
        strain energy, the numerators of the formulation's averages), each Σ_e ξ_e f_e(x₀ + V q) over its sample, at the loads of the
        moment, by name: those the sample has cells for (collective)."""
        self._at(q)
        return self._functionals()

    def update_coefficients(self) -> None:
        """θ = Θ(x₀ + V q) of the state-dependent loads at the current q and values, from the
        sample (collective)."""
        self._at(self.coordinates)
        for term in self._coupled:
            term.update()

    @functools.cached_property
    def sensitivities(self) -> Sensitivities:
        """The derivatives of this model's own answer with respect to μ (compiled on first use)."""
        return Sensitivities(self)

    def _start_derivatives(self, derivatives: ValueDerivatives) -> np.ndarray:
        """dx₀/dμ = D da/dμ on the reduced mesh (its dofs, parameters): from the imposed
        displacements' directions, which a body of sampled cells holds whole; and a start found
        at every μ, its own (an imaged body's other fields: ``derivatives.start``)."""
        imposed = self._D @ derivatives.amplitudes[self._constraints]
        return imposed if derivatives.start is None else imposed + self.mesh.restrict(derivatives.start)

    def _at_loads(self) -> None:
        """x₀ = r + D a on the reduced mesh, a the imposed displacements' factors of the current
        loads."""
        self._origin = self._r + self._D @ self.model.imposed_amplitudes()[self._constraints]

    def _on_columns(self, x: np.ndarray) -> np.ndarray:
        """Rows of ``x`` (on the sub dofs) on the matrix's columns: 0 on its extra ghost columns,
        which only other ranks' rows reach."""
        found = self._columns >= 0
        shape = (len(self._columns), *x.shape[1:])
        on_columns = np.zeros(shape)
        on_columns[found] = x[self._columns[found]]
        return on_columns

    def _set(self, q: np.ndarray) -> None:
        """The reduced mesh's state x₀ + V q, x₀ at the loads of the last :meth:`_at_loads`."""
        self._q = np.array(q, dtype=float)
        self.mesh.state.x.array[:] = self._origin + self.V @ q

    def _z(self) -> np.ndarray:
        """z = (q, imposed factors) of the reduced mesh's state."""
        return np.concatenate([self._q, self.model.imposed_amplitudes()[self._constraints]])

    def _at(self, q: np.ndarray) -> None:
        """The reduced mesh's state x₀ + V q at the current loads (outside a solve, where they may
        have moved since: a new time, new parameters)."""
        self._at_loads()
        self._set(q)

    def reduced_residual(self, q: np.ndarray) -> np.ndarray:
        """Σ_e ξ_e Vᵀ r_e(x₀ + V q) over the sample (sets the reduced mesh's state); state-dependent
        loads with θ = Θ(q), balanced exactly at every iterate."""
        self._set(q)
        for term in self._coupled:
            term.update()
        b = self._vector.array
        b[:] = 0.0
        fem.assemble_vector(b, self._residual)  # type: ignore[arg-type]  # the into-an-array overload (singledispatch) is not in the hints
        self._assembled.residual(self.model.loading, self._q)
        return gram(self.V, b[:, None], self.comm)[:, 0]

    def enriched_terms(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, Σ_e ξ_e Uᵀ r_e, Σ_e ξ_e Uᵀ K_e U) at the current q, U = [V W] the basis and its
        enrichment W: the sampled residual and tangent of the enriched space, on the reduced mesh
        (collective). Right after a solve, its last residual (at the answer) and its last
        tangent (at the iterate before: an indicator needs no quadratic convergence) serve, as
        assembled; else both are assembled at q."""
        if not self._assembled.holds(self.model.loading, self.coordinates):
            self._at(self.coordinates)
            self.reduced_residual(self.coordinates)
            self._matrix.set_value(0.0)
            fem.assemble_matrix(self._matrix, self._jacobian)  # type: ignore[arg-type]  # the into-a-matrix overload (singledispatch) is not in the hints
            self._assembled.tangent(self.model.loading)
        assert self._enriched is not None, "enriched terms need an enrichment"
        U, on_rows, on_columns = self._enriched
        r = gram(U, self._vector.array[:, None], self.comm)[:, 0]
        return self.coordinates.copy(), r, gram(on_rows, self._tangent @ on_columns, self.comm)

    def reduced_jacobian(self) -> np.ndarray:
        """Σ_e ξ_e Vᵀ K_e V at the reduced mesh's state, plus the state-dependent loads' low-rank
        term −(Vᵀ ∂W/∂θ)(Vᵀ dΘ/du)ᵀ (:mod:`lungmech.fem.state_dependent`)."""
        self._matrix.set_value(0.0)
        fem.assemble_matrix(self._matrix, self._jacobian)  # type: ignore[arg-type]  # the into-a-matrix overload, as above
        self._assembled.tangent(self.model.loading)
        reduced = gram(self._row_basis, self._tangent @ self._column_basis, self.comm)
        self._works = []
        for term in self._coupled:
            work, gradient = term.linearise()
            reduced -= work @ gradient.T
            self._works.append(work)
        return reduced

    def floor(self) -> float:
        """‖|V|ᵀ ε|K|s‖, s = |x| + h on the displacement: the round-off floor of the reduced
        residual (see :mod:`lungmech.fem.convergence`), at the last tangent's state."""
        s = np.abs(self.mesh.state.x.array) + self._magnitude
        rounding = EPS * (abs(self._tangent) @ self._on_columns(s))
        floor = float(np.linalg.norm(gram(np.abs(self._row_basis), rounding[:, None], self.comm)))
        # and that of state-dependent coefficients θ (balanced gravity: a KKT solve), through ∂r/∂θ
        return floor + sum(float(np.linalg.norm(np.abs(w) @ t.rounding())) for w, t in zip(self._works, self._coupled))

    @functools.cached_property
    def residual_form(self) -> fem.Form:
        """The full model's compiled residual (for a diagnosis of a failed load path)."""
        return jit.form(self.model.residual)

    @functools.cached_property
    def jacobian_form(self) -> fem.Form:
        """The full model's compiled tangent."""
        return jit.form(self.model.jacobian)

    def destroy(self) -> None:
        """Nothing PETSc holds: the reduced mesh's vectors and matrices are DOLFINx's."""


class Sensitivities:
    """The exact derivatives of a :class:`HyperReducedSolver`'s own answer with respect to μ:
    its state's (:meth:`state`) and its sampled strain energy's (:meth:`energy`), from its
    sampled residual, tangent and energy on the reduced mesh (collective)."""

    def __init__(self, solver: HyperReducedSolver) -> None:
        self.solver = solver
        # ∂/∂c of the sampled residual and strain energy, and the energy's gradient, on the reduced
        # mesh; without the energy's sample (an imaged body's inverse motion) the residual's alone
        self.forms = DerivativeForms(
            solver.model,
            solver._restricted,
            solver._energy,
            solver.mesh.form,
            derivative_forms(solver.model),
            with_energy=solver._energy is not None,
        )

    def state(self, derivatives: ValueDerivatives) -> np.ndarray:
        """dq/dμ = −J⁻¹ (∂r/∂μ + Vᵀ K dx₀/dμ) at the current q, J, r and K those of the sample:
        the exact derivative of this model's own answer, (k, parameters). Collective."""
        solver, forms = self.solver, self.forms
        solver.update_coefficients()
        jacobian = solver.reduced_jacobian()  # and K on the reduced mesh, at q (with θ's low rank)
        start = solver._start_derivatives(derivatives)
        if solver._coupled and _moves_the_body(solver, start):
            raise ParameterError(
                "sensitivities of a hyper-reduced model with balanced gravity: a parameter moves its start's "
                "displacement (an imposed displacement), which the sampled coefficients' derivative does not follow"
            )
        imposed = solver._on_columns(start)
        rhs = gram(solver._row_basis, solver._tangent @ imposed, solver.comm)
        b = solver._vector.array
        solver._assembled.forget_residual()
        for i in range(len(derivatives.names) if forms.residual is not None else 0):
            assert forms.residual is not None  # (the loop runs only then)
            forms.set_weights(derivatives, i)
            b[:] = 0.0
            fem.assemble_vector(b, forms.residual)  # type: ignore[arg-type]  # the into-an-array overload (singledispatch) is not in the hints
            rhs[:, i] += gram(solver.V, b[:, None], solver.comm)[:, 0]
        return -np.linalg.solve(jacobian, rhs)

    def energy(self, dq: np.ndarray, derivatives: ValueDerivatives) -> np.ndarray:
        """dẼ/dμ = ∇Ẽ · (V dq/dμ + dx₀/dμ) + Σ_k ∂Ẽ/∂c_k ∂c_k/∂μ of the sampled strain energy Ẽ
        at the current q, (parameters,). Collective."""
        solver, forms = self.solver, self.forms
        if forms.energy_gradient is None:
            raise ParameterError("sensitivities need the strain energy's ECSW sample (train it)")
        solver._at(solver.coordinates)
        g = solver._vector.array
        solver._assembled.forget_residual()
        g[:] = 0.0
        fem.assemble_vector(g, forms.energy_gradient)  # type: ignore[arg-type]  # the into-an-array overload, as above
        total = gram(solver.V, g[:, None], solver.comm)[:, 0] @ dq
        total = total + gram(g[:, None], solver._start_derivatives(derivatives), solver.comm)[0]
        for i in range(len(derivatives.names) if forms.energy is not None else 0):
            assert forms.energy is not None  # (the loop runs only then)
            forms.set_weights(derivatives, i)
            total[i] += solver.comm.allreduce(fem.assemble_scalar(forms.energy), op=MPI.SUM)
        return total


class _Coupled(Protocol):
    """A state-dependent load bound to the solver's integration (``StateDependentWork.bind``)."""

    def update(self) -> None: ...

    def linearise(self) -> tuple[np.ndarray, np.ndarray]: ...

    def rounding(self) -> np.ndarray: ...


class _Assembled:
    """What the solver's residual vector and tangent matrix hold: both at one loading of the
    model (:attr:`lungmech.fem.model.Model.loading`), the residual at ``at``."""

    loading: int | None
    at: np.ndarray | None

    def __init__(self) -> None:
        self.loading, self.at, self.has_tangent = None, None, False

    def residual(self, loading: int, q: np.ndarray) -> None:
        if loading != self.loading:
            self.loading, self.has_tangent = loading, False
        self.at = q

    def tangent(self, loading: int) -> None:
        if loading != self.loading:
            self.loading, self.at = loading, None
        self.has_tangent = True

    def holds(self, loading: int, q: np.ndarray) -> bool:
        """Both a residual at ``q`` and a tangent, at ``loading``."""
        return loading == self.loading and self.has_tangent and self.at is not None and np.array_equal(self.at, q)

    def forget_residual(self) -> None:
        """The residual vector was used for something else."""
        self.at = None


def _positions(index_map: common.IndexMap, space: fem.FunctionSpace) -> np.ndarray:
    """For each local index of a matrix's (expanded) row or column ``index_map``, the local sub
    dof of ``space`` with the same global number (unrolled), or -1."""
    dofs, bs = space.dofmap.index_map, space.dofmap.index_map_bs
    blocks = dofs.local_to_global(np.arange(dofs.size_local + dofs.num_ghosts, dtype=np.int32))
    numbers = (bs * blocks[:, None] + np.arange(bs)).reshape(-1)
    wanted = index_map.local_to_global(np.arange(index_map.size_local + index_map.num_ghosts, dtype=np.int32))
    order = np.argsort(numbers)
    at = np.minimum(np.searchsorted(numbers[order], wanted), len(numbers) - 1)
    return np.where(numbers[order][at] == wanted, order[at], -1)


def _moves_the_body(solver: HyperReducedSolver, start: np.ndarray) -> bool:
    """Whether dx₀/dμ (the reduced mesh's dofs × parameters) has a displacement part on any rank."""
    reduced = solver.mesh
    rows = reduced.space.sub(0).collapse()[1] if solver.model.multi_field else slice(None)
    local = float(np.abs(start[rows]).max(initial=0.0))
    return solver.comm.allreduce(local, op=MPI.MAX) > 0.0


def _displacement_magnitude(model: Model, reduced: ReducedMesh, h: float) -> np.ndarray:
    """``h`` (the whole mesh's smallest cell size) on the sub dofs of the displacement, 0 on
    other fields: what F's rounding adds to |x|."""
    if not model.multi_field:
        return np.full(len(reduced.parent_dofs), h)
    magnitude = np.zeros(len(reduced.parent_dofs))
    magnitude[reduced.space.sub(0).collapse()[1]] = h
    return magnitude


def _projection(model: Model, basis: Basis, reference: np.ndarray) -> np.ndarray:
    """q of the model's current state: (W V)ᵀ (x − x₀) (collective)."""
    owned = basis.vectors.shape[0]
    x = model.state.x.array[:owned] - origin(model, reference)[:owned]
    return gram(dual(model, basis), x[:, None], model.geometry.mesh.comm)[:, 0]
