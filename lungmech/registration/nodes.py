"""Mappings of a mesh as nodal displacement fields: canonical node order, nodal masses, and
moving the mesh's nodes.

A mapping Φ = Id + u of a mesh is a vector Lagrange field u of the mesh's own geometry degree, so
its dofs sit on the geometry nodes. Written in the canonical order of :mod:`lungmech.rom.layout`
((component, node) sorted by coordinates), it reads the same on any number of MPI ranks.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np
import ufl
from dolfinx import fem, la

from lungmech.geometry import node_dofs
from lungmech.rom.layout import Layout, layout

__all__ = ["deformed", "displacement_space", "gather", "masses", "move_nodes", "positions", "scatter"]


def displacement_space(mesh) -> tuple[fem.FunctionSpace, Layout]:
    """The vector Lagrange space on the geometry nodes and its canonical layout (collective)."""
    space = fem.functionspace(mesh, ("Lagrange", mesh.geometry.cmaps[0].degree, (3,)))
    return space, layout(space)


def gather(function: fem.Function, where: Layout) -> np.ndarray:
    """A nodal vector field as (nodes, 3) in canonical node order, on every rank (collective)."""
    owned = function.function_space.dofmap.index_map.size_local * 3
    # Canonical dofs are sorted by (component, node): all x components, then y, then z.
    return where.gather(function.x.array[:owned]).reshape(3, -1).T


def positions(space: fem.FunctionSpace, where: Layout) -> np.ndarray:
    """The nodes' current positions (nodes, 3) in canonical order, on every rank (collective)."""
    identity = fem.Function(space)
    identity.interpolate(lambda x: x)
    return gather(identity, where)


def scatter(values: np.ndarray, function: fem.Function, where: Layout) -> None:
    """Set ``function`` from canonical (nodes, 3) values (ghosts included)."""
    owned = function.function_space.dofmap.index_map.size_local * 3
    function.x.array[:owned] = where.scatter(np.asarray(values).T.ravel())
    function.x.scatter_forward()


def masses(space: fem.FunctionSpace, where: Layout) -> np.ndarray:
    """Lumped nodal masses (row sums of the mass matrix) in canonical order, summing to 1."""
    v = ufl.TestFunction(space)
    lumped = fem.assemble_vector(fem.form(v[0] * ufl.dx(domain=space.mesh)))
    lumped.scatter_reverse(la.InsertMode.add)
    owned = space.dofmap.index_map.size_local * 3
    nodes = where.gather(lumped.array[:owned]).reshape(3, -1)[0]
    return nodes / nodes.sum()


def move_nodes(displacement: fem.Function) -> None:
    """Move the mesh's nodes by the displacement (in place: the mesh becomes Φ(Ω))."""
    mesh = displacement.function_space.mesh
    displacement.x.scatter_forward()
    mesh.geometry.x[:, :3] += displacement.x.array.reshape(-1, 3)[node_dofs(displacement.function_space)]


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
