"""Energy-conserving sampling and weighting (ECSW): the reduced residual from a few weighted cells.

The reduced residual sums every cell's contribution,

.. math:: Vᵀ R(x) = Σ_e Vᵀ r_e(x),

r_e from the integrals over cell e, in three families sampled apart: its internal forces (of
the energy density), the loads on it (weight) and on its exterior facets (pressures). ECSW (Farhat, Chapman & Avery 2015) keeps a sample
E of each with weights ξ_e > 0,

.. math:: Vᵀ R(x) ≈ Σ_{e∈E} ξ_e Vᵀ r_e(x),

chosen on training states x_s so that their reduced forces are reproduced to a tolerance τ:

.. math:: ‖G ξ − b‖ ≤ τ ‖b‖,   G_{(s, i), e} = (Vᵀ r_e(x_s))_i / ‖b_s‖,   b = G 1,

each state's block scaled by its own reduced force b_s, so that every state counts alike. The
internal forces (of the energy density) and the loads are sampled apart, as in Farhat et al.:
at an equilibrium their sum, the residual, vanishes, and would leave nothing to reproduce. This
is a sparse non-negative least-squares problem, solved by the greedy Lawson–Hanson variant of
Chapman et al. (2017, IJNME 109), which stops as soon as τ is met (:func:`sparse_nnls`). Weights
that are positive keep the reduced tangent a positively weighted sum of cell tangents, so a
hyper-reduced model of a stable, conservative full model stays stable and conservative (the
"energy-conserving" of the name).

A load whose coefficients are global functionals of the state (balanced gravity, see
:mod:`lungmech.fem.state_dependent`) declares the integrals they come from: the affine ones are
evaluated exactly from (q, imposed factors), the others are sampled like functionals (vector
valued: the pressure's 54 response entries per training state), and its rank-12 tangent term
comes from the same samples (:class:`_SampledIntegration`).

The weights enter the forms as piecewise-constant (DG0) fields, one per family (an exterior
facet has one cell, whose weight it takes): the same
forms give the Galerkin reduced model (all weights 1), the training matrix G (their derivative
with respect to the weights: column e is r_e), and, integrated over the sampled cells only, the
hyper-reduced one (:class:`HyperReducedSolver`).
"""

from __future__ import annotations

import contextlib
import functools
import time
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import ufl
from dolfinx import fem, la
from dolfinx import mesh as dmesh
from dolfinx.fem.petsc import assemble_matrix, create_matrix
from mpi4py import MPI
from petsc4py import PETSc

from lungmech.errors import ParameterError
from lungmech.fem.convergence import EPS, Fields
from lungmech.fem.limits import Inversion, at_quadrature_points, quadrature_degree, smallest
from lungmech.fem.quantities import vector_integral
from lungmech.fem.sensitivity import DerivativeForms, ValueDerivatives, derivative_forms
from lungmech.fem.solver import NOT_CONVERGED, NewtonOptions, NewtonResult
from lungmech.fem.state_dependent import FullIntegration, StateDependent
from lungmech.parallel.linalg import apply, gram
from lungmech.rom.basis import inner_product, origin, reference_state
from lungmech.rom.galerkin import check_basis, newton
from lungmech.rom.outputs import affine, imposed_directions
from lungmech.rom.reduced_mesh import ReducedMesh

__all__ = [
    "FAMILIES",
    "FUNCTIONALS",
    "HyperReducedSolver",
    "Sample",
    "Training",
    "WeightedForms",
    "sparse_nnls",
    "train",
]

# The families sampled, each with its own weights, and their integral type: the cells' internal
# forces (of the energy density), the loads on cells (weight) and on the boundary (pressures).
FAMILIES = {"internal": "cell", "cell_load": "cell", "boundary_load": "exterior_facet"}
# Scalar functionals (cell integrals) sampled the same way, for outputs: their cells' values are
# the columns, each training state one row scaled by the functional's value there.
FUNCTIONALS = ("strain_energy",)


