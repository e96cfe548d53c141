"""ECSW's training: the matrix G of the training states' reduced contributions, held compressed as
it grows, and the sample it gives (see :mod:`lungmech.rom.ecsw` for the method and its notation).

:class:`Training` takes one state at a time (:meth:`Training.add`, or every Newton iterate of a
solver with :meth:`Training.watching`, or stored iterates with :meth:`Training.replay`), the
reduced tangents at the start of a few load steps too; :meth:`Training.sample` solves the sparse
NNLS at τ. :func:`train` does all of it for the training load paths.
"""

from __future__ import annotations

import contextlib
import time
import weakref
from collections.abc import Callable, Iterator, Sequence

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx import fem, la
from dolfinx.fem.petsc import assemble_matrix, create_matrix
from ufl.algorithms import expand_derivatives

from lungmech import jit
from lungmech.errors import ParameterError
from lungmech.fem.model import Model
from lungmech.fem.solver import NewtonSolver
from lungmech.fem.state_dependent import StateDependent
from lungmech.rom.basis import Basis
from lungmech.rom.ecsw import (
    Sample,
    WeightedForms,
    is_functional,
    sparse_nnls,
)

__all__ = [
    "COMPRESSION",
    "COMPRESS_ROWS",
    "TANGENT",
    "TANGENT_STATES",
    "TANGENT_TOLERANCE",
    "Training",
    "iterates",
    "train",
]

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


def _whitening(matrix: np.ndarray) -> np.ndarray:
    """S = |Λ|^-½ Qᵀ of the symmetric part Q Λ Qᵀ of ``matrix``, |λ| floored at 1e-12 of the
    largest: S M Sᵀ has eigenvalues ±1 (for M symmetric)."""
    eigenvalues, vectors = np.linalg.eigh(0.5 * (matrix + matrix.T))
    magnitudes = np.maximum(np.abs(eigenvalues), 1e-12 * np.abs(eigenvalues).max())
    return vectors.T / np.sqrt(magnitudes)[:, None]


