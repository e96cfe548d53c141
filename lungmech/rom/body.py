"""The body of a hyper-reduced model: its sampled cells, as a mesh of their own.

A hyper-reduced model integrates over a few sampled cells (:mod:`lungmech.rom.ecsw`). Online it
needs those cells only: their reference nodes and tags (regions, named boundaries), the values
there of the model's material fields, and the rows there of its basis, start state and imposed
displacements. :func:`export` takes them from the full model (offline); :func:`geometry` makes
the cells a mesh of their own and :func:`place` puts the values back (online, with no full mesh:
the load is flat in the mesh size).

Sampled cells that share a node in the full mesh share it in the body (a model file written
before they did keeps its cells apart, each with nodes of its own: the answers are the same, the
body's vectors longer). Every integral a hyper-reduced model evaluates is a sum of cell integrals
and tagged exterior-facet integrals, each a function of its own cell's dofs, so cells joined or
apart give the same sums, and a dof sits, with its value, in every cell that holds it. A cell
keeps its nodes in the full mesh's local order, and their input numbers in the same relative
order, so that DOLFINx lays out its dofs as on the full mesh (by the input order of the vertices:
:mod:`lungmech.parallel.layout`) and numbers its facets alike: values are copied position by
position, and a facet's tag goes with its local number. A facet two sampled cells share is
interior to the body as to the full mesh, and carries no exterior-facet integral in either.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from mpi4py import MPI

import basix.ufl
import dolfinx.mesh as dmesh
import numpy as np
from dolfinx import fem
from ufl.algorithms import extract_coefficients

from lungmech.errors import ModelFileError, ParameterError
from lungmech.fem.model import Model
from lungmech.mesh.geometry import Geometry
from lungmech.rom.ecsw import Sample

__all__ = ["cells_of", "export", "geometry", "material_functions", "place", "place_functions"]

PREFIX = "body/"


def export(model: Model, cells: np.ndarray, columns: Mapping[str, np.ndarray]) -> dict[str, np.ndarray] | None:
    """The owned ``cells`` (local indices) of ``model``'s mesh as arrays, on rank 0 (None on the
    others), in the order of their input indices: ``body/nodes`` (cells, nodes, gdim) at the
    mesh's current nodes, ``body/node_numbers`` their input numbers (``body/order`` their relative
    order in each cell, for a reader that keeps cells apart), the cell
    tags and each local facet's tag (``body/facet_tags``, where ``body/facet_tagged``), the
    cell-local values of every column of ``columns`` (name → owned rows of the model's space,
    ``body/<name>``: (cells, cell dofs, columns)) and of each :func:`material_functions` field
    (``body/function<i>``). Collective."""
    mesh = model.geometry.mesh
    if mesh.geometry.cmaps[0].degree != 1 or mesh.topology.cell_name() not in ("triangle", "tetrahedron"):
        raise ParameterError(
            "a hyper-reduced model's body is kept for meshes of straight-sided triangles or tetrahedra"
        )
    cells = np.unique(np.asarray(cells, dtype=np.int32))
    tdim = mesh.topology.dim
    geometry_dofs = mesh.geometry.dofmaps[0][cells]
    local: dict[str, np.ndarray] = {
        "cells": np.asarray(mesh.topology.original_cell_index, dtype=np.int64)[cells],
        "nodes": mesh.geometry.x[geometry_dofs][:, :, : mesh.geometry.dim],
        "node_numbers": np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)[geometry_dofs],
        # and their relative order alone: what a lungmech that kept cells apart reads
        "order": np.argsort(np.argsort(mesh.geometry.input_global_indices[geometry_dofs], axis=1), axis=1),
    }
    mesh.topology.create_connectivity(tdim, tdim - 1)
    facets = mesh.topology.connectivity(tdim, tdim - 1)
    per_cell = np.array([facets.links(c) for c in cells], dtype=np.int32).reshape(len(cells), tdim + 1)
    tags = model.geometry.facet_tags
    value = np.zeros(mesh.topology.index_map(tdim - 1).size_local + mesh.topology.index_map(tdim - 1).num_ghosts, int)
    tagged = np.zeros(len(value), bool)
    value[tags.indices], tagged[tags.indices] = tags.values, True
    local["facet_tags"], local["facet_tagged"] = value[per_cell], tagged[per_cell]
    if model.geometry.cell_tags is not None:
        count = mesh.topology.index_map(tdim).size_local + mesh.topology.index_map(tdim).num_ghosts
        marks, marked = np.zeros(count, np.int64), np.zeros(count, bool)
        marks[model.geometry.cell_tags.indices], marked[model.geometry.cell_tags.indices] = (
            model.geometry.cell_tags.values,
            True,
        )
        local["cell_tags"], local["cell_tagged"] = marks[cells], marked[cells]
    for name, vectors in columns.items():
        local[name] = _cell_values(model.space, cells, vectors)
    for i, function in enumerate(material_functions(model)):
        function.x.scatter_forward()
        local[f"function{i}"] = _cell_values(function.function_space, cells, function.x.array, ghosts=True)[:, :, 0]
    gathered = mesh.comm.gather(local, root=0)
    if mesh.comm.rank != 0:
        return None
    joined = {name: np.concatenate([part[name] for part in gathered]) for name in local}
    order = np.argsort(joined["cells"])
    return {PREFIX + name: array[order] for name, array in joined.items()}


def _cell_values(space: fem.FunctionSpace, cells: np.ndarray, vectors: np.ndarray, ghosts: bool = False) -> np.ndarray:
    """(cells, cell dofs unrolled, columns): the values of ``vectors`` (owned rows, or every
    local row with ``ghosts``) at each cell's dofs, in the dofmap's order."""
    vectors = np.asarray(vectors, dtype=float)
    vectors = vectors[:, None] if vectors.ndim == 1 else vectors
    if not ghosts:  # the ghost rows from their owners
        work = fem.Function(space)
        full = np.empty((len(work.x.array), vectors.shape[1]))
        for j in range(vectors.shape[1]):
            work.x.array[: len(vectors)] = vectors[:, j]
            work.x.scatter_forward()
            full[:, j] = work.x.array
        vectors = full
    return vectors[_unrolled(space, cells)]


def _unrolled(space: fem.FunctionSpace, cells: np.ndarray) -> np.ndarray:
    """(cells, cell dofs × block size): the local dofs of each cell, unrolled."""
    bs = space.dofmap.index_map_bs
    blocks = space.dofmap.list[cells]
    return (bs * blocks[:, :, None] + np.arange(bs)).reshape(len(cells), -1)


def material_functions(model: Model) -> list[fem.Function]:
    """The Functions the model's forms hold besides its state (material fields: a region's
    stiffness, an imaged porosity), in the order of their creation: what a body copies."""
    held = [model.residual, model.energy_density]
    held += [i.expr for term in model.state_dependent for i in term.integrals.values()]
    found = {c for h in held for c in extract_coefficients(h) if isinstance(c, fem.Function) and c is not model.state}
    return sorted(found, key=lambda function: function.count())


def geometry(
    arrays: Mapping[str, np.ndarray | None],
    comm: MPI.Comm,
    boundaries: Mapping[str, int],
    whole: Mapping[str, float],
    source: str,
) -> Geometry:
    """The body's cells as a :class:`~lungmech.mesh.geometry.Geometry` of their own (``arrays``
    on rank 0, None on the others; collective), its boundaries named by ``boundaries``, the
    measures of the whole body ``whole``. Each cell's input index is its position in the body."""
    on_root = comm.rank == 0
    count, per_cell, gdim = comm.bcast(_held(arrays, "nodes").shape if on_root else None)
    element = basix.ufl.element("Lagrange", {3: "triangle", 4: "tetrahedron"}[per_cell], 1, shape=(gdim,))
    connectivity, x = np.zeros((0, per_cell), np.int64), np.zeros((0, gdim))
    if on_root:
        connectivity = _input_nodes(arrays, count, per_cell)
        x = np.empty((int(connectivity.max()) + 1 if count else 0, gdim))
        x[connectivity.reshape(-1)] = _held(arrays, "nodes").reshape(-1, gdim)
    mesh = dmesh.create_mesh(comm, connectivity, element, x)  # type: ignore[arg-type]  # the hint omits UFL elements
    tdim = mesh.topology.dim
    cells = np.arange(mesh.topology.index_map(tdim).size_local, dtype=np.int32)
    mesh.topology.create_connectivity(tdim, tdim - 1)
    mesh.topology.create_connectivity(tdim - 1, tdim)  # (boundary conditions locate dofs by facet)
    facets = mesh.topology.connectivity(tdim, tdim - 1)
    local_facets = np.array([facets.links(c) for c in cells], dtype=np.int32).reshape(len(cells), tdim + 1)
    names = ["facet_tagged", "facet_tags"] + (
        ["cell_tagged", "cell_tags"] if comm.bcast(on_root and PREFIX + "cell_tags" in arrays) else []
    )
    rows = _rows(mesh, arrays, names)
    tagged = rows["facet_tagged"].astype(bool)
    indices, first = np.unique(local_facets[tagged], return_index=True)
    values = rows["facet_tags"][tagged][first].astype(np.int32)
    facet_tags = dmesh.meshtags(mesh, tdim - 1, indices.astype(np.int32), values)
    cell_tags = None
    if "cell_tags" in rows:
        marked = rows["cell_tagged"].astype(bool)
        cell_tags = dmesh.meshtags(mesh, tdim, cells[marked], rows["cell_tags"][marked].astype(np.int32))
    return Geometry(mesh, facet_tags, boundaries, cell_tags, source=source, whole=dict(whole))