class WeightedForms:
    """The model's residual R = R_int + R_load with a weight per cell on each family's integrals.

    ``weights[family]`` is the DG0 field of that family's weights (1 everywhere: ``residual`` is
    the model's). :meth:`contribution` is the derivative with respect to one family's weights,
    a rectangular form whose assembled column e is the residual of cell e's integrals of that
    family (an exterior facet's: of its one cell). ``functionals`` are the scalar outputs
    sampled alike (:data:`FUNCTIONALS`: the strain energy ∫ ψ dX), with weights of their own."""

    def __init__(self, model):
        parts = {
            "internal": _integrals(model.internal_residual, "cell"),
            "cell_load": _integrals(model.load_residual, "cell"),
            "boundary_load": _integrals(model.load_residual, "exterior_facet"),
        }
        kinds = {i.integral_type() for form in (model.internal_residual, model.load_residual) for i in form.integrals()}
        if unsupported := kinds - {"cell", "exterior_facet"}:
            raise ParameterError(
                f"ECSW samples cell and exterior-facet integrals; this residual also has {sorted(unsupported)}"
            )
        self.space = space = fem.functionspace(model.geometry.mesh, ("DG", 0))
        # the integrals state-dependent loads compute their coefficients from (balanced gravity:
        # the pressure's response), but the affine ones, which a reduced model evaluates exactly
        self.integrals = {
            f"load{index}_{name}": integral
            for index, term in enumerate(model.state_dependent)
            for name, integral in term.integrals.items()
            if not integral.affine
        }
        names = (*FAMILIES, *FUNCTIONALS, *self.integrals)
        self.weights = {name: fem.Function(space, name=f"{name}_weight") for name in names}
        for weight in self.weights.values():
            weight.x.array[:] = 1.0
        self.families = tuple(family for family, integrals in parts.items() if integrals)
        self.parts = {
            family: [i.reconstruct(integrand=self.weights[family] * i.integrand()) for i in parts[family]]
            for family in self.families
        }
        self.residual = ufl.Form([i for family in self.families for i in self.parts[family]])
        self.functionals = {"strain_energy": self.weights["strain_energy"] * model.energy_density * model.dx}

    def contribution(self, name: str) -> ufl.Form:
        """∂R_ξ/∂ξ_family: column e is the residual of cell e's ``family`` integrals; for a
        functional, entry e is its integral over cell e."""
        if name in self.functionals:
            return ufl.derivative(self.functionals[name], self.weights[name], ufl.TestFunction(self.space))
        return ufl.derivative(ufl.Form(self.parts[name]), self.weights[name], ufl.TrialFunction(self.space))

    @property
    def sampled(self) -> tuple[str, ...]:
        """Every family, functional and state-dependent load's integral that gets a sample."""
        return (*self.families, *self.functionals, *self.integrals)

    def cell_values(self, name: str) -> tuple[ufl.Form, fem.FunctionSpace]:
        """A form whose assembled vector holds each cell's contribution to the integral ``name``
        (its entries flattened: a DG0 field with as many components), and its space."""
        integral = self.integrals[name]
        flat = _flat(integral.expr)
        mesh = self.space.mesh
        space = fem.functionspace(mesh, ("DG", 0, (flat.ufl_shape[0],)))
        return ufl.inner(flat, ufl.TestFunction(space)) * integral.measure, space


def _flat(expr) -> ufl.core.expr.Expr:
    """A vector of the entries of a scalar, vector or tensor expression."""
    shape = expr.ufl_shape
    if len(shape) == 1:
        return expr
    return ufl.as_vector([expr[index] for index in np.ndindex(shape)] if shape else [expr])


def _integrals(form: ufl.Form, kind: str) -> list:
    return [integral for integral in form.integrals() if integral.integral_type() == kind]


