"""A mesh's geometry nodes: where they are, vector fields on them, and the one place that moves them.

Every change of a mesh's reference configuration goes through :func:`move`, :func:`place` or
:func:`deformed`: the inverse problem replaces the imaged nodes by the unloaded reference, a
reduced model puts back the reference it was built on, registration maps a reference mesh onto
an image. Nothing is recompiled when nodes move: forms read the coordinates at assembly.

A nodal field is a vector Lagrange field of the mesh's own geometry degree, so its dofs sit on
the geometry nodes (:func:`displacement_space`). Written in the canonical order of
:mod:`lungmech.parallel.layout` (all x components, then y, then z, each in the same node order)
it reads the same on any number of MPI ranks. Canonical (nodes, gdim) arrays live on rank 0 only:
:func:`gather`, :func:`positions` and :func:`masses` return them there (None elsewhere), and
:func:`scatter` and :func:`place_canonical` read them there.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

import numpy as np
import numpy.typing as npt
import ufl
from dolfinx import fem, la
from dolfinx import mesh as dmesh

from lungmech import jit
from lungmech.parallel.layout import Layout, layout
from lungmech.parallel.owned import owned_size

__all__ = [
    "deformed",
    "displacement_space",
    "gather",
    "masses",
    "move",
    "move_nodes",
    "node_dofs",
    "place",
    "positions",
    "place_canonical",
    "sampler",
    "scatter",
]


def node_dofs(space: fem.FunctionSpace) -> npt.NDArray[np.int64]:
    """The dof (block) of every geometry node, owned and ghost, for a Lagrange space of the
    mesh's own degree: both numberings enumerate the same points cell by cell."""
    mesh = space.mesh
    node_of_dof = np.empty(space.dofmap.index_map.size_local + space.dofmap.index_map.num_ghosts, dtype=np.int64)
    node_of_dof[space.dofmap.list.ravel()] = mesh.geometry.dofmaps[0].ravel()
    dof_of_node = np.empty_like(node_of_dof)
    dof_of_node[node_of_dof] = np.arange(node_of_dof.size)
    return dof_of_node


def displacement_space(mesh: dmesh.Mesh) -> tuple[fem.FunctionSpace, Layout]:
    """Collective: the vector Lagrange space on the geometry nodes and its canonical layout."""
    space = fem.functionspace(mesh, ("Lagrange", mesh.geometry.cmaps[0].degree, (mesh.geometry.dim,)))
    return space, layout(space)


def gather(function: fem.Function, where: Layout) -> np.ndarray | None:
    """Collective: a nodal vector field as (nodes, gdim) in canonical node order on rank 0, None
    elsewhere."""
    bs = function.function_space.dofmap.index_map_bs
    owned = function.function_space.dofmap.index_map.size_local * bs
    canonical = where.gather(function.x.array[:owned])
    # Canonical dofs are sorted by (component, node): all x components, then y, then z.
    return None if canonical is None else canonical.reshape(bs, -1).T


def positions(space: fem.FunctionSpace, where: Layout) -> np.ndarray | None:
    """Collective: the nodes' current positions (nodes, gdim) in canonical order on rank 0, None
    elsewhere."""
    identity = fem.Function(space)
    identity.interpolate(lambda x: x[: space.mesh.geometry.dim])
    return gather(identity, where)


def scatter(values: np.ndarray | None, function: fem.Function, where: Layout) -> None:
    """Collective: set ``function`` (ghosts included) from canonical (nodes, gdim) ``values``
    given on rank 0 (the other ranks may pass None)."""
    owned = owned_size(function.function_space)
    canonical = None if values is None else np.asarray(values).T.ravel()
    function.x.array[:owned] = where.scatter(canonical)
    function.x.scatter_forward()


def masses(space: fem.FunctionSpace, where: Layout) -> np.ndarray | None:
    """Collective: lumped nodal masses (row sums of the mass matrix) in canonical order, summing
    to 1, on rank 0; None elsewhere."""
    v = ufl.TestFunction(space)
    lumped = fem.assemble_vector(jit.form(v[0] * ufl.dx(domain=space.mesh)))
    lumped.scatter_reverse(la.InsertMode.add)
    bs = space.dofmap.index_map_bs
    owned = space.dofmap.index_map.size_local * bs
    canonical = where.gather(lumped.array[:owned])
    if canonical is None:
        return None
    nodes = canonical.reshape(bs, -1)[0]
    return nodes / nodes.sum()


def sampler(mesh: dmesh.Mesh) -> Callable[[fem.Function], np.ndarray]:
    """A function that returns a vector field's values at the geometry nodes (owned and ghost,
    the mesh's local node order), shape (nodes, gdim); the nodal space is made once."""
    space, _ = displacement_space(mesh)
    dof_of_node = node_dofs(space)
    at_nodes = fem.Function(space)

    def sample(function: fem.Function) -> np.ndarray:
        at_nodes.interpolate(function)
        return at_nodes.x.array.reshape(-1, mesh.geometry.dim)[dof_of_node]

    return sample


def move(mesh: dmesh.Mesh, by: np.ndarray) -> None:
    """Move every node (owned and ghost, local node order) by ``by``, shape (nodes, gdim)."""
    mesh.geometry.x[:, : mesh.geometry.dim] += by


def place(mesh: dmesh.Mesh, x: np.ndarray) -> None:
    """Put every node (owned and ghost, local node order) at ``x``, shape (nodes, gdim)."""
    mesh.geometry.x[:, : mesh.geometry.dim] = x


def move_nodes(displacement: fem.Function) -> None:
    """Move the mesh's nodes by a nodal displacement field (in place: the mesh becomes Φ(Ω))."""
    mesh = displacement.function_space.mesh
    displacement.x.scatter_forward()
    move(mesh, displacement.x.array.reshape(-1, mesh.geometry.dim)[node_dofs(displacement.function_space)])


@contextlib.contextmanager
def deformed(displacement: fem.Function) -> Iterator:
    """Within the block the mesh's nodes sit at X + u; afterwards they are restored."""
    mesh = displacement.function_space.mesh
    reference = mesh.geometry.x.copy()
    move_nodes(displacement)
    try:
        yield mesh
    finally:
        mesh.geometry.x[:] = reference


def place_canonical(space: fem.FunctionSpace, where: Layout, x: np.ndarray | None) -> None:
    """Collective: put the nodes at ``x`` (nodes, gdim), given on rank 0 in the canonical order
    ``where`` of ``space`` (a :func:`displacement_space`; its order is topological, so it holds
    after the nodes moved). The other ranks may pass None."""
    target = fem.Function(space)
    scatter(x, target, where)
    place(space.mesh, target.x.array.reshape(-1, space.mesh.geometry.dim)[node_dofs(space)])
