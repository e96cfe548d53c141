"""A reduced mesh: the cells a hyper-reduced model integrates over, as a mesh of their own.

A hyper-reduced model evaluates the full model's forms on a few sampled cells only. Assembling
them into vectors and matrices of the full space would still cost O(mesh) per Newton iteration
(zeroing, ghost updates, products with the basis), so the sampled cells become a DOLFINx submesh
with the model's space on it: the state, the test and the trial functions of the forms move to
that space, while the integrals stay on the full mesh's sampled cells and every other coefficient
(material fields, loads, weights) stays where it lives, reached through the submesh's entity map.
Vectors and matrices then have the sample's dofs only, and so has the basis restricted to them.

The sub dofs are tied to the full ones cell by cell (the same element on the same cell, in the
same local order): :attr:`ReducedMesh.parent_dofs` restricts any full state array.
"""

from __future__ import annotations

from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from ufl.algorithms import expand_derivatives

from lungmech import jit
from lungmech.fem.model import Model

__all__ = ["ReducedMesh"]


class ReducedMesh:
    """The owned ``cells`` (local indices) of ``model``'s mesh as a submesh, with the model's
    space and a state on it (collective). On a body of sampled cells (:mod:`lungmech.rom.body`)
    that ``cells`` cover on every rank, the body is the reduced mesh, its space and state the
    model's own; a sample covering part of one (an imaged body's inverse motion, whose sample
    shares the body with the breath's) gets a submesh of its cells, so that its vectors and
    products with the basis hold its own cells' dofs, not the whole body's."""

    def __init__(self, model: Model, cells: np.ndarray) -> None:
        parent = model.geometry.mesh
        tdim = parent.topology.dim
        self.model = model
        self.cells = np.unique(np.asarray(cells, dtype=np.int32))
        index_map, bs = model.space.dofmap.index_map, model.space.dofmap.index_map_bs
        if self._covers_a_body():  # the model's own mesh: nothing to move
            self.mesh, self.entity_map, self.space, self.state = parent, None, model.space, model.state
            self.owned = index_map.size_local * bs
            self.parent_dofs = np.arange((index_map.size_local + index_map.num_ghosts) * bs)
            return
        self.mesh, self.entity_map, _, _ = dmesh.create_submesh(parent, tdim, self.cells)
        self.space = fem.functionspace(self.mesh, model.space.ufl_element())
        self.state = fem.Function(self.space, name="reduced_mesh_state")
        index_map, bs = self.space.dofmap.index_map, self.space.dofmap.index_map_bs
        self.owned = index_map.size_local * bs  # owned sub dofs, unrolled
        self.parent_dofs = self._parent_dofs(bs)

    def _covers_a_body(self) -> bool:
        """Whether the model's mesh is a body of sampled cells and :attr:`cells` are all of its
        cells, on every rank (collective)."""
        if self.model.geometry.whole is None:
            return False
        mesh = self.model.geometry.mesh
        everything = len(self.cells) == mesh.topology.index_map(mesh.topology.dim).size_local
        return bool(mesh.comm.allreduce(everything, op=MPI.LAND))

    def _parent_dofs(self, bs: int) -> np.ndarray:
        """For every local sub dof (owned, then ghost; unrolled), the full space's local dof."""
        assert self.entity_map is not None  # a submesh (not the model's whole mesh) has its entity map
        sub_cells = np.arange(self.mesh.topology.index_map(self.mesh.topology.dim).size_local, dtype=np.int32)
        parents = self.entity_map.sub_topology_to_topology(sub_cells, inverse=False)
        sub_map, full_map = self.space.dofmap, self.model.space.dofmap
        index_map = sub_map.index_map
        blocks = np.full(index_map.size_local + index_map.num_ghosts, -1, dtype=np.int64)
        for cell, parent in zip(sub_cells, parents):
            blocks[sub_map.cell_dofs(cell)] = full_map.cell_dofs(parent)
        return (bs * blocks[:, None] + np.arange(bs)).reshape(-1)

    def restrict(self, x: np.ndarray) -> np.ndarray:
        """The entries of a full local array (owned and ghost; rows of a 2-D one) on the sub dofs."""
        return x[self.parent_dofs]

    def restrict_columns(self, vectors: np.ndarray) -> np.ndarray:
        """Owned rows of full-space vectors (columns) on the sub dofs, ghosts included (collective)."""
        full = fem.Function(self.model.space)
        owned = vectors.shape[0]
        restricted = np.empty((len(self.parent_dofs), vectors.shape[1]))
        for i in range(vectors.shape[1]):
            full.x.array[:owned] = vectors[:, i]
            full.x.scatter_forward()
            restricted[:, i] = full.x.array[self.parent_dofs]
        return restricted

    def expression(self, expr: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
        """``expr`` of the model's state, as one of the state on the submesh (evaluated there)."""
        return expr if self.entity_map is None else ufl.replace(expr, {self.model.state: self.state})

    def form(self, form: ufl.Form) -> fem.Form:
        """``form`` (in the model's state, test and trial functions; integrals over the sampled
        cells) compiled with them on the submesh. Arguments of other spaces (already on the
        submesh) stay."""
        if self.entity_map is None:
            return jit.form(form)
        expanded = expand_derivatives(form)
        mapping: dict[ufl.core.expr.Expr, ufl.core.expr.Expr] = {self.model.state: self.state}
        for argument in expanded.arguments():
            if argument.ufl_function_space() == self.model.space:
                mapping[argument] = ufl.Argument(self.space, argument.number(), argument.part())
        return jit.form(ufl.replace(expanded, mapping), entity_maps=[self.entity_map])