class Training:
    """The matrix G of ECSW, one training state at a time (collective).

    Each :meth:`add` takes the model's current state and loads: for every family, the reduced
    contributions Vᵀ r_e of the owned cells, scaled by the family's reduced force ‖b_s‖ (the
    internal forces and the loads each: they balance at an equilibrium, neither vanishes); for
    every functional, its cells' values scaled by its value. A family without force at a state
    (at rest; a load not applied yet) skips it.
    """

    def __init__(self, model, V: np.ndarray):
        self.model, self.V = model, np.ascontiguousarray(V)
        self.forms = WeightedForms(model)
        self.comm = model.geometry.mesh.comm
        self._state_dependent = StateDependent(model)
        self._integrals = {}
        for name in self.forms.integrals:
            form, space = self.forms.cell_values(name)
            self._integrals[name] = (fem.form(form), fem.Function(space).x, space.dofmap.index_map_bs)
        names = (*self.forms.families, *self.forms.functionals)
        self._compiled = {name: fem.form(self.forms.contribution(name)) for name in names}
        self._matrices = {family: create_matrix(self._compiled[family]) for family in self.forms.families}
        self.cells = self.forms.space.dofmap.index_map.size_local
        self.blocks: dict[str, list[np.ndarray]] = {name: [] for name in self.forms.sampled}
        rows, k = self.V.shape  # V as a distributed dense matrix, wrapping self.V's memory
        self._basis = PETSc.Mat().createDense(((rows, None), (None, k)), array=self.V, comm=self.comm)

    def add(self) -> bool:
        """Add the model's current state (True), or skip it when its reduced force is 0 (False)."""
        self._state_dependent.update()  # θ = Θ(x) of this state, as a solve would have it
        local = {}
        for name, (form, vector, size) in self._integrals.items():  # each cell's entries of the integral
            vector.array[:] = 0.0
            fem.assemble_vector(vector.array, form)
            vector.scatter_reverse(la.InsertMode.add)  # a facet's contribution to its cell's owner
            local[name] = vector.array[: self.cells * size].reshape(self.cells, size).T.copy()
        for name in self.forms.functionals:  # a DG0 vector: entry e is cell e's integral
            local[name] = fem.assemble_vector(self._compiled[name]).array[None, : self.cells].copy()
        for family in self.forms.families:
            form, C = self._compiled[family], self._matrices[family]
            C.zeroEntries()
            assemble_matrix(C, form)
            C.assemble()
            product = C.transposeMatMult(self._basis)  # (cells × k): row e is (Vᵀ r_e)ᵀ
            local[family] = product.getDenseArray()[: self.cells].T.copy()
            product.destroy()
        added = False
        for family, block in local.items():
            scale = float(np.linalg.norm(self.comm.allreduce(block.sum(axis=1), op=MPI.SUM)))
            if scale > 0.0:
                self.blocks[family].append(block / scale)
                added = True
        return added

    def add_state(self, state: np.ndarray, time: float, load_factor: float = 1.0) -> bool:
        """Set the model to a stored state (its whole local array) at its time and load factor,
        then :meth:`add` it."""
        self.model.state.x.array[:] = state
        self.model.state.x.scatter_forward()
        self.model.set_time(time, load_factor=load_factor)
        return self.add()

    @contextlib.contextmanager
    def watching(self, solver) -> Iterator[Training]:
        """Within the block, :meth:`add` every Newton iterate of ``solver`` (a full
        :class:`~lungmech.fem.solver.NewtonSolver`): the states an online Newton passes through,
        not only the converged ones, so that the sample also reproduces the reduced forces away
        from equilibrium. Each iterate is added at the solver's loads of the moment."""
        active, training = [True], weakref.ref(self)  # PETSc keeps the monitor: it must not keep us

        def add_iterate(snes, iteration, norm) -> None:
            if active[0] and (this := training()) is not None:
                x, state = snes.getSolution(), this.model.state
                state.x.array[: x.getLocalSize()] = x.getArray(readonly=True)
                state.x.scatter_forward()
                this.add()

        solver.problem.solver.setMonitor(add_iterate)
        try:
            yield self
        finally:
            active[0] = False

    @property
    def states(self) -> int:
        """The most training states any family holds."""
        return max((len(blocks) for blocks in self.blocks.values()), default=0)

    def matrix(self, family: str) -> np.ndarray:
        """G of one family: rows (state, reduced component), columns the owned cells."""
        if not self.blocks[family]:
            raise ParameterError(f"ECSW has no training state with a load on its {family} integrals (add states first)")
        return np.vstack(self.blocks[family])

    def sample(self, tolerance: float) -> Sample:
        """The sparse positive weights of each family that reproduce the training reduced forces
        to ``tolerance`` (relative, per family), see :func:`sparse_nnls`."""
        if not self.states:
            raise ParameterError("ECSW has no training state with a load (add states first)")
        chosen = {name: sparse_nnls(self.matrix(name), tolerance, self.comm) for name in self.forms.sampled}
        return Sample(
            {family: cells for family, (cells, _) in chosen.items()},
            {family: weights for family, (_, weights) in chosen.items()},
            tolerance,
        )

    def destroy(self) -> None:
        for matrix in (*self._matrices.values(), self._basis):
            matrix.destroy()


def train(
    model, basis, solver, runs: Callable[[], object], tolerance: float, timings: dict[str, float] | None = None
) -> Sample:
    """The ECSW sample of ``model`` on ``basis`` at ``tolerance``, trained on every Newton
    iterate (converged states included) ``solver`` takes while ``runs()`` drives it along the
    training load paths. ``timings``, if given, receives the seconds of the training pass and of
    the NNLS. Collective."""
    tic = time.perf_counter()
    training = Training(model, basis.vectors)
    try:
        with training.watching(solver):
            runs()
        seconds = {"ecsw_training": time.perf_counter() - tic}
        tic = time.perf_counter()
        sample = training.sample(tolerance)
        seconds["nnls"] = time.perf_counter() - tic
    finally:
        training.destroy()
    if timings is not None:
        timings.update(seconds)
    return sample


