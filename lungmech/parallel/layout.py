"""A partition-independent order of a model's dofs, and the mesh fingerprint that goes with it.

DOLFINx numbers dofs differently on every partition, so a basis written from 4 ranks could not be
read on 1 without a common order. :func:`layout` gives every owned dof a canonical global index
in 0..N-1 that depends only on the mesh as it was read and on the element:

* A dof of a field's node is named by the cells that hold it: each such cell contributes the
  candidate (original input index of the cell, position of the node in the cell's dofmap), and the
  node's key is the smallest candidate. Both numbers are partition-independent: DOLFINx keeps the
  input index of every cell (``topology.original_cell_index``) and lays out a cell's dofs by the
  input order of its vertices (``tests/test_mpi.py`` checks this for P1, P2, P3, Taylor–Hood and
  the poromechanics P1-vector + DG0 space, on a box and on a gmsh mesh).
* Dofs are ordered by (field, component, key): all x components of the first field, then all y,
  ..., then the next field. A node of the mesh's own degree therefore sits at the same position
  within every component, as :mod:`lungmech.mesh.nodes` expects. The order is topological: it
  does not change when the nodes move.

Why it scales: nothing proportional to the mesh is gathered onto any rank. A rank sees every cell
that holds one of its owned nodes except across partition boundaries, so ghost nodes send their
candidates to their owners (one exchange with the neighbours through ``index_map.ghosts`` and
``owners``). The keys are then sorted by a bucket sort with fixed buckets: rank r receives the
keys of the cells with input index in the r-th of ``size`` equal ranges, sorts them, and a prefix
sum of the bucket sizes turns local positions into global ones, which go back to the senders.
Every rank holds O(N / ranks) data; only a few numbers per rank (counts) are exchanged by all.

The fingerprint is a sum mod 2^64 of one 64-bit hash per cell of (input index, canonical indices
of its dofs, quantised coordinates of its geometry nodes), summed over ranks (the sum does not
depend on which rank holds which cell), hashed with the element, the numbers of dofs and cells
and the size of the mesh into 16 hex digits. It changes when the nodes move, the connectivity
changes or the element changes. Coordinates are rounded on a grid of 1e-9 × the mesh diameter;
they are the geometry's own nodes, copied unchanged to every partition, so rounding gives the
same integers on any number of ranks.

:meth:`Layout.gather` and :meth:`Layout.scatter` move canonically ordered arrays to and from one
rank (the one that reads or writes a file): that rank alone holds the whole array.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from dataclasses import dataclass

from mpi4py import MPI

import numpy as np
import numpy.typing as npt
from dolfinx import fem, la
from dolfinx import mesh as dmesh

from lungmech.parallel.owned import owned_size

__all__ = ["Layout", "field_dofs", "layout"]

_RESOLUTION = 1e-9  # coordinates are compared on a grid of 1e-9 × the mesh diameter
_INDEX, _VALUES = 71, 72  # message tags of gather and scatter
_BLOCK = 1 << 16  # cells hashed at a time


@dataclass(frozen=True)
class Layout:
    """Canonical position of every owned dof of a state vector, and the mesh fingerprint.

    Attributes:
        index: Canonical global index of each owned local dof (owned,).
        size: Global number of dofs.
        fingerprint: 16 hex digits; the same on any number of ranks.
        comm: The mesh's communicator.
    """

    index: np.ndarray
    size: int
    fingerprint: str
    comm: MPI.Comm

    def gather(self, local: npt.ArrayLike, root: int = 0) -> np.ndarray | None:
        """Collective: the owned rows of every rank, (owned, ...) each, as one (size, ...) float
        array in canonical order on rank ``root``; None on the other ranks.

        Only ``root`` holds the whole array (it writes it); the others send their rows. Every
        rank passes rows of the same shape.
        """
        local = np.ascontiguousarray(local, dtype=np.float64)
        if self.comm.rank != root:
            self.comm.Send(self.index, dest=root, tag=_INDEX)
            self.comm.Send(local, dest=root, tag=_VALUES)
            return None
        result = np.empty((self.size, *local.shape[1:]))
        result[self.index] = local
        for rank in range(self.comm.size):
            if rank != root:
                index = self._receive_index(rank)
                values = np.empty((len(index), *local.shape[1:]))
                self.comm.Recv(values, source=rank, tag=_VALUES)
                result[index] = values
        return result

    def scatter(self, canonical: npt.ArrayLike | None, root: int = 0) -> np.ndarray:
        """Collective: this rank's owned rows (owned, ...) of the (size, ...) array in canonical
        order given on rank ``root`` (the other ranks pass None: what they pass is not read)."""
        canonical = None if canonical is None or self.comm.rank != root else np.asarray(canonical, dtype=np.float64)
        shape = self.comm.bcast(canonical.shape if canonical is not None else None, root=root)
        if not shape or shape[0] != self.size:
            raise ValueError(f"scatter: a canonical array has {self.size} rows, got shape {shape}")
        if self.comm.rank != root:
            self.comm.Send(self.index, dest=root, tag=_INDEX)
            rows = np.empty((len(self.index), *shape[1:]))
            self.comm.Recv(rows, source=root, tag=_VALUES)
            return rows
        assert canonical is not None  # given on the root, the one rank here
        for rank in range(self.comm.size):
            if rank != root:
                index = self._receive_index(rank)
                self.comm.Send(np.ascontiguousarray(canonical[index]), dest=rank, tag=_VALUES)
        return canonical[self.index]

    def _receive_index(self, source: int) -> npt.NDArray[np.int64]:
        """The canonical indices of the owned dofs of rank ``source``, sent to this rank."""
        status = MPI.Status()
        self.comm.Probe(source=source, tag=_INDEX, status=status)
        index = np.empty(status.Get_count(MPI.INT64_T), dtype=np.int64)
        self.comm.Recv(index, source=source, tag=_INDEX)
        return index


def layout(space: fem.FunctionSpace) -> Layout:
    """Collective: the canonical layout of ``space`` (a displacement, nodal or mixed space).

    See the module's description for the order and the fingerprint.
    """
    mesh = space.mesh
    comm = mesh.comm
    cells = _input_cells(mesh)
    cell_count = comm.allreduce(int(cells.max(initial=-1)) + 1, op=MPI.MAX)
    owned = owned_size(space)
    index = np.full(owned, -1, dtype=np.int64)
    start = 0
    for collapsed, parent in field_dofs(space):
        bs = collapsed.dofmap.index_map_bs
        per_cell = collapsed.dofmap.list.shape[1]
        keys = _node_keys(collapsed, cells, comm)
        home = keys // per_cell * comm.size // max(cell_count, 1)  # bucket: range of cell indices
        position, nodes = _positions(comm, keys, home)
        for component in range(bs):
            index[parent[np.arange(len(keys)) * bs + component]] = start + component * nodes + position
        start += bs * nodes
    assert (index >= 0).all(), "every owned dof belongs to exactly one field"
    return Layout(index, start, _fingerprint(space, index, cells, start), comm)


def field_dofs(space: fem.FunctionSpace) -> list[tuple[fem.FunctionSpace, np.ndarray]]:
    """(collapsed space, its dofs in ``space``) per field: one for a plain (vector) space."""
    mixed = space.dofmap.index_map_bs == 1 and space.ufl_element().num_sub_elements > 1
    if not mixed:
        return [(space, np.arange(owned_size(space)))]
    fields = [space.sub(i).collapse() for i in range(space.ufl_element().num_sub_elements)]
    return [(collapsed, np.asarray(parent).ravel()) for collapsed, parent in fields]


def _input_cells(mesh: dmesh.Mesh) -> npt.NDArray[np.int64]:
    """The input index of every local cell, owned and ghost (the same on any partition)."""
    cells = np.asarray(mesh.topology.original_cell_index, dtype=np.int64)
    cell_map = mesh.topology.index_map(mesh.topology.dim)
    if len(cells) != cell_map.size_local + cell_map.num_ghosts:
        raise ValueError("layout: the mesh does not know the input index of its cells (original_cell_index)")
    return cells


def _node_keys(space: fem.FunctionSpace, cells: np.ndarray, comm: MPI.Comm) -> npt.NDArray[np.int64]:
    """Collective: the key of every owned node (block) of ``space``: the smallest
    input cell index × dofs per cell + position in that cell, over all cells holding the node."""
    nodes = space.dofmap.list
    per_cell = nodes.shape[1]
    index_map = space.dofmap.index_map
    keys = np.full(index_map.size_local + index_map.num_ghosts, np.iinfo(np.int64).max)
    for position in range(per_cell):  # one position at a time: a cells × dofs table would dominate
        np.minimum.at(keys, nodes[:, position], cells * per_cell + position)
    # Cells on other ranks may hold an owned node too: each ghost sends its candidate to the owner.
    owned = index_map.size_local
    order = np.argsort(index_map.owners, kind="stable")
    rows = np.column_stack([index_map.ghosts, keys[owned:]])[order]
    received, _ = _alltoallv(comm, rows, np.bincount(index_map.owners, minlength=comm.size))
    keys = keys[:owned]
    np.minimum.at(keys, received[:, 0] - index_map.local_range[0], received[:, 1])
    return keys


def _positions(comm: MPI.Comm, keys: np.ndarray, home: np.ndarray) -> tuple[npt.NDArray[np.int64], int]:
    """Collective: the position of each of this rank's ``keys`` among the keys of all ranks (all
    distinct), and their number. A bucket sort: rank r sorts the keys whose ``home`` is r; homes
    must not decrease as keys increase, so a prefix sum of the bucket sizes places the buckets."""
    order = np.argsort(home, kind="stable")
    received, senders = _alltoallv(comm, keys[order, None], np.bincount(home, minlength=comm.size))
    here = len(received)
    position = np.empty(here, dtype=np.int64)
    position[np.argsort(received[:, 0])] = (comm.exscan(here) or 0) + np.arange(here)  # type: ignore[attr-defined]  # mpi4py's lower-case exscan, missing from its stubs
    answers, _ = _alltoallv(comm, position[:, None], senders)  # back to the senders, in their order
    result = np.empty(len(keys), dtype=np.int64)
    result[order] = answers[:, 0]
    return result, comm.allreduce(here)


def _alltoallv(comm: MPI.Comm, rows: np.ndarray, counts: np.ndarray) -> tuple[npt.NDArray[np.int64], np.ndarray]:
    """Collective: send ``counts[r]`` consecutive int64 rows of ``rows`` (n, w) to rank r; the
    rows received (from rank 0 first) and how many came from each rank."""
    width = rows.shape[1]
    counts = np.asarray(counts, dtype=np.int64)
    incoming = np.empty_like(counts)
    comm.Alltoall(counts, incoming)  # one number per rank pair
    received = np.empty((int(incoming.sum()), width), dtype=np.int64)

    def spec(buffer: np.ndarray, sizes: np.ndarray) -> list:
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        return [buffer, sizes * width, offsets * width, MPI.INT64_T]

    comm.Alltoallv(spec(np.ascontiguousarray(rows, dtype=np.int64), counts), spec(received, incoming))
    return received, incoming


def _fingerprint(space: fem.FunctionSpace, index: np.ndarray, cells: np.ndarray, size: int) -> str:
    """Collective: 16 hex digits from the element, the sizes and a sum of per-cell hashes of
    (input index, canonical dofs in cell order, quantised geometry nodes in cell order)."""
    mesh = space.mesh
    comm = mesh.comm
    owned_cells = mesh.topology.index_map(mesh.topology.dim).size_local
    bs = space.dofmap.index_map_bs
    canonical = la.vector(space.dofmap.index_map, bs, dtype=np.int64)  # canonical index of ghosts too
    canonical.array[: len(index)] = index
    canonical.scatter_forward()
    nodes = mesh.geometry.dofmaps[0]  # a copy, made once
    diameter = _diameter(mesh)
    grid = _RESOLUTION * diameter

    def columns(block: slice) -> Iterator[np.ndarray]:
        """The hashed numbers of a block of owned cells, one column at a time."""
        yield cells[block]
        dofs = space.dofmap.list[block]
        for position in range(dofs.shape[1]):
            for component in range(bs):
                yield canonical.array[dofs[:, position] * bs + component]
        for node in range(nodes.shape[1]):
            for axis in range(3):
                yield np.round(mesh.geometry.x[nodes[block, node], axis] / grid)

    local = 0
    for first in range(0, owned_cells, _BLOCK):  # blocks of cells keep the temporaries small
        block = slice(first, min(first + _BLOCK, owned_cells))
        digest = np.full(block.stop - block.start, 0x9E3779B97F4A7C15, dtype=np.uint64)
        for column in columns(block):
            digest ^= _mix(column.astype(np.int64).astype(np.uint64))  # two's complement bits, copied
            digest = _mix(digest)
        local += int(digest.sum(dtype=np.uint64))  # wraps mod 2^64, as the total does below
    total = comm.allreduce(local) % 2**64  # Python ints: exact, then wrapped
    summary = f"{space.ufl_element()}|{size}|{comm.allreduce(owned_cells)}|{diameter:.9e}|{total:016x}"
    return hashlib.sha256(summary.encode()).hexdigest()[:16]


def _mix(h: npt.NDArray[np.uint64]) -> npt.NDArray[np.uint64]:
    """The splitmix64 finaliser, elementwise and in place (a bijection of 64-bit words that
    spreads every bit); returns ``h``."""
    h ^= h >> np.uint64(30)
    h *= np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(27)
    h *= np.uint64(0x94D049BB133111EB)
    h ^= h >> np.uint64(31)
    return h


def _diameter(mesh: dmesh.Mesh) -> float:
    """Collective: the diagonal of the mesh's bounding box."""
    x = mesh.geometry.x
    local = np.concatenate([x.min(axis=0), -x.max(axis=0)]) if len(x) else np.full(6, np.inf)
    bounds = np.empty_like(local)
    mesh.comm.Allreduce(np.ascontiguousarray(local, dtype=np.float64), bounds, op=MPI.MIN)
    return float(np.linalg.norm(-bounds[3:] - bounds[:3]))