class Training:
    """The matrix G of ECSW, one training state at a time (collective).

    Each :meth:`add` takes the model's current state and loads: for every family, the reduced
    contributions Vᵀ r_e of the owned cells, scaled by the family's reduced force ‖b_s‖ (the
    internal forces and the loads each: they balance at an equilibrium, neither vanishes); for
    every functional, its cells' values scaled by its value. A family without force at a state
    (at rest; a load not applied yet) skips it. :meth:`add_tangents` adds the families' reduced
    tangents at a state (see the module's doc). ``outputs``: with the functionals (the strain
    energy, the averages' numerators); a model whose answer is a start, not outputs (an imaged
    body's inverse motion, :mod:`lungmech.rom.imaged`), samples its residual alone.
    """

    def __init__(self, model: Model, V: np.ndarray, outputs: bool = True) -> None:
        self.model, self.V = model, np.ascontiguousarray(V)
        self.forms = WeightedForms(model)
        functionals = tuple(self.forms.functionals) if outputs else ()
        self.sampled = (*self.forms.families, *functionals, *self.forms.integrals)  # what gets a sample
        self.comm = model.geometry.mesh.comm
        self._state_dependent = StateDependent(model)
        self._integrals: dict[str, tuple[fem.Form, la.Vector, int]] = {}
        for name in self.forms.integrals:
            form, space = self.forms.cell_values(name)
            self._integrals[name] = (jit.form(form), fem.Function(space).x, space.dofmap.index_map_bs)
        names = (*self.forms.families, *functionals)
        self._compiled = {name: jit.form(self.forms.contribution(name)) for name in names}
        self._matrices = {family: create_matrix(self._compiled[family]) for family in self.forms.families}
        # ∂/∂x of each family's columns along a direction V_j: column e is K_e V_j
        self._direction = fem.Function(model.space)
        self._tangents: dict[str, tuple[fem.Form, PETSc.Mat]] = {}
        for family in self.forms.families:
            form = ufl.derivative(self.forms.contribution(family), model.state, self._direction)
            if not expand_derivatives(form).empty():  # a load independent of the state has none
                compiled = jit.form(form)
                self._tangents[family] = (compiled, create_matrix(compiled))
        self.cells = self.forms.space.dofmap.index_map.size_local
        names = (*self.sampled, *(family + TANGENT for family in self._tangents))
        self.blocks: dict[str, list[np.ndarray]] = {name: [] for name in names}  # G's rows, compressed
        self.added = dict.fromkeys(names, 0)  # the training states in each family's G
        self._since = dict.fromkeys(names, 0)  # its rows since it was compressed
        rows, k = self.V.shape  # V as a distributed dense matrix, wrapping self.V's memory
        self.seconds = {"tangents": 0.0, "compression": 0.0}  # of the training so far: where its time goes
        self._basis = PETSc.Mat().createDense(((rows, None), (None, k)), array=self.V, comm=self.comm)  # type: ignore[arg-type]  # petsc4py's stub lacks None (PETSC_DECIDE) sizes, ndarrays

    def add(self) -> bool:
        """Add the model's current state (True), or skip it when its reduced force is 0 (False)."""
        self._state_dependent.update()  # θ = Θ(x) of this state, as a solve would have it
        local = {}
        for name, (form, vector, size) in self._integrals.items():  # each cell's entries of the integral
            vector.array[:] = 0.0
            fem.assemble_vector(vector.array, form)  # type: ignore[arg-type]  # the into-an-array overload (singledispatch) is not in the hints
            vector.scatter_reverse(la.InsertMode.add)  # a facet's contribution to its cell's owner
            local[name] = vector.array[: self.cells * size].reshape(self.cells, size).T.copy()
        for name in (
            n for n in self.forms.functionals if n in self._compiled
        ):  # a DG0 vector: entry e is cell e's integral
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
        assemble_matrix(C, form)  # type: ignore[arg-type]  # the into-a-matrix overload (singledispatch) is not in the hints
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
        """Set the model to a stored state (its owned rows, or its whole local array: the ghosts
        are updated from their owners) at its time, load factor and ``parameters`` (default: as
        they are), then :meth:`add` it (and, with ``tangents``, :meth:`add_tangents`)."""
        if parameters is not None:
            self.model.set_parameters(parameters)
        self.model.state.x.array[: len(state)] = state
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
    def watching(self, solver: NewtonSolver, tangents: Callable[[], bool] = lambda: True) -> Iterator[Training]:
        """Within the block, :meth:`add` every Newton iterate of ``solver`` (a full
        :class:`~lungmech.fem.solver.NewtonSolver`): the states an online Newton passes through,
        not only the converged ones, so that the sample also reproduces the reduced forces away
        from equilibrium. Each iterate is added at the solver's loads of the moment, and the
        first of a solve (a load step's start) with its tangents (:meth:`add_tangents`) where
        ``tangents()`` says so: by default at every step, where :meth:`replay` picks
        :data:`TANGENT_STATES` of them."""
        training = weakref.ref(self)  # PETSc keeps the monitor: it must not keep us

        def add(iteration: int) -> None:
            if (this := training()) is not None:
                this.add()
                if iteration == 0 and tangents():  # a load step's first iterate
                    this.add_tangents()

        with iterates(solver, add):
            yield self

    @property
    def states(self) -> int:
        """The most training states any family's forces hold."""
        return max((self.added[name] for name in self.sampled), default=0)

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
        see :meth:`matrix` and :func:`sparse_nnls`. An output's functional that vanishes at
        every training state (an average of a stress the states leave at 0) gets no cells: its
        reduced value is that 0."""
        if not self.states:
            raise ParameterError("ECSW has no training state with a load (add states first)")
        nothing = (np.zeros(0, np.int32), np.zeros(0))
        chosen = {
            name: nothing
            if is_functional(name) and not self.blocks[name]
            else sparse_nnls(self.matrix(name, tolerance), tolerance, self.comm)
            for name in self.sampled
        }
        return Sample(
            {family: cells for family, (cells, _) in chosen.items()},
            {family: weights for family, (_, weights) in chosen.items()},
            tolerance,
        )

    def destroy(self) -> None:
        for matrix in (*self._matrices.values(), *(C for _, C in self._tangents.values()), self._basis):
            matrix.destroy()


def train(
    model: Model,
    basis: Basis,
    solver: NewtonSolver,
    runs: Callable[[], object],
    tolerance: float,
    timings: dict[str, float] | None = None,
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
def iterates(solver: NewtonSolver, seen: Callable[[int], None]) -> Iterator[None]:
    """Within the block, ``seen(iteration)`` after every Newton iterate of ``solver`` (a full
    :class:`~lungmech.fem.solver.NewtonSolver`; 0: a solve's start), with the model's state set
    to that iterate."""
    active = [True]
    model = solver.model

    def monitor(snes: PETSc.SNES, iteration: int, norm: float) -> None:
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