@dataclass(frozen=True)
class Sample:
    """The sampled owned cells of each family (local indices) and their weights (> 0)."""

    cells: dict[str, np.ndarray]
    weights: dict[str, np.ndarray]
    tolerance: float

    def count(self, comm: MPI.Comm) -> dict[str, int]:
        """How many cells each family samples, over all ranks."""
        return {family: comm.allreduce(len(cells), op=MPI.SUM) for family, cells in self.cells.items()}

    def cells_per_type(self, comm: MPI.Comm) -> dict[str, int]:
        """How many distinct cells the residual's sample holds per integral type, over all ranks
        (what a Newton iteration assembles; the functionals' samples are assembled for outputs)."""
        counts = {}
        for kind in ("cell", "exterior_facet"):
            cells = [c for family, c in self.cells.items() if FAMILIES.get(family) == kind]
            mine = len(np.unique(np.concatenate(cells))) if cells else 0
            counts[kind] = comm.allreduce(mine, op=MPI.SUM)
        return counts

    def export(self, mesh) -> dict[str, np.ndarray]:
        """The sample in a partition-independent form, the same on every rank (collective): per
        family, the input (mesh-file) indices of the sampled cells, sorted, and their weights;
        arrays named ``<family>_cells`` and ``<family>_weights``."""
        original = np.asarray(mesh.topology.original_cell_index, dtype=np.int64)
        data = {}
        for family, cells in self.cells.items():
            pairs = mesh.comm.allgather((original[cells], self.weights[family]))
            indices = np.concatenate([i for i, _ in pairs])
            order = np.argsort(indices)
            data[f"{family}_cells"] = indices[order]
            data[f"{family}_weights"] = np.concatenate([w for _, w in pairs])[order]
        return data

    @staticmethod
    def place(mesh, data: dict[str, np.ndarray], tolerance: float) -> Sample:
        """The sample :meth:`export` gave, on this mesh and partition: each rank keeps its owned
        cells. Collective; a cell index the mesh does not have is an error."""
        owned = mesh.topology.index_map(mesh.topology.dim).size_local
        original = np.asarray(mesh.topology.original_cell_index, dtype=np.int64)[:owned]
        local = np.argsort(original)
        cells, weights = {}, {}
        for family in sorted(name[: -len("_cells")] for name in data if name.endswith("_cells")):
            wanted, given = np.asarray(data[f"{family}_cells"]), np.asarray(data[f"{family}_weights"])
            found = np.isin(wanted, original)
            if mesh.comm.allreduce(int(found.sum()), op=MPI.SUM) != len(wanted):
                raise ParameterError(f"the ECSW sample ({family} integrals) names input cells this mesh does not have")
            position = local[np.searchsorted(original[local], wanted[found])]
            order = np.argsort(position)
            cells[family] = position[order].astype(np.int32)
            weights[family] = given[found][order]
        return Sample(cells, weights, tolerance)

    @staticmethod
    def every_cell(forms: WeightedForms) -> Sample:
        """All owned cells at weight 1: the Galerkin reduced model."""
        cells = np.arange(forms.space.dofmap.index_map.size_local, dtype=np.int32)
        return Sample(
            {name: cells for name in forms.sampled},
            {name: np.ones(len(cells)) for name in forms.sampled},
            0.0,
        )


def sparse_nnls(G: np.ndarray, tolerance: float, comm: MPI.Comm) -> tuple[np.ndarray, np.ndarray]:
    """A sparse ξ ≥ 0 with ‖G ξ − b‖ ≤ tolerance ‖b‖, b = G 1 (collective; the columns of G are
    the owned cells of this rank). Returns the local column indices it uses and their weights.

    Greedy Lawson–Hanson (Chapman et al. 2017): add the column most correlated with the residual
    b − G ξ; solve the least-squares problem on the chosen columns; where a weight would turn
    negative, step back to the boundary and drop that column; repeat until the tolerance is met.
    The chosen columns are gathered on every rank, which all solve the same small problem."""
    b = comm.allreduce(G.sum(axis=1), op=MPI.SUM)
    target = tolerance * float(np.linalg.norm(b))
    offsets = np.cumsum([0, *comm.allgather(G.shape[1])])
    start = offsets[comm.rank]
    chosen: list[int] = []  # global column numbers
    excluded: set[int] = set()  # columns whose least-squares weight was not positive when added
    columns = np.zeros((G.shape[0], 0))
    weights = np.zeros(0)
    residual = b.copy()
    while float(np.linalg.norm(residual)) > target:
        correlation = G.T @ residual
        if taken := [c - start for c in (*chosen, *excluded) if start <= c < start + G.shape[1]]:
            correlation[taken] = -np.inf
        best = int(np.argmax(correlation)) if correlation.size else -1
        value = float(correlation[best]) if best >= 0 else -np.inf
        candidates = comm.allgather((value, start + best))
        value, column = max(candidates)
        if not value > 0:  # nothing left that lowers the residual: the tolerance is out of reach
            break
        owner = int(np.searchsorted(offsets, column, side="right") - 1)
        vector = comm.bcast(G[:, column - start] if comm.rank == owner else None, root=owner)
        chosen.append(column)
        columns = np.column_stack([columns, vector])
        weights = np.append(weights, 0.0)
        while True:
            trial = np.linalg.lstsq(columns, b, rcond=None)[0]
            if np.all(trial > 0):
                weights = trial
                break
            negative = trial <= 0
            steps = weights[negative] / (weights[negative] - trial[negative])
            weights = weights + steps.min() * (trial - weights)
            keep = weights > 1e-14 * max(1.0, weights.max())
            keep[np.flatnonzero(negative)[np.argmin(steps)]] = False
            if not keep[-1]:  # the new column itself (round-off; never in exact arithmetic)
                excluded.add(chosen[-1])
            chosen = [c for c, k in zip(chosen, keep) if k]
            columns, weights = columns[:, keep], weights[keep]
        residual = b - columns @ weights
    mine = np.array([i for i, c in enumerate(chosen) if start <= c < start + G.shape[1]], dtype=int)
    cells = np.array([chosen[i] - start for i in mine], dtype=np.int32)
    order = np.argsort(cells)
    return cells[order], weights[mine][order]


