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

Forces alone leave the reduced tangent Vᵀ K V free: a sample can reproduce the training
states' forces and be much softer or stiffer than the Galerkin model in a direction they do not
load, and then, at a state between or beyond them, settle far from its Galerkin answer (on the
bundled lung at τ = 1e-2 its generalised eigenvalues against the Galerkin tangent spanned
0.32–1.9; on a block, it ran into a limit point that is not the body's). So the sample also
reproduces the reduced tangent of each family at the start of load steps (their first Newton
iterate: the step before's answer under the new loads), in the metric of the elastic
reduced tangent there, so that every direction counts, the softest as the stiffest; the
tangents are reproduced to :data:`TANGENT_TOLERANCE` (:meth:`Training.add_tangents`,
:meth:`Training.matrix`). Matching the forces and their derivatives at the training states
makes the forces right near them, not only on them.

A load whose coefficients are global functionals of the state (balanced gravity, see
:mod:`lungmech.fem.state_dependent`) declares the integrals they come from: the affine ones are
evaluated exactly from (q, imposed factors), the others are sampled like functionals (vector
valued: the pressure's 54 response entries per training state), and its rank-12 tangent term
comes from the same samples (:mod:`lungmech.rom.hyper_reduced`).

The weights enter the forms as piecewise-constant (DG0) fields, one per family (an exterior
facet has one cell, whose weight it takes): the same
forms give the Galerkin reduced model (all weights 1), the training matrix G (their derivative
with respect to the weights: column e is r_e), and, integrated over the sampled cells only, the
hyper-reduced one (:class:`lungmech.rom.hyper_reduced.HyperReducedSolver`).

G has a row per training state and reduced component and a column per cell: thousands by
hundreds of thousands on a large lung, more than a machine holds. The NNLS needs only the
norms ‖G x‖, and the training states' rows are far from independent, so each family's G is held
compressed as it grows: a matrix R of few rows with RᵀR = GᵀG to within the squared singular
values dropped (below :data:`COMPRESSION` times the largest), found from the Gram matrix of
its rows whenever :data:`COMPRESS_ROWS` new rows have come (the method of snapshots; the
columns stay distributed over the ranks).
"""

from __future__ import annotations

import contextlib
import time
import weakref
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx import fem, la
from dolfinx import mesh as dmesh
from dolfinx.fem.petsc import assemble_matrix, create_matrix
from ufl.algorithms import expand_derivatives

from lungmech.errors import ParameterError
from lungmech.fem.state_dependent import StateDependent

__all__ = [
    "COMPRESSION",
    "COMPRESS_ROWS",
    "FAMILIES",
    "FUNCTIONALS",
    "NO_CELLS",
    "TANGENT",
    "TANGENT_STATES",
    "TANGENT_TOLERANCE",
    "Sample",
    "Training",
    "WeightedForms",
    "flattened",
    "over_cells",
    "sampled_residual",
    "sparse_nnls",
    "train",
]

# The families sampled, each with its own weights, and their integral type: the cells' internal
# forces (of the energy density), the loads on cells (weight) and on the boundary (pressures).
FAMILIES = {"internal": "cell", "cell_load": "cell", "boundary_load": "exterior_facet"}
# Scalar functionals (cell integrals) sampled the same way, for outputs: their cells' values are
# the columns, each training state one row scaled by the functional's value there.
FUNCTIONALS = ("strain_energy",)
# G of a family is compressed when this many rows have come since (see the module's doc) ...
COMPRESS_ROWS = 1024
# ... dropping its singular values below this fraction of the largest: far below any τ
# (‖G x‖ changes by that fraction of ‖G‖ ‖x‖ at most), and above the Gram matrix's rounding
# (its eigenvalues are the squares: 1e-14 of the largest, against ε = 2e-16)
COMPRESSION = 1e-7
# the key of a family's tangent rows in a Training's blocks
TANGENT = ":tangent"
# the tangents' tolerance: their error (in the whitened rows of Training.add_tangents) moves the
# reduced stiffness's eigenvalues by at most √k times it, in practice a fraction of that: the
# stability that a sample needs, without the force's τ, which would cost cells for no accuracy
TANGENT_TOLERANCE = 0.02
# the most load steps whose tangents a replay adds (each costs k assemblies per family): a large
# mesh's greedy replays hundreds of steps every round
TANGENT_STATES = 4


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
        flat = flattened(integral.expr)
        mesh = self.space.mesh
        space = fem.functionspace(mesh, ("DG", 0, (flat.ufl_shape[0],)))
        return ufl.inner(flat, ufl.TestFunction(space)) * integral.measure, space


def flattened(expr) -> ufl.core.expr.Expr:
    """A vector of the entries of a scalar, vector or tensor expression."""
    shape = expr.ufl_shape
    if len(shape) == 1:
        return expr
    return ufl.as_vector([expr[index] for index in np.ndindex(shape)] if shape else [expr])


def _whitening(matrix: np.ndarray) -> np.ndarray:
    """S = |Λ|^-½ Qᵀ of the symmetric part Q Λ Qᵀ of ``matrix``, |λ| floored at 1e-12 of the
    largest: S M Sᵀ has eigenvalues ±1 (for M symmetric)."""
    eigenvalues, vectors = np.linalg.eigh(0.5 * (matrix + matrix.T))
    magnitudes = np.maximum(np.abs(eigenvalues), 1e-12 * np.abs(eigenvalues).max())
    return vectors.T / np.sqrt(magnitudes)[:, None]


def _integrals(form: ufl.Form, kind: str) -> list:
    return [integral for integral in form.integrals() if integral.integral_type() == kind]


class Training:
    """The matrix G of ECSW, one training state at a time (collective).

    Each :meth:`add` takes the model's current state and loads: for every family, the reduced
    contributions Vᵀ r_e of the owned cells, scaled by the family's reduced force ‖b_s‖ (the
    internal forces and the loads each: they balance at an equilibrium, neither vanishes); for
    every functional, its cells' values scaled by its value. A family without force at a state
    (at rest; a load not applied yet) skips it. :meth:`add_tangents` adds the families' reduced
    tangents at a state (see the module's doc).
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
        # ∂/∂x of each family's columns along a direction V_j: column e is K_e V_j
        self._direction = fem.Function(model.space)
        self._tangents = {}
        for family in self.forms.families:
            form = ufl.derivative(self.forms.contribution(family), model.state, self._direction)
            if not expand_derivatives(form).empty():  # a load independent of the state has none
                compiled = fem.form(form)
                self._tangents[family] = (compiled, create_matrix(compiled))
        self.cells = self.forms.space.dofmap.index_map.size_local
        names = (*self.forms.sampled, *(family + TANGENT for family in self._tangents))
        self.blocks: dict[str, list[np.ndarray]] = {name: [] for name in names}  # G's rows, compressed
        self.added = dict.fromkeys(names, 0)  # the training states in each family's G
        self._since = dict.fromkeys(names, 0)  # its rows since it was compressed
        rows, k = self.V.shape  # V as a distributed dense matrix, wrapping self.V's memory
        self.seconds = {"tangents": 0.0, "compression": 0.0}  # of the training so far: where its time goes
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
            local[family] = self._reduced_columns(self._compiled[family], self._matrices[family])
        return any([self._append(name, block) for name, block in local.items()])

    def add_tangents(self) -> bool:
        """Add every family's reduced tangent at the model's current state and loads, in the
        metric of the internal forces' (the elastic) reduced tangent K_V = Σ_e Vᵀ K_e V there:
        the rows of every cell's S Vᵀ K_e V Sᵀ, S = |Λ|^-½ Qᵀ of K_V's symmetric part Q Λ Qᵀ, over
        √k. An error ε in them moves each of K_V's eigenvalues by at most ε √k of itself, in
        every direction, the softest as the stiffest: an error relative to ‖K_V‖ would leave
        the soft ones free, a condition number times looser. False: no family's tangent is
        nonzero. k assemblies of a matrix of the cells' columns per family, for k vectors."""
        tic = time.perf_counter()
        try:
            return self._add_tangents()
        finally:
            self.seconds["tangents"] += time.perf_counter() - tic

    def _add_tangents(self) -> bool:
        self._state_dependent.update()
        owned, k = self.V.shape
        tangents = {}  # family: (j, i, cell) ↦ V_iᵀ K_e V_j
        for family, (form, C) in self._tangents.items():
            rows = []
            for j in range(k):
                self._direction.x.array[:owned] = self.V[:, j]
                self._direction.x.scatter_forward()
                rows.append(self._reduced_columns(form, C))
            tangents[family] = np.stack(rows)
        if not tangents:
            return False
        metric = self.comm.reduce(tangents.get("internal", next(iter(tangents.values()))).sum(axis=2), op=MPI.SUM)
        # rank 0's for all, as in _compress: each rank's columns must be scaled alike
        whitening = self.comm.bcast(_whitening(metric) if self.comm.rank == 0 else None, root=0)
        added = []
        for family, block in tangents.items():
            scaled = np.einsum("ai,jie,bj->abe", whitening, block, whitening) / np.sqrt(k)
            added.append(self._append(family + TANGENT, scaled.reshape(k * k, -1), scaled=True))
        return any(added)

    def _reduced_columns(self, form: fem.Form, C: PETSc.Mat) -> np.ndarray:
        """Vᵀ C of the assembled ``form`` (columns: the owned cells)."""
        C.zeroEntries()
        assemble_matrix(C, form)
        C.assemble()
        product = C.transposeMatMult(self._basis)  # (cells × k): row e is (Vᵀ C_e)ᵀ
        try:
            return product.getDenseArray()[: self.cells].T.copy()
        finally:
            product.destroy()

    def _append(self, name: str, block: np.ndarray, scaled: bool = False) -> bool:
        """Add a state's ``block`` of rows to G of ``name``, divided by the norm of its sum over
        all cells unless ``scaled`` already; False (and nothing added) when that is 0."""
        scale = float(np.linalg.norm(self.comm.allreduce(block.sum(axis=1), op=MPI.SUM)))
        if scale == 0.0:
            return False
        self.blocks[name].append(block if scaled else block / scale)
        self.added[name] += 1
        self._since[name] += block.shape[0]
        if self._since[name] >= COMPRESS_ROWS:
            self._compress(name)
        return True

    def _compress(self, family: str) -> None:
        """Replace the rows of ``family``'s G by R = Σ^½ Uᵀ G over the eigenpairs (λ, U) of the
        rows' Gram matrix G Gᵀ with λ ≥ (:data:`COMPRESSION` λ_max)²: RᵀR = GᵀG but for the
        dropped ones (the method of snapshots; the Gram matrix sums the ranks' columns)."""
        tic = time.perf_counter()
        rows = np.vstack(self.blocks[family])
        self.blocks[family] = []  # the blocks go before R comes: one copy of G at a time
        gram_matrix = self.comm.reduce(rows @ rows.T, op=MPI.SUM, root=0)
        # one rank's eigenvectors for all: each rank's rows of R must be the same combination
        # (an eigenvector's sign, a degenerate pair's basis, are not the same on rounded copies)
        eigenvalues, vectors = self.comm.bcast(np.linalg.eigh(gram_matrix) if self.comm.rank == 0 else None, root=0)
        kept = eigenvalues >= COMPRESSION**2 * max(eigenvalues.max(), 0.0)
        self.blocks[family] = [vectors[:, kept].T @ rows]
        self._since[family] = 0
        self.seconds["compression"] += time.perf_counter() - tic

    def add_state(
        self,
        state: np.ndarray,
        time: float,
        load_factor: float = 1.0,
        parameters: dict[str, float] | None = None,
        tangents: bool = False,
    ) -> bool:
        """Set the model to a stored state (its whole local array) at its time, load factor and
        ``parameters`` (default: as they are), then :meth:`add` it (and, with ``tangents``,
        :meth:`add_tangents`)."""
        if parameters is not None:
            self.model.set_parameters(parameters)
        self.model.state.x.array[:] = state
        self.model.state.x.scatter_forward()
        self.model.set_time(time, load_factor=load_factor)
        added = self.add()
        if tangents:
            added = self.add_tangents() or added
        return added

    def replay(self, states: Sequence[tuple[np.ndarray, float, dict[str, float]]]) -> None:
        """:meth:`add_state` every stored Newton iterate ``(state, time, parameters)`` (e.g. those
        a greedy training kept, :attr:`lungmech.rom.greedy.Greedy.iterates`), with the tangents
        at the first of :data:`TANGENT_STATES` load steps spread evenly over them (a step: a
        run of one time and parameters); the model's state is restored afterwards (its time and
        parameters are the last state's)."""
        starts = [i for i, (_, t, mu) in enumerate(states) if i == 0 or states[i - 1][1:] != (t, mu)]
        spread = np.linspace(0, len(starts) - 1, min(TANGENT_STATES, len(starts)))
        tangents = {starts[j] for j in np.round(spread).astype(int)}
        with self.model.kept_state():
            for index, (state, t, parameters) in enumerate(states):
                self.add_state(state, t, parameters=parameters, tangents=index in tangents)

    @contextlib.contextmanager
    def watching(self, solver) -> Iterator[Training]:
        """Within the block, :meth:`add` every Newton iterate of ``solver`` (a full
        :class:`~lungmech.fem.solver.NewtonSolver`): the states an online Newton passes through,
        not only the converged ones, so that the sample also reproduces the reduced forces away
        from equilibrium. Each iterate is added at the solver's loads of the moment, and the
        first of every solve (a load step's start) with its tangents (:meth:`add_tangents`:
        at every step, where :meth:`replay` picks :data:`TANGENT_STATES` of them)."""
        training = weakref.ref(self)  # PETSc keeps the monitor: it must not keep us

        def add(iteration: int) -> None:
            if (this := training()) is not None:
                this.add()
                if iteration == 0:  # a load step's first iterate
                    this.add_tangents()

        with iterates(solver, add):
            yield self

    @property
    def states(self) -> int:
        """The most training states any family's forces hold."""
        return max((self.added[name] for name in self.forms.sampled), default=0)

    def matrix(self, family: str, tolerance: float = TANGENT_TOLERANCE) -> np.ndarray:
        """G of one family, columns the owned cells: rows (state, reduced component) or, once
        it was compressed, rows whose norms ‖G x‖ are G's (see the module's doc); below them its
        tangents' rows, if it has any, weighted by α √(force states / tangent states),
        α = min(1, ``tolerance`` / :data:`TANGENT_TOLERANCE`): the two parts weigh alike in
        all, but for α, so that a sample meeting ``tolerance`` reproduces the tangents to
        :data:`TANGENT_TOLERANCE` (or better), the forces to ``tolerance``."""
        if not self.blocks[family]:
            raise ParameterError(f"ECSW has no training state with a load on its {family} integrals (add states first)")
        rows = [np.vstack(self.blocks[family])]
        if self.added.get(tangent := family + TANGENT):
            weight = min(1.0, tolerance / TANGENT_TOLERANCE) * np.sqrt(self.added[family] / self.added[tangent])
            rows.append(weight * np.vstack(self.blocks[tangent]))
        return np.vstack(rows)

    def sample(self, tolerance: float) -> Sample:
        """The sparse positive weights of each family that reproduce the training reduced forces
        to ``tolerance`` (relative, per family) and its tangents to :data:`TANGENT_TOLERANCE`,
        see :meth:`matrix` and :func:`sparse_nnls`."""
        if not self.states:
            raise ParameterError("ECSW has no training state with a load (add states first)")
        chosen = {name: sparse_nnls(self.matrix(name, tolerance), tolerance, self.comm) for name in self.forms.sampled}
        return Sample(
            {family: cells for family, (cells, _) in chosen.items()},
            {family: weights for family, (_, weights) in chosen.items()},
            tolerance,
        )

    def destroy(self) -> None:
        for matrix in (*self._matrices.values(), *(C for _, C in self._tangents.values()), self._basis):
            matrix.destroy()


def train(
    model, basis, solver, runs: Callable[[], object], tolerance: float, timings: dict[str, float] | None = None
) -> Sample:
    """The ECSW sample of ``model`` on ``basis`` at ``tolerance``, trained on every Newton
    iterate (converged states included) ``solver`` takes while ``runs()`` drives it along the
    training load paths. ``timings``, if given, receives the seconds of the training pass (and
    of its tangents and compressions) and of the NNLS. Collective."""
    tic = time.perf_counter()
    training = Training(model, basis.vectors)
    try:
        with training.watching(solver):
            runs()
        seconds = {"ecsw_training": time.perf_counter() - tic}
        seconds |= {f"ecsw_{part}": value for part, value in training.seconds.items()}
        tic = time.perf_counter()
        sample = training.sample(tolerance)
        seconds["nnls"] = time.perf_counter() - tic
    finally:
        training.destroy()
    if timings is not None:
        timings.update(seconds)
    return sample


@contextlib.contextmanager
def iterates(solver, seen: Callable[[int], None]) -> Iterator[None]:
    """Within the block, ``seen(iteration)`` after every Newton iterate of ``solver`` (a full
    :class:`~lungmech.fem.solver.NewtonSolver`; 0: a solve's start), with the model's state set
    to that iterate."""
    active = [True]
    model = solver.model

    def monitor(snes, iteration, norm) -> None:
        if active[0]:
            x = snes.getSolution()
            model.state.x.array[: x.getLocalSize()] = x.getArray(readonly=True)
            model.state.x.scatter_forward()
            seen(iteration)

    snes = solver.problem.solver
    snes.setMonitor(monitor)
    try:
        yield
    finally:
        active[0] = False
        monitors = snes.getMonitor() or []  # petsc4py's own list: leave the solver's monitors only
        monitors[:] = [entry for entry in monitors if entry[0] is not monitor]


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


def sampled_residual(forms: WeightedForms, mesh, sample: Sample) -> ufl.Form:
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


NO_CELLS = np.zeros(0, np.int32)


def over_cells(form: ufl.Form, mesh, cells: np.ndarray) -> ufl.Form:
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


def _facets_of(mesh, tags, cells: np.ndarray):
    """The boundary facet tags ``tags`` kept on the facets of ``cells`` only."""
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim, tdim - 1)
    connectivity = mesh.topology.connectivity(tdim, tdim - 1)
    mine = np.unique(np.concatenate([connectivity.links(c) for c in cells])) if len(cells) else np.zeros(0, np.int32)
    keep = np.isin(tags.indices, mine)
    return dmesh.meshtags(mesh, tdim - 1, tags.indices[keep], tags.values[keep])
