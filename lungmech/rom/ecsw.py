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

from dataclasses import dataclass

from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh

from lungmech.errors import ParameterError
from lungmech.fem.averages import averages
from lungmech.fem.model import Model

__all__ = [
    "AVERAGE",
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
    "is_functional",
    "over_cells",
    "sampled_residual",
    "sparse_nnls",
    "train",
    "iterates",
]

# The families sampled, each with its own weights, and their integral type: the cells' internal
# forces (of the energy density), the loads on cells (weight) and on the boundary (pressures).
FAMILIES = {"internal": "cell", "cell_load": "cell", "boundary_load": "exterior_facet"}
# Scalar functionals (cell integrals) sampled the same way, for outputs: their cells' values are
# the columns, each training state one row scaled by the functional's value there. Every model
# has the strain energy; a formulation's averages add their numerators, named AVERAGE + name.
FUNCTIONALS = ("strain_energy",)
AVERAGE = "average_"


def is_functional(name: str) -> bool:
    """Whether the sampled ``name`` is an output's functional (not part of the residual)."""
    return name in FUNCTIONALS or name.startswith(AVERAGE)


class WeightedForms:
    """The model's residual R = R_int + R_load with a weight per cell on each family's integrals.

    ``weights[family]`` is the DG0 field of that family's weights (1 everywhere: ``residual`` is
    the model's). :meth:`contribution` is the derivative with respect to one family's weights,
    a rectangular form whose assembled column e is the residual of cell e's integrals of that
    family (an exterior facet's: of its one cell). ``functionals`` are the scalar outputs
    sampled alike, with weights of their own: the strain energy ∫ ψ dX and the numerators
    ∫ f w dX of the formulation's averages (:mod:`lungmech.fem.averages`), named
    :data:`AVERAGE` + the average's name."""

    def __init__(self, model: Model) -> None:
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
        densities = {"strain_energy": model.energy_density} | {
            AVERAGE + name: average.weighted(model) for name, average in averages(model).items()
        }
        names = (*FAMILIES, *densities, *self.integrals)
        self.weights = {name: fem.Function(space, name=f"{name}_weight") for name in names}
        for weight in self.weights.values():
            weight.x.array[:] = 1.0
        self.families = tuple(family for family, integrals in parts.items() if integrals)
        self.parts = {
            family: [i.reconstruct(integrand=self.weights[family] * i.integrand()) for i in parts[family]]
            for family in self.families
        }
        self.residual = ufl.Form([i for family in self.families for i in self.parts[family]])
        self.functionals = {name: self.weights[name] * density * model.dx for name, density in densities.items()}

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


def _integrals(form: ufl.Form, kind: str) -> list:
    return [integral for integral in form.integrals() if integral.integral_type() == kind]


def flattened(expr: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """A vector of the entries of a scalar, vector or tensor expression."""
    shape = expr.ufl_shape
    if len(shape) == 1:
        return expr
    return ufl.as_vector([expr[index] for index in np.ndindex(shape)] if shape else [expr])


@dataclass(frozen=True)
class Sample:
    """The sampled owned cells of each family (local indices) and their weights (> 0)."""

    cells: dict[str, np.ndarray]
    weights: dict[str, np.ndarray]
    tolerance: float

    def count(self, comm: MPI.Comm) -> dict[str, int]:
        """How many cells each family samples, over all ranks."""
        return {family: comm.allreduce(len(cells), op=MPI.SUM) for family, cells in self.cells.items()}

    def described(self, comm: MPI.Comm) -> str:
        """The sampled cells in words: per family of the residual (and state-dependent load's
        integral), then the outputs' functionals' together (collective)."""
        counts = self.count(comm)
        outputs = [name for name in counts if is_functional(name)]
        solved = ", ".join(f"{n} {name.replace('_', ' ')}" for name, n in counts.items() if name not in outputs)
        mine = np.unique(np.concatenate([self.cells[name] for name in outputs] + [NO_CELLS]))
        averaged = sum(name.startswith(AVERAGE) for name in outputs)
        what = ["strain energy"] * ("strain_energy" in outputs) + [f"{averaged} averages"] * bool(averaged)
        cells = comm.allreduce(len(mine), op=MPI.SUM)
        return f"{solved} sampled cells" + (f"; its outputs ({', '.join(what)}) on {cells} cells" if what else "")

    def cells_per_type(self, comm: MPI.Comm) -> dict[str, int]:
        """How many distinct cells the residual's sample holds per integral type, over all ranks
        (what a Newton iteration assembles; the functionals' samples are assembled for outputs)."""
        counts = {}
        for kind in ("cell", "exterior_facet"):
            cells = [c for family, c in self.cells.items() if FAMILIES.get(family) == kind]
            mine = len(np.unique(np.concatenate(cells))) if cells else 0
            counts[kind] = comm.allreduce(mine, op=MPI.SUM)
        return counts

    def export(self, mesh: dmesh.Mesh) -> dict[str, np.ndarray]:
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
    def place(mesh: dmesh.Mesh, data: dict[str, np.ndarray], tolerance: float) -> Sample:
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


def sampled_residual(forms: WeightedForms, mesh: dmesh.Mesh, sample: Sample) -> ufl.Form:
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


def over_cells(form: ufl.Form, mesh: dmesh.Mesh, cells: np.ndarray) -> ufl.Form:
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


def _facets_of(mesh: dmesh.Mesh, tags: dmesh.MeshTags, cells: np.ndarray) -> dmesh.MeshTags:
    """The boundary facet tags ``tags`` kept on the facets of ``cells`` only."""
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim, tdim - 1)
    connectivity = mesh.topology.connectivity(tdim, tdim - 1)
    mine = np.unique(np.concatenate([connectivity.links(c) for c in cells])) if len(cells) else np.zeros(0, np.int32)
    keep = np.isin(tags.indices, mine)
    return dmesh.meshtags(mesh, tdim - 1, tags.indices[keep], tags.values[keep])


# The training, in a module of its own, under the names it always had here.
from lungmech.rom.ecsw_training import (  # noqa: E402
    COMPRESS_ROWS,
    COMPRESSION,
    TANGENT,
    TANGENT_STATES,
    TANGENT_TOLERANCE,
    Training,
    iterates,
    train,
)