def _input_nodes(arrays: Mapping[str, np.ndarray | None], count: int, per_cell: int) -> np.ndarray:
    """(cells, nodes): each cell's nodes as input numbers of the body, in the relative order of
    the full mesh's: the rank of a node's full input number among the body's (nodes shared as
    there), or, for a file that kept cells apart (``body/order``, their relative order alone),
    per_cell i + its rank among cell i's."""
    if PREFIX + "node_numbers" in arrays:
        _, numbers = np.unique(_held(arrays, "node_numbers"), return_inverse=True)
        return numbers.reshape(count, per_cell).astype(np.int64)
    return (per_cell * np.arange(count)[:, None] + _held(arrays, "order")).astype(np.int64)


def _rows(mesh: dmesh.Mesh, arrays: Mapping[str, np.ndarray | None], names: Sequence[str]) -> dict[str, np.ndarray]:
    """Rank 0's cell-wise arrays ``body/<name>`` (rows in body order), each rank given the rows
    of its owned cells (collective; one gather and one scatter for all ``names``)."""
    comm, tdim = mesh.comm, mesh.topology.dim
    mine = np.asarray(mesh.topology.original_cell_index, dtype=np.int64)[: mesh.topology.index_map(tdim).size_local]
    asked = comm.gather(mine, root=0)
    sent = [{n: _held(arrays, n)[rows] for n in names} for rows in asked] if comm.rank == 0 else None
    return comm.scatter(sent, root=0)