class HyperReducedSolver:
    """Reduced Newton in q with ECSW: the residual and tangent integrate over the sampled cells
    (and their exterior facets) only, with their weights, on a :class:`ReducedMesh` of them, so
    that no online operation touches the full mesh. The solver's state is q; the model's state
    is written only when asked (:meth:`update_model`). Same interface as
    :class:`~lungmech.rom.galerkin.ReducedSolver` otherwise; :attr:`assembled_cells` counts
    what one assembly visits.

    ``start`` is the full state the basis is relative to (default: the unloaded state)."""

    def __init__(self, model, basis, sample: Sample, options=None, start: np.ndarray | None = None):
        check_basis(model, basis)
        self.model, self.basis, self.sample = model, basis, sample
        self.options = options or NewtonOptions()
        self.comm = model.geometry.mesh.comm
        forms = WeightedForms(model)
        if missing := [name for name in forms.sampled if name not in sample.cells and name not in FUNCTIONALS]:
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
        restricted = self._restricted = _restricted(forms, model.geometry.mesh, sample)
        self._weights = forms  # the forms reach the weights' Functions: keep them alive
        self.mesh = reduced = ReducedMesh(model, np.concatenate([*sample.cells.values(), np.zeros(0, np.int32)]))
        self._residual = reduced.form(restricted)
        self._jacobian = reduced.form(ufl.derivative(restricted, model.state, ufl.TrialFunction(model.space)))
        self._vector = fem.assemble_vector(self._residual)
        mesh = model.geometry.mesh
        self._sampled = {
            name: _sampled(forms.functionals[name], mesh, sample.cells[name])
            for name in forms.functionals
            if name in sample.cells
        }
        self._functionals = {name: reduced.form(functional) for name, functional in self._sampled.items()}
        self._matrix = fem.create_matrix(self._jacobian, block_mode=la.BlockMode.expanded)
        self.V = reduced.restrict_columns(np.ascontiguousarray(basis.vectors))  # sub dofs, ghosts too
        # Each rank reduces its own cells' contributions, ghost rows included, and one Allreduce
        # sums them: no ghost exchange. The matrix numbers its rows and columns its own way.
        self._rows, self._columns = (_positions(self._matrix.index_map(i), reduced.space) for i in (0, 1))
        self._row_basis, self._column_basis = self.V[self._rows], self._on_columns(self.V)
        self._tangent = self._matrix.to_scipy(ghosted=True)  # shares the matrix's values
        self.reference = reference_state(model) if start is None else np.array(start, dtype=float)
        self._imposed = origin(model, self.reference)  # x₀; the imposed dofs are rewritten at each solve
        self._origin = reduced.restrict(self._imposed)
        degree = quadrature_degree(model)
        self._gradient = at_quadrature_points(reduced.expression(model.F), reduced.mesh, degree)
        jacobians = at_quadrature_points(reduced.expression(ufl.det(model.F)), reduced.mesh, degree)
        # J > 0 is checked where the model is evaluated: on the sampled cells
        self.inversion = Inversion(model, smallest(jacobians, self.comm))
        self._magnitude = _displacement_magnitude(model, reduced)
        self.coordinates = np.zeros(basis.size)  # at the start state (set_state(project()) follows a moved model)
        self._q = self.coordinates.copy()  # where the reduced mesh's state is
        self._works: list[np.ndarray] = []  # Vᵀ ∂W/∂θ of each state-dependent load, at the last tangent
        # state-dependent loads (balanced gravity): their coefficients from affine integrals in
        # z = (q, imposed factors), exactly, and from the others' samples on the reduced mesh
        self._coupled = []
        if model.state_dependent:
            start_state, imposed, self._constraints = imposed_directions(model, self.reference)
            self._affine_basis = start_state, np.hstack([basis.vectors, imposed[: basis.vectors.shape[0]]])
            for index, term in enumerate(model.state_dependent):
                self._coupled.append(term.bind(_SampledIntegration(self, index, term.integrals)))
        self.description = (
            f"hyper-reduced (ECSW, τ = {sample.tolerance:g}): {basis.kind} basis of {basis.size} vectors, "
            + ", ".join(f"{n} {family.replace('_', ' ')}" for family, n in sample.count(self.comm).items())
            + " sampled cells"
        )
        self.iterations_total = 0

    @property
    def state(self) -> np.ndarray:
        """The reduced coordinates q (the load stepping keeps and extrapolates these)."""
        return self.coordinates

    def set_state(self, state: np.ndarray) -> None:
        self.coordinates[:] = state

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

    def functional(self, name: str, q: np.ndarray) -> float:
        """The sampled functional ``name`` (:data:`FUNCTIONALS`), Σ_e ξ_e f_e(x₀ + V q) over its
        sample, at the loads of the last solve (collective)."""
        if name not in self._functionals:
            raise ParameterError(f"this ECSW sample has no cells for the functional {name!r} (train it)")
        self._at(q)
        return self.comm.allreduce(fem.assemble_scalar(self._functionals[name]), op=MPI.SUM)

    @functools.cached_property
    def derivative_forms(self) -> DerivativeForms:
        """∂/∂c of the sampled residual and strain energy, and the energy's gradient, on the
        reduced mesh (compiled on first use; collective)."""
        if "strain_energy" not in self._sampled:
            raise ParameterError("sensitivities need the strain energy's ECSW sample (train it)")
        return DerivativeForms(
            self.model, self._restricted, self._sampled["strain_energy"], self.mesh.form, derivative_forms(self.model)
        )

    def state_derivatives(self, derivatives: ValueDerivatives) -> np.ndarray:
        """dq/dμ = −J⁻¹ (∂r/∂μ + Vᵀ K dx₀/dμ) at the current q, J, r and K those of the sample:
        the exact derivative of this model's own answer, (k, parameters). Collective."""
        forms = self.derivative_forms
        self._at(self.coordinates)
        jacobian = self.reduced_jacobian()  # and K on the reduced mesh, at q
        imposed = self._on_columns(self.mesh.restrict(derivatives.imposed))
        rhs = gram(self._row_basis, self._tangent @ imposed, self.comm)
        b = self._vector.array
        for i in range(len(derivatives.names) if forms.residual is not None else 0):
            forms.set_weights(derivatives, i)
            b[:] = 0.0
            fem.assemble_vector(b, forms.residual)
            rhs[:, i] += gram(self.V, b[:, None], self.comm)[:, 0]
        return -np.linalg.solve(jacobian, rhs)

    def energy_derivatives(self, dq: np.ndarray, derivatives: ValueDerivatives) -> np.ndarray:
        """dẼ/dμ = ∇Ẽ · (V dq/dμ + dx₀/dμ) + Σ_k ∂Ẽ/∂c_k ∂c_k/∂μ of the sampled strain energy Ẽ
        at the current q, (parameters,). Collective."""
        forms = self.derivative_forms
        self._at(self.coordinates)
        g = self._vector.array
        g[:] = 0.0
        fem.assemble_vector(g, forms.energy_gradient)
        total = gram(self.V, g[:, None], self.comm)[:, 0] @ dq
        total = total + gram(g[:, None], self.mesh.restrict(derivatives.imposed), self.comm)[0]
        for i in range(len(derivatives.names) if forms.energy is not None else 0):
            forms.set_weights(derivatives, i)
            total[i] += self.comm.allreduce(fem.assemble_scalar(forms.energy), op=MPI.SUM)
        return total

    def _at_loads(self) -> None:
        """x₀ on the reduced mesh with the imposed displacements of the current loads (DOLFINx
        writes the imposed dofs only: O(boundary))."""
        for bc in self.model.bcs:
            bc.set(self._imposed)
        self._origin = self.mesh.restrict(self._imposed)

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
        fem.assemble_vector(b, self._residual)
        return gram(self.V, b[:, None], self.comm)[:, 0]

    def reduced_jacobian(self) -> np.ndarray:
        """Σ_e ξ_e Vᵀ K_e V at the reduced mesh's state, plus the state-dependent loads' low-rank
        term −(Vᵀ ∂W/∂θ)(Vᵀ dΘ/du)ᵀ (:mod:`lungmech.fem.state_dependent`)."""
        self._matrix.set_value(0.0)
        fem.assemble_matrix(self._matrix, self._jacobian)
        reduced = gram(self._row_basis, self._tangent @ self._column_basis, self.comm)
        self._works = []
        for term in self._coupled:
            work, gradient = term.linearise()
            reduced -= work @ gradient.T
            self._works.append(work)
        return reduced

    def sampled_vector(self, family: str, expr, measure) -> Callable[[], np.ndarray]:
        """Σ_e ξ_e ∫_e ``expr`` over the sample of ``family`` (any value shape), on the reduced
        mesh at its state (collective)."""
        flat = _flat(expr)
        size = flat.ufl_shape[0]
        space = fem.functionspace(self.mesh.mesh, ("DG", 0, (size,)))
        form = ufl.inner(self._weights.weights[family] * flat, ufl.TestFunction(space)) * measure
        compiled = self.mesh.form(_over(form, self.model.geometry.mesh, self.sample.cells.get(family, _NONE)))
        vector = fem.Function(space).x

        def evaluate() -> np.ndarray:
            vector.array[:] = 0.0
            fem.assemble_vector(vector.array, compiled)
            total = np.empty(size)
            self.comm.Allreduce(vector.array.reshape(-1, size).sum(axis=0), total, op=MPI.SUM)
            return total.reshape(expr.ufl_shape)

        return evaluate

    def sampled_column(self, form: ufl.Form, families: dict[str, str]) -> Callable[[], np.ndarray]:
        """Vᵀ b of a linear ``form`` (in the model's test function) over the samples: each
        integral over the sample of ``families[its type]``, with its weights (collective)."""
        mesh = self.model.geometry.mesh
        weighted: dict[str, list] = {}  # by family: one restricted tag set per integral type
        for integral in form.integrals():
            family = families[integral.integral_type()]
            integrand = self._weights.weights[family] * integral.integrand()
            weighted.setdefault(family, []).append(integral.reconstruct(integrand=integrand))
        integrals = [
            restricted
            for family, parts in weighted.items()
            for restricted in _over(ufl.Form(parts), mesh, self.sample.cells.get(family, _NONE)).integrals()
        ]
        compiled = self.mesh.form(ufl.Form(integrals))
        vector = fem.Function(self.mesh.space).x
        packed = {"at": None, "coefficients": None}  # packed once per state: only Constants vary in between

        def evaluate() -> np.ndarray:
            if packed["at"] is not self._q:
                packed["at"], packed["coefficients"] = self._q, fem.pack_coefficients(compiled)
            vector.array[:] = 0.0
            fem.assemble_vector(vector.array, compiled, coeffs=packed["coefficients"])
            return gram(self.V, vector.array[:, None], self.comm)[:, 0]

        return evaluate

    def floor(self) -> float:
        """‖|V|ᵀ ε|K|s‖, s = |x| + h on the displacement: the round-off floor of the reduced
        residual (see :mod:`lungmech.fem.convergence`), at the last tangent's state."""
        s = np.abs(self.mesh.state.x.array) + self._magnitude
        rounding = EPS * (abs(self._tangent) @ self._on_columns(s))
        floor = float(np.linalg.norm(gram(np.abs(self._row_basis), rounding[:, None], self.comm)))
        # and that of state-dependent coefficients θ (balanced gravity: a KKT solve), through ∂r/∂θ
        return floor + sum(float(np.linalg.norm(np.abs(w) @ t.rounding())) for w, t in zip(self._works, self._coupled))

    @functools.cached_property
    def residual_form(self):
        """The full model's compiled residual (for a diagnosis of a failed load path)."""
        return fem.form(self.model.residual)

    @functools.cached_property
    def jacobian_form(self):
        """The full model's compiled tangent."""
        return fem.form(self.model.jacobian)

    @property
    def assembled_cells(self) -> dict[str, int]:
        """How many distinct cells one assembly of the residual visits, over all ranks: with its
        cell integrals ("cell"), and through its exterior-facet integrals ("exterior_facet");
        compare :meth:`Sample.cells_per_type`."""
        form = self._residual._cpp_object
        counts = {}
        for name, kind in (("cell", fem.IntegralType.cell), ("exterior_facet", fem.IntegralType.exterior_facet)):
            cells = [np.zeros(0, np.int32)]
            if kind in form.integral_types:
                for i in range(form.num_integrals(kind, 0)):
                    entities = np.asarray(form.domains(kind, i)).reshape(-1)
                    cells.append(entities if kind == fem.IntegralType.cell else entities[::2])
            counts[name] = self.comm.allreduce(len(np.unique(np.concatenate(cells))), op=MPI.SUM)
        return counts

    def destroy(self) -> None:
        """Nothing PETSc holds: the reduced mesh's vectors and matrices are DOLFINx's."""


