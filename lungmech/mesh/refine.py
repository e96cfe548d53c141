"""Nested uniform refinement of a geometry: every simplex cut into 2^d children.

A refined geometry is the same body (the same polyhedron: the new nodes are edge midpoints),
so a sequence of refinements measures the discretisation's convergence alone, with no change
of shape between levels. Its boundaries keep their names and tags, its cells their tags, and
each child cell knows its parent (:attr:`Refined.parents`), through which values given per
cell of the coarse mesh pass unchanged (:func:`Refined.cell_values`: a file of cell values
in the coarse mesh's cell order becomes one in the refined mesh's).

Collective: under MPI, call on all ranks. The children stay on their parent's rank.
"""

from __future__ import annotations

from dataclasses import dataclass

from mpi4py import MPI

import dolfinx.la
import dolfinx.mesh
import numpy as np
import numpy.typing as npt

from lungmech.errors import GeometryError
from lungmech.mesh.geometry import Geometry

__all__ = ["Refined", "refined"]

SIMPLICES = ("interval", "triangle", "tetrahedron")


@dataclass(frozen=True, eq=False)
class Refined:
    """A refined ``geometry`` and, for each of this rank's owned cells of it, the local index
    of its ``parents``' cell in the coarse ``coarse`` geometry."""

    geometry: Geometry
    coarse: Geometry
    parents: npt.NDArray[np.int32]

    def cell_values(self, values: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Values per cell in the coarse mesh's input (file) order → the same per child, in the
        refined mesh's input order, on every rank (a child takes its parent's value: exact for
        a field constant per cell). Collective."""
        coarse_mesh, mesh = self.coarse.mesh, self.geometry.mesh
        given = np.asarray(values, dtype=np.float64).ravel()
        total = coarse_mesh.topology.index_map(coarse_mesh.topology.dim).size_global
        if given.size != total:
            raise GeometryError(f"{given.size} cell values for a mesh of {total} cells")
        coarse_inputs = np.asarray(coarse_mesh.topology.original_cell_index, dtype=np.int64)
        owned = mesh.topology.index_map(mesh.topology.dim).size_local
        inputs = np.asarray(mesh.topology.original_cell_index, dtype=np.int64)[:owned]
        mine = (inputs, given[coarse_inputs[self.parents]])
        parts = mesh.comm.allgather(mine)
        refined = np.empty(mesh.topology.index_map(mesh.topology.dim).size_global)
        for where, value in parts:
            refined[where] = value
        return refined


def refined(geometry: Geometry, times: int = 1) -> Refined:
    """``geometry`` refined uniformly ``times`` times (each edge halved: 2^d children per cell),
    its facet tags, boundary names and cell tags carried over (see the module's doc). Straight
    (affine) simplices only: DOLFINx refines no hexahedra and no curved cells."""
    if isinstance(times, bool) or not isinstance(times, int | np.integer) or times < 1:
        raise GeometryError(f"refine a mesh one or more times (got {times!r})")
    mesh = geometry.mesh
    name = mesh.topology.cell_name()
    if name not in SIMPLICES:
        raise GeometryError(f"{geometry.source or 'the mesh'} has {name} cells: only simplex meshes are refined")
    if mesh.geometry.cmaps[0].degree != 1:
        raise GeometryError(
            f"{geometry.source or 'the mesh'} has curved cells (geometry of degree {mesh.geometry.cmaps[0].degree}): "
            "only straight cells are refined"
        )
    current, parents = geometry, None
    for _ in range(int(times)):
        current, step = _once(current)
        parents = step if parents is None else parents[step]
    assert parents is not None
    return Refined(current, geometry, parents)


def _once(geometry: Geometry) -> tuple[Geometry, npt.NDArray[np.int32]]:
    """One uniform refinement, and each owned child's parent (local index)."""
    mesh = geometry.mesh
    tdim = mesh.topology.dim
    mesh.topology.create_entities(1)
    mesh.topology.create_connectivity(tdim - 1, tdim)
    fine, parent_cells, parent_facets = dolfinx.mesh.refine(
        mesh, option=dolfinx.mesh.RefinementOption.parent_cell_and_facet
    )
    # The parents are listed in the children's order before the mesh was built, which numbers
    # a rank's owned cells from its first global index on, then reorders them.
    cells = fine.topology.index_map(tdim)
    created = np.asarray(fine.topology.original_cell_index[: cells.size_local], dtype=np.int64) - cells.local_range[0]
    _check_partition(fine.comm, created, len(parent_cells))
    parents = np.asarray(parent_cells, dtype=np.int32)[created]
    facets = np.asarray(parent_facets, dtype=np.int64).reshape(len(parent_cells), -1)[created]
    facet_tags = _facet_tags(geometry, fine, parents, facets)
    cell_tags = None
    if geometry.cell_tags is not None:
        cell_tags = _tags(fine, tdim, _on_entities(geometry.cell_tags, mesh, tdim)[parents], np.arange(len(parents)))
        cell_tags.name = geometry.cell_tags.name
    source = f"{geometry.source or 'the mesh'} refined"
    refined_geometry = Geometry(fine, facet_tags, geometry.boundaries, cell_tags, source)
    return refined_geometry, parents


def _facet_tags(
    geometry: Geometry, fine: dolfinx.mesh.Mesh, parents: npt.NDArray[np.int32], facets: npt.NDArray[np.int64]
) -> dolfinx.mesh.MeshTags:
    """The coarse facet tags on the refined mesh: a child cell's local facet ``j`` lies in its
    parent's local facet ``facets[c, j]`` (−1: inside the parent), and takes that facet's tag.
    (DOLFINx's own transfer refuses ghosted meshes.)"""
    mesh, tdim = geometry.mesh, geometry.mesh.topology.dim
    coarse = _on_entities(geometry.facet_tags, mesh, tdim - 1)
    mesh.topology.create_connectivity(tdim, tdim - 1)
    fine.topology.create_entities(tdim - 1)
    fine.topology.create_connectivity(tdim, tdim - 1)
    coarse_facets = _cell_facets(mesh)[parents]  # per child: its parent's facets
    fine_facets = _cell_facets(fine)[: len(parents)]
    inside = facets < 0
    values = np.where(inside, 0, coarse[np.take_along_axis(coarse_facets, np.maximum(facets, 0), axis=1)])
    tagged = values > 0
    tags = _tags(fine, tdim - 1, values[tagged], fine_facets[tagged])
    tags.name = geometry.facet_tags.name
    return tags


def _cell_facets(mesh: dolfinx.mesh.Mesh) -> npt.NDArray[np.int64]:
    """Each local cell's facets, one row per cell (simplices: d + 1 each)."""
    tdim = mesh.topology.dim
    links = mesh.topology.connectivity(tdim, tdim - 1).array
    return np.asarray(links, dtype=np.int64).reshape(-1, tdim + 1)


def _on_entities(tags: dolfinx.mesh.MeshTags, mesh: dolfinx.mesh.Mesh, dim: int) -> npt.NDArray[np.int32]:
    """A tag per local entity of dimension ``dim`` (0: none)."""
    index_map = mesh.topology.index_map(dim)
    values = np.zeros(index_map.size_local + index_map.num_ghosts, dtype=np.int32)
    values[tags.indices] = tags.values
    return values


def _tags(
    mesh: dolfinx.mesh.Mesh, dim: int, values: npt.NDArray[np.int32], entities: npt.NDArray[np.int64]
) -> dolfinx.mesh.MeshTags:
    """MeshTags of ``entities`` (local, set by the owned cells of this rank) made the same on every
    rank that sees them: each entity's (value, count) summed onto its owner, the mean (the one
    value all its setters gave) copied to the ranks that ghost it."""
    index_map = mesh.topology.index_map(dim)
    vector = dolfinx.la.vector(index_map, 2)
    pairs = vector.array.reshape(-1, 2)
    pairs[:] = 0.0
    unique, first = np.unique(entities, return_index=True)  # an entity set twice by one rank counts once
    pairs[unique] = np.column_stack([values[first], np.ones(len(unique))])
    vector.scatter_reverse(dolfinx.la.InsertMode.add)
    vector.scatter_forward()
    tagged = np.flatnonzero(pairs[:, 1] > 0.5).astype(np.int32)
    return dolfinx.mesh.meshtags(mesh, dim, tagged, np.rint(pairs[tagged, 0] / pairs[tagged, 1]).astype(np.int32))


def _check_partition(comm: MPI.Comm, created: npt.NDArray[np.int64], parents: int) -> None:
    """Every owned child has its parent on this rank (DOLFINx's identity partitioner)."""
    kept = created.size == parents and (not created.size or (created.min() >= 0 and created.max() < parents))
    if not comm.allreduce(bool(kept), op=MPI.LAND):
        raise GeometryError("the refined mesh was redistributed: its cells' parents are not on their ranks")