def _held(arrays: Mapping[str, np.ndarray | None], name: str) -> np.ndarray:
    """The array ``body/<name>`` on rank 0, which holds the file's arrays (the others hold None)."""
    array = arrays[PREFIX + name]
    assert array is not None, f"{PREFIX + name} is read on rank 0"
    return array


def place(space: fem.FunctionSpace, arrays: Mapping[str, np.ndarray | None], name: str) -> np.ndarray:
    """The columns ``body/<name>`` on ``space`` of the body's mesh, as local rows (owned, then
    ghost: a ghost dof of an owned cell gets its value from that cell; collective)."""
    values = _rows(space.mesh, arrays, [name])[name]
    dofs = _unrolled(space, np.arange(len(values), dtype=np.int32))
    local = space.dofmap.index_map.size_local + space.dofmap.index_map.num_ghosts
    result = np.zeros((local * space.dofmap.index_map_bs, values.shape[2]))
    result[dofs] = values
    return result


def place_functions(model: Model, arrays: Mapping[str, np.ndarray | None]) -> None:
    """Set the body model's :func:`material_functions` to the full model's values (collective).
    A body whose model holds other fields than the full one had is an error."""
    functions = material_functions(model)
    stored = model.geometry.mesh.comm.bcast(
        sorted(n for n in arrays if n.startswith(PREFIX + "function")) if model.geometry.mesh.comm.rank == 0 else None
    )
    if len(stored) != len(functions):
        raise ModelFileError(
            f"the body's model has {len(functions)} material fields, the full model had {len(stored)}: rebuild it"
        )
    rows = _rows(model.geometry.mesh, arrays, [f"function{i}" for i in range(len(functions))])
    for i, function in enumerate(functions):
        values = rows[f"function{i}"]
        function.x.array[_unrolled(function.function_space, np.arange(len(values), dtype=np.int32))] = values
        function.x.scatter_forward()


def cells_of(sample: Sample) -> np.ndarray:
    """Every owned cell ``sample`` (:class:`~lungmech.rom.ecsw.Sample`) samples, local indices."""
    return np.unique(np.concatenate([np.zeros(0, np.int32), *sample.cells.values()])).astype(np.int32)