def _positions(index_map, space) -> np.ndarray:
    """For each local index of a matrix's (expanded) row or column ``index_map``, the local sub
    dof of ``space`` with the same global number (unrolled), or -1."""
    dofs, bs = space.dofmap.index_map, space.dofmap.index_map_bs
    blocks = dofs.local_to_global(np.arange(dofs.size_local + dofs.num_ghosts, dtype=np.int32))
    numbers = (bs * blocks[:, None] + np.arange(bs)).reshape(-1)
    wanted = index_map.local_to_global(np.arange(index_map.size_local + index_map.num_ghosts, dtype=np.int32))
    order = np.argsort(numbers)
    at = np.minimum(np.searchsorted(numbers[order], wanted), len(numbers) - 1)
    return np.where(numbers[order][at] == wanted, order[at], -1)


def _displacement_magnitude(model, reduced: ReducedMesh) -> np.ndarray:
    """h on the sub dofs of the displacement, 0 on other fields: what F's rounding adds to |x|."""
    h = Fields(model).cell_size
    if not model.mixed:
        return np.full(len(reduced.parent_dofs), h)
    magnitude = np.zeros(len(reduced.parent_dofs))
    magnitude[reduced.space.sub(0).collapse()[1]] = h
    return magnitude


def _projection(model, basis, reference: np.ndarray) -> np.ndarray:
    """q of the model's current state: (W V)ᵀ (x − x₀) (collective)."""
    W = inner_product(model, basis.inner_product)
    dual = apply(W, np.ascontiguousarray(basis.vectors), model.geometry.mesh.comm)
    if W is not None:
        W.destroy()
    owned = basis.vectors.shape[0]
    x = model.state.x.array[:owned] - origin(model, reference)[:owned]
    return gram(dual, x[:, None], model.geometry.mesh.comm)[:, 0]


