"""A partition-independent order of a model's dofs, and the mesh fingerprint that goes with it.

DOLFINx numbers dofs differently on every partition, so a basis written from 4 ranks could not be
read on 1. Each owned dof is keyed by (field, component, quantised coordinates of its node); the
sorted keys give every dof a global position that depends only on the mesh and the element, and
their hash is the fingerprint that a stored reduced model checks before it is used.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
from dolfinx import fem
from mpi4py import MPI

_RESOLUTION = 1e-9  # coordinates are compared on a grid of 1e-9 × the mesh diameter


@dataclass(frozen=True)
class Layout:
    """Canonical position of every owned dof of a state vector, and the mesh fingerprint."""

    index: np.ndarray  # canonical global index of owned local dof i
    size: int  # global number of dofs
    fingerprint: str
    comm: MPI.Comm

    def gather(self, local: np.ndarray) -> np.ndarray:
        """Rows of every rank in canonical order, on every rank: (owned, k) -> (size, k)."""
        pieces = self.comm.allgather((self.index, np.asarray(local)))
        result = np.empty((self.size, *np.shape(local)[1:]), dtype=float)
        for index, values in pieces:
            result[index] = values
        return result

    def scatter(self, canonical: np.ndarray) -> np.ndarray:
        """This rank's owned rows of a canonically ordered array."""
        return np.asarray(canonical)[self.index]


def layout(space: fem.FunctionSpace) -> Layout:
    """The canonical layout of ``space`` (a displacement or mixed space of a model)."""
    comm = space.mesh.comm
    owned = space.dofmap.index_map.size_local * space.dofmap.index_map_bs
    keys = np.zeros((owned, 5), dtype=np.int64)
    seen = np.zeros(owned, dtype=bool)
    grid = _RESOLUTION * _diameter(space.mesh)
    for field, (collapsed, parent) in enumerate(field_dofs(space)):
        bs = collapsed.dofmap.index_map_bs
        nodes = collapsed.dofmap.index_map.size_local
        points = np.round(collapsed.tabulate_dof_coordinates()[:nodes] / grid).astype(np.int64)
        for component in range(bs):
            rows = parent[np.arange(nodes) * bs + component]
            keys[rows, 0], keys[rows, 1], keys[rows, 2:] = field, component, points
            seen[rows] = True
    assert seen.all(), "every owned dof belongs to exactly one field"

    pieces = comm.allgather(keys)
    everything = np.concatenate(pieces)
    order = np.lexsort(everything.T[::-1])
    position = np.empty(len(order), dtype=np.int64)
    position[order] = np.arange(len(order))
    offset = sum(len(k) for k in pieces[: comm.rank])
    digest = hashlib.sha256(str(space.ufl_element()).encode())
    digest.update(np.ascontiguousarray(everything[order]).tobytes())
    digest.update(_cell_midpoints(space.mesh, grid).tobytes())  # the connectivity, not only the nodes
    return Layout(position[offset : offset + owned], len(order), digest.hexdigest()[:16], comm)


def field_dofs(space: fem.FunctionSpace) -> list[tuple[fem.FunctionSpace, np.ndarray]]:
    """(collapsed space, its dofs in ``space``) per field: one for a plain (vector) space."""
    mixed = space.dofmap.index_map_bs == 1 and space.ufl_element().num_sub_elements > 1
    if not mixed:
        return [(space, np.arange(space.dofmap.index_map.size_local * space.dofmap.index_map_bs))]
    fields = [space.sub(i).collapse() for i in range(space.ufl_element().num_sub_elements)]
    return [(collapsed, np.asarray(parent).ravel()) for collapsed, parent in fields]


def _cell_midpoints(mesh, grid: float) -> np.ndarray:
    """Quantised midpoints of every cell, sorted (identical on any partition)."""
    cells = mesh.topology.index_map(mesh.topology.dim).size_local
    nodes = mesh.geometry.dofmaps[0][:cells]
    midpoints = np.round(mesh.geometry.x[nodes].mean(axis=1) / grid).astype(np.int64)
    everything = np.concatenate(mesh.comm.allgather(midpoints))
    return np.ascontiguousarray(everything[np.lexsort(everything.T[::-1])])


def _diameter(mesh) -> float:
    """The diagonal of the mesh's bounding box (collective)."""
    x = mesh.geometry.x
    local = np.concatenate([x.min(axis=0), -x.max(axis=0)]) if len(x) else np.full(6, np.inf)
    bounds = np.empty_like(local)
    mesh.comm.Allreduce(np.ascontiguousarray(local, dtype=np.float64), bounds, op=MPI.MIN)
    return float(np.linalg.norm(-bounds[3:] - bounds[:3]))
