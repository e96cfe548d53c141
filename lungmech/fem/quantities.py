"""Global quantities and point values, MPI-safe: every reduction happens in here."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, NamedTuple

from mpi4py import MPI

import basix.ufl
import numpy as np
import ufl
from dolfinx import fem, la
from dolfinx import geometry as dgeometry

from lungmech import jit
from lungmech.errors import ParameterError

if TYPE_CHECKING:
    import dolfinx.mesh

    from lungmech.fem.model import Model


def integral(form: ufl.Form, comm: MPI.Comm) -> Callable[[], float]:
    """A function returning the global value of a scalar form (compiled once, summed over ranks)."""
    compiled = jit.form(form)
    return lambda: comm.allreduce(fem.assemble_scalar(compiled), op=MPI.SUM)


def assemble_owned(form: fem.Form, vector: la.Vector, owned: int) -> np.ndarray:
    """The owned entries of the linear ``form`` assembled into ``vector`` (a work vector of the
    form's space, overwritten); contributions of ghost cells go to their owners. Collective."""
    vector.array[:] = 0.0
    fem.assemble_vector(vector.array, form)  # type: ignore[arg-type]  # DOLFINx's into-an-array overload (singledispatch) is not in its hints
    vector.scatter_reverse(la.InsertMode.add)
    return vector.array[:owned].copy()


def vector_integral(
    expr: ufl.core.expr.Expr, measure: ufl.Measure, mesh: dolfinx.mesh.Mesh
) -> Callable[[], np.ndarray]:
    """A function returning the global integral of a vector or tensor expression, all components at once.

    One compiled form instead of one per component: the expression is tested against a
    piecewise-constant field with as many components, whose cell values are then summed.
    """
    shape = expr.ufl_shape
    flat = ufl.as_vector([expr[index] for index in np.ndindex(shape)]) if len(shape) != 1 else expr
    size = flat.ufl_shape[0]
    space = fem.functionspace(mesh, basix.ufl.element("DG", mesh.basix_cell(), 0, shape=(size,)))
    compiled = jit.form(ufl.inner(flat, ufl.TestFunction(space)) * measure)
    vector = fem.Function(space).x
    owned = space.dofmap.index_map.size_local * size

    def evaluate() -> np.ndarray:
        vector.array[:] = 0.0
        fem.assemble_vector(vector.array, compiled)
        vector.scatter_reverse(la.InsertMode.add)  # ghost cells' contributions go to their owners
        local = vector.array[:owned].reshape(-1, size).sum(axis=0)
        total = np.empty_like(local)
        mesh.comm.Allreduce(local, total, op=MPI.SUM)
        return total.reshape(shape)

    return evaluate


def deformed_volume(model: Model) -> Callable[[], float]:
    """∫ J dX: the current volume of the body."""
    return integral(ufl.det(model.F) * model.dx, model.geometry.mesh.comm)


def strain_energy(model: Model) -> Callable[[], float]:
    """∫ ψ dX (the energy density of the model's formulation)."""
    return integral(model.energy_density * model.dx, model.geometry.mesh.comm)


class Probe:
    """Values of a Function at material points, the same on every rank.

    The points are given in the mesh's configuration when the probe is made (for an imaged body:
    the image) and each is kept as its cell and reference coordinates ξ, so it follows its
    material point when the nodes move (the inverse problem's reference): the value is taken at
    x(ξ) = Σ N_i(ξ) x_i of the current nodes."""

    def __init__(self, mesh: dolfinx.mesh.Mesh, points: Sequence[Sequence[float]]) -> None:
        self.points = np.atleast_2d(np.asarray(points, dtype=float))
        gdim = mesh.geometry.dim
        if self.points.ndim != 2 or self.points.shape[1] != gdim:
            raise ParameterError(
                f"probe points need {gdim} coordinates each on a {gdim}-D mesh (got shape {self.points.shape})"
            )
        located = np.column_stack([self.points, np.zeros((len(self.points), 3 - gdim))])  # DOLFINx: 3 coordinates
        tree = dgeometry.bb_tree(mesh, mesh.topology.dim)
        candidates = dgeometry.compute_collisions_points(tree, located)
        colliding = dgeometry.compute_colliding_cells(mesh, candidates, located)
        found = np.array([len(colliding.links(i)) > 0 for i in range(len(self.points))])
        comm = mesh.comm
        # The lowest rank holding a point answers for it.
        owner = np.empty(len(self.points), dtype=np.int64)
        comm.Allreduce(np.where(found, comm.rank, comm.size).astype(np.int64), owner, op=MPI.MIN)
        missing = np.flatnonzero(owner == comm.size)
        if missing.size:
            point = ", ".join(f"{v:g}" for v in self.points[missing[0]])
            raise ParameterError(f"probe point ({point}) lies outside the mesh")
        self._mesh = mesh
        self._mine = np.flatnonzero(owner == comm.rank)
        self._cells = np.array([colliding.links(int(i))[0] for i in self._mine], dtype=np.int32)
        self._reference = np.array(
            [
                mesh.geometry.cmaps[0].pull_back(self.points[[i]], self._nodes(c))[0]
                for i, c in zip(self._mine, self._cells)
            ]
        ).reshape(len(self._mine), mesh.topology.dim)
        self._comm = comm

    def _nodes(self, cell: int) -> np.ndarray:
        """The current positions of a cell's geometry nodes, (nodes, gdim)."""
        geometry = self._mesh.geometry
        return geometry.x[geometry.dofmaps[0][cell], : geometry.dim]

    def positions(self) -> np.ndarray:
        """Where this rank's material points are now, (points, 3)."""
        now = np.zeros((len(self._mine), 3))
        for row, (xi, cell) in enumerate(zip(self._reference, self._cells)):
            now[row, : self._mesh.geometry.dim] = self._mesh.geometry.cmaps[0].push_forward(
                xi[None, :], self._nodes(cell)
            )[0]
        return now

    def __call__(self, function: fem.Function) -> np.ndarray:
        """Values at the points, shape (number of points, value size)."""
        values = np.zeros((len(self.points), function.function_space.value_size))
        if self._mine.size:
            values[self._mine] = function.eval(self.positions(), self._cells).reshape(len(self._mine), -1)
        total = np.empty_like(values)
        self._comm.Allreduce(values, total, op=MPI.SUM)
        return total


class Reaction(NamedTuple):
    force: np.ndarray  # resultant, shape (3,) (a plane body's: per unit thickness, z = 0)
    moment: np.ndarray  # about the origin, with the nodes at their current positions


def reaction(model: Model, boundary: str) -> Callable[[], Reaction]:
    """The force and moment the supports exert on ``boundary``, from the residual at its nodes.

    At equilibrium the residual vanishes except at imposed dofs, where it is the support's
    nodal force; so the reaction balances every other force on the body, and measures what a
    held region (the hilum) carries.
    """
    space = model.displacement_space
    collapsed, parent_map = space.collapse() if model.multi_field else (space, np.arange(len(model.state.x.array)))
    parent = np.asarray(parent_map).ravel()  # DOLFINx 0.11 gives the map as a list of one array
    bs = collapsed.dofmap.index_map_bs
    fdim = model.geometry.mesh.topology.dim - 1
    blocks = fem.locate_dofs_topological(collapsed, fdim, model.geometry.facets(boundary))
    blocks = blocks[blocks < collapsed.dofmap.index_map.size_local]  # each node counted once, by its owner
    dofs = np.asarray(parent)[blocks[:, None] * bs + np.arange(bs)]  # (nodes, components) in the state
    nodes = collapsed.tabulate_dof_coordinates()[blocks, :bs]
    residual = jit.form(model.residual)
    vector = fem.Function(model.space).x

    def evaluate() -> Reaction:
        vector.array[:] = 0.0
        fem.assemble_vector(vector.array, residual)
        vector.scatter_reverse(la.InsertMode.add)
        # 3-D vectors: a plane body's reaction lies in its plane, its moment along z
        forces, positions = np.zeros((len(dofs), 3)), np.zeros((len(dofs), 3))
        forces[:, :bs] = vector.array[dofs]
        positions[:, :bs] = nodes + model.state.x.array[dofs]
        local = np.concatenate([forces.sum(axis=0), np.cross(positions, forces).sum(axis=0)])
        total = np.empty_like(local)
        model.geometry.mesh.comm.Allreduce(local, total, op=MPI.SUM)
        return Reaction(total[:3], total[3:])

    return evaluate