def _restricted(forms: WeightedForms, mesh, sample: Sample) -> ufl.Form:
    """The weighted residual with each family's integrals over its sampled cells only (boundary
    loads: over the sampled cells' facets, their boundary tags kept). The cells of the two cell
    families share one tag set: bit 1 internal, bit 2 cell load."""
    tdim = mesh.topology.dim
    owned = mesh.topology.index_map(tdim).size_local
    bits = np.zeros(owned, dtype=np.int32)
    for bit, family in ((1, "internal"), (2, "cell_load")):
        bits[sample.cells.get(family, np.zeros(0, np.int32))] |= bit
    tagged = np.flatnonzero(bits).astype(np.int32)
    cell_tags = dmesh.meshtags(mesh, tdim, tagged, bits[tagged])
    integrals = []
    facet_tags = {}
    for family in forms.families:
        for integral in forms.parts[family]:
            if FAMILIES[family] == "cell":
                bit = 1 if family == "internal" else 2
                integrals.append(integral.reconstruct(subdomain_id=(bit, 3), subdomain_data=cell_tags))
                continue
            tags = integral.subdomain_data()
            if tags is None:  # lungmech's loads name their boundaries; an untagged ds is not sampled
                raise ParameterError("ECSW samples boundary integrals over named (tagged) boundaries only")
            if id(tags) not in facet_tags:
                facet_tags[id(tags)] = _facets_of(mesh, tags, sample.cells.get(family, np.zeros(0, np.int32)))
            integrals.append(integral.reconstruct(subdomain_data=facet_tags[id(tags)]))
    return ufl.Form(integrals)


_NONE = np.zeros(0, np.int32)


def _sampled(functional: ufl.Form, mesh, cells: np.ndarray) -> ufl.Form:
    """A weighted functional's cell integrals over ``cells`` only."""
    return _over(functional, mesh, cells)


def _over(form: ufl.Form, mesh, cells: np.ndarray) -> ufl.Form:
    """``form``'s cell integrals over ``cells`` only, its exterior-facet integrals over their
    facets (their boundary tags kept)."""
    cells = np.unique(cells).astype(np.int32)
    tags = dmesh.meshtags(mesh, mesh.topology.dim, cells, np.ones(len(cells), dtype=np.int32))
    integrals, facet_tags = [], {}  # one restricted tag set per boundary tag set: DOLFINx wants one per type
    for integral in form.integrals():
        if integral.integral_type() == "cell":
            integrals.append(integral.reconstruct(subdomain_id=1, subdomain_data=tags))
            continue
        boundary = integral.subdomain_data()
        if boundary is None:
            raise ParameterError("ECSW samples boundary integrals over named (tagged) boundaries only")
        if id(boundary) not in facet_tags:
            facet_tags[id(boundary)] = _facets_of(mesh, boundary, cells)
        integrals.append(integral.reconstruct(subdomain_data=facet_tags[id(boundary)]))
    return ufl.Form(integrals)


class _SampledIntegration:
    """The integrals of state-dependent load ``index`` on a hyper-reduced solver
    (:class:`~lungmech.fem.state_dependent.Integration`): the affine ones exactly in z = (q,
    imposed factors), from k + 2 full evaluations offline; the others over their ECSW sample on
    the reduced mesh; columns as Vᵀ b, over the sample of the integral they derive from (the
    load's own work: the load families')."""

    def __init__(self, solver: HyperReducedSolver, index: int, integrals: dict):
        self.solver, self.index, self.integrals = solver, index, integrals

    def vector(self, name: str, expr, measure) -> Callable[[], np.ndarray]:
        solver = self.solver
        if not self.integrals[name].affine:
            return solver.sampled_vector(f"load{self.index}_{name}", expr, measure)
        model = solver.model
        f0, F1 = affine(model, vector_integral(expr, measure, model.geometry.mesh), *solver._affine_basis)
        return lambda: (f0 + F1 @ solver._z()).reshape(expr.ufl_shape)

    def column(self, name: str, form: ufl.Form) -> Callable[[], np.ndarray]:
        solver = self.solver
        if name == "residual":
            return solver.sampled_column(form, {"cell": "cell_load", "exterior_facet": "boundary_load"})
        if not self.integrals[name].affine:
            family = f"load{self.index}_{name}"
            return solver.sampled_column(form, {"cell": family, "exterior_facet": family})
        # the derivative of an affine integral is a constant: once, on the whole mesh
        constant = gram(solver.basis.vectors, FullIntegration(solver.model).column(name, form)()[:, None], solver.comm)
        return lambda: constant[:, 0]


def _facets_of(mesh, tags, cells: np.ndarray):
    """The boundary facet tags ``tags`` kept on the facets of ``cells`` only."""
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim, tdim - 1)
    connectivity = mesh.topology.connectivity(tdim, tdim - 1)
    mine = np.unique(np.concatenate([connectivity.links(c) for c in cells])) if len(cells) else np.zeros(0, np.int32)
    keep = np.isin(tags.indices, mine)
    return dmesh.meshtags(mesh, tdim - 1, tags.indices[keep], tags.values[keep])
