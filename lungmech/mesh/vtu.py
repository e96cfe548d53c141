"""Mesh files every tool opens: VTK's XML unstructured grid (``.vtu``), with the tags inside.

The format. One ``.vtu`` file holds the body's cells and, after them, its tagged facets
(triangles or quadrilaterals of a 3-D body, lines of a plane one) as cells of one dimension
less. The cell data ``tags`` is, on a body cell, its cell tag (0: none) and, on a facet, its
facet tag. The field data names the boundaries as meshio names gmsh's physical groups,
``name -> [tag, dimension]``, and ``lungmech_sha256`` holds a digest of the file's arrays, by
which lungmech knows a file it wrote and may replace. A plane body is written in the plane
z = 0. meshio, pyvista and ParaView read it: in ParaView, *Extract Cells By Type* or
*Threshold* on ``tags`` separates the boundary from the body.

Why ``.vtu``. DOLFINx's XDMF keeps the mesh and its tags as separate grids, which meshio and
VTK's XDMF reader cannot open; VTKHDF is read by VTK and ParaView but not by meshio. A ``.vtu``
is read by all of them, needs no companion file, and is a format of VTK's own.

The order. Nodes are written in the order of the mesh's input (``input_global_indices``),
body cells in their input order (``original_cell_index``), facets sorted by their nodes and each
facet's nodes in one canonical order: the file does not depend on the partition, and a
mesh read from it keeps the file's order as its input order, so writing it again gives the
same arrays.

Limits. Collective; rank 0 gathers the whole mesh and writes the file, and reads it (the mesh
is then distributed by DOLFINx's partitioner): one rank must hold the mesh, 8 bytes per node
index and per coordinate, twice over while VTK copies them. Straight-sided cells, and quadratic
tetrahedra and triangles. For a mesh too large for one rank, ``.xdmf`` (DOLFINx's parallel HDF5)
remains, read by lungmech and ParaView.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from mpi4py import MPI

import basix.ufl
import dolfinx.graph
import dolfinx.io
import dolfinx.io.utils
import dolfinx.mesh
import numpy as np
import numpy.typing as npt
import ufl

from lungmech.errors import GeometryError
from lungmech.mesh.geometry import Geometry
from lungmech.parallel import on_root

__all__ = ["DIGEST", "read", "write", "written_by_lungmech"]

DIGEST = "lungmech_sha256"  # the field data holding the digest; not a boundary name
TAGS = "tags"  # the cell data holding cell and facet tags

# The cells a file can hold, by meshio's name: DOLFINx's shape, geometry degree, VTK's type number
# and node count; and the facets of each kind of body cell.
_KINDS = {
    "line": ("interval", 1, 3, 2),
    "line3": ("interval", 2, 21, 3),
    "triangle": ("triangle", 1, 5, 3),
    "triangle6": ("triangle", 2, 22, 6),
    "quad": ("quadrilateral", 1, 9, 4),
    "tetra": ("tetrahedron", 1, 10, 4),
    "tetra10": ("tetrahedron", 2, 24, 10),
    "hexahedron": ("hexahedron", 1, 12, 8),
}
_FACET = {"triangle": "line", "triangle6": "line3", "quad": "line", "tetra": "triangle"}
_FACET |= {"tetra10": "triangle6", "hexahedron": "quad"}
_DIMENSION = {"interval": 1, "triangle": 2, "quadrilateral": 2, "tetrahedron": 3, "hexahedron": 3}


def _kind(shape: str, nodes: int) -> str:
    """meshio's name of a cell of DOLFINx's ``shape`` with ``nodes`` geometry nodes."""
    for name, (kind_shape, _, _, kind_nodes) in _KINDS.items():
        if (kind_shape, kind_nodes) == (shape, nodes):
            return name
    raise GeometryError(
        f"cannot write the mesh as .vtu: {shape} cells with {nodes} nodes (.vtu holds straight-sided cells and "
        "quadratic simplices); write it as .xdmf"
    )


def _dimension(kind: str) -> int:
    return _DIMENSION[_KINDS[kind][0]]


def _to_dolfinx(kind: str) -> npt.NDArray[np.intp]:
    """Node permutation: ``dolfinx_nodes = vtk_nodes[perm]``."""
    shape, _, _, nodes = _KINDS[kind]
    return np.asarray(dolfinx.io.utils.cell_perm_vtk(dolfinx.mesh.CellType[shape], nodes))


@dataclass(frozen=True)
class _Grid:
    """A mesh file's arrays in the file's order, on one rank (empty on the others).

    ``cells`` and ``facets`` index ``points`` with their nodes in VTK's order.
    """

    kind: str  # meshio's name of the body's cells
    gdim: int  # 3, or 2 for a plane body (z = 0)
    boundaries: Mapping[str, int]
    points: npt.NDArray[np.float64]  # (nodes, 3)
    cells: npt.NDArray[np.int64]
    cell_tags: npt.NDArray[np.int32]  # 0: no tag
    facets: npt.NDArray[np.int64]
    facet_tags: npt.NDArray[np.int32]

    @classmethod
    def empty(cls, kind: str, gdim: int, boundaries: Mapping[str, int]) -> _Grid:
        """What a rank other than the reader holds: the header, no rows."""
        none = np.zeros(0, dtype=np.int32)
        cells, facets = (np.zeros((0, _KINDS[k][3]), dtype=np.int64) for k in (kind, _FACET[kind]))
        return cls(kind, gdim, boundaries, np.zeros((0, 3)), cells, none, facets, none)

    @property
    def header(self) -> tuple[str, int, dict[str, int]]:
        return self.kind, self.gdim, dict(self.boundaries)

    def digest(self) -> bytes:
        """SHA-256 of every array and name, in a fixed form (the same after a read)."""
        sha = hashlib.sha256()
        for array in (self.points, self.cells, self.facets, self.cell_tags, self.facet_tags):
            sha.update(np.ascontiguousarray(array, dtype=np.float64 if array is self.points else np.int64).tobytes())
        sha.update(json.dumps([self.kind, self.gdim, sorted(self.boundaries.items())]).encode())
        return sha.digest()


def write(geometry: Geometry, path: Path) -> None:
    """Collective: write ``geometry`` to the ``.vtu`` file ``path`` (see the module's docstring)."""
    grid = _gathered(geometry)
    on_root(geometry.mesh.comm, lambda: _save(grid, path))


def read(path: Path, comm: MPI.Comm) -> Geometry:
    """Collective: the geometry in the ``.vtu`` file ``path``, distributed over ``comm``.

    Boundary names come from the field data (``name -> [tag, dimension]``); the caller
    (:func:`lungmech.mesh.files.from_file`) names the facet tags that have none.
    """
    loaded: _Grid | str | None = None
    if comm.rank == 0:
        try:
            loaded, _ = _load(path)
        except GeometryError as e:
            loaded = str(e)
    header = comm.bcast(loaded if isinstance(loaded, str) else loaded.header if loaded else None, root=0)
    if isinstance(header, str):
        raise GeometryError(header)
    grid = loaded if isinstance(loaded, _Grid) else _Grid.empty(*header)
    kind, gdim, boundaries = header
    shape, degree, _, _ = _KINDS[kind]
    element = ufl.Mesh(basix.ufl.element("Lagrange", shape, degree, shape=(gdim,)))
    cells = grid.cells[:, _to_dolfinx(kind)]
    mesh = dolfinx.mesh.create_mesh(comm, cells, element, np.ascontiguousarray(grid.points[:, :gdim]))
    tdim = mesh.topology.dim
    facet_tags = _meshtags(mesh, tdim - 1, grid.facets[:, _to_dolfinx(_FACET[kind])], grid.facet_tags)
    tagged = grid.cell_tags != 0
    has_cell_tags = comm.allreduce(bool(tagged.any()), op=MPI.LOR)
    cell_tags = _meshtags(mesh, tdim, cells[tagged], grid.cell_tags[tagged]) if has_cell_tags else None
    return Geometry(mesh, facet_tags, boundaries, cell_tags)


def written_by_lungmech(path: str | Path) -> bool:
    """Whether the ``.vtu`` file ``path`` was written by :func:`write` and is unchanged since."""
    try:
        grid, stored = _load(Path(path))
    except Exception:  # any reader's failure: not a file lungmech can vouch for
        return False
    return stored == grid.digest()


def _meshtags(
    mesh: dolfinx.mesh.Mesh, dim: int, entities: npt.NDArray[np.int64], values: npt.NDArray[np.int32]
) -> dolfinx.mesh.MeshTags:
    """Collective: tags of entities given by their geometry nodes' input indices (DOLFINx's node
    order), on any rank."""
    local, local_values = dolfinx.io.distribute_entity_data(mesh, dim, entities.astype(np.int64), values)
    mesh.topology.create_connectivity(dim, mesh.topology.dim)
    adjacency = dolfinx.graph.adjacencylist(local)
    return dolfinx.mesh.meshtags_from_entities(mesh, dim, adjacency, local_values.astype(np.int32, copy=False))


def _gathered(geometry: Geometry) -> _Grid | None:
    """Collective: the geometry's arrays in the file's order, on rank 0 (None elsewhere)."""
    mesh, comm = geometry.mesh, geometry.mesh.comm
    tdim = mesh.topology.dim
    kind = _kind(mesh.topology.cell_name(), mesh.geometry.dofmaps[0].shape[1])
    facet_kind = _FACET[kind]
    given = [geometry.facet_tags.values] + ([geometry.cell_tags.values] if geometry.cell_tags is not None else [])
    lowest = comm.allreduce(min((int(v.min()) for v in given if v.size), default=1), op=MPI.MIN)
    if lowest < 1:
        raise GeometryError(f"cannot write the mesh as .vtu: tag {lowest} is not a positive integer (0 marks no tag)")

    inputs = mesh.geometry.input_global_indices.astype(np.int64)
    owned_nodes = mesh.geometry.index_map().size_local
    owned_cells = mesh.topology.index_map(tdim).size_local
    cells = inputs[mesh.geometry.dofmaps[0][:owned_cells]][:, np.argsort(_to_dolfinx(kind))]
    cell_tags = np.zeros(owned_cells, dtype=np.int32)
    if geometry.cell_tags is not None:
        mine = geometry.cell_tags.indices < owned_cells
        cell_tags[geometry.cell_tags.indices[mine]] = geometry.cell_tags.values[mine]
    mesh.topology.create_connectivity(tdim - 1, tdim)
    tags = geometry.facet_tags
    mine = tags.indices < mesh.topology.index_map(tdim - 1).size_local
    facet_nodes = dolfinx.mesh.entities_to_geometry(mesh, tdim - 1, tags.indices[mine])
    facets = inputs[facet_nodes.reshape(-1, _KINDS[facet_kind][3])][:, np.argsort(_to_dolfinx(facet_kind))]
    parts = comm.gather(
        (
            mesh.geometry.x[:owned_nodes],
            inputs[:owned_nodes],
            cells,
            mesh.topology.original_cell_index[:owned_cells].astype(np.int64),
            cell_tags,
            facets,
            tags.values[mine].astype(np.int32),
        ),
        root=0,
    )
    if parts is None:
        return None
    x, node_inputs, cells, cell_inputs, cell_tags, facets, facet_tags = (np.concatenate(p) for p in zip(*parts))
    nodes = np.argsort(node_inputs)
    numbered = node_inputs[nodes]
    by_input = np.argsort(cell_inputs)
    facets = _canonical(np.searchsorted(numbered, facets), facet_kind)
    by_nodes = np.lexsort(facets.T[::-1])
    return _Grid(
        kind,
        mesh.geometry.dim,
        dict(geometry.boundaries),
        np.asarray(x[nodes], dtype=np.float64),
        np.searchsorted(numbered, cells[by_input]).astype(np.int64),
        cell_tags[by_input],
        facets[by_nodes].astype(np.int64),
        facet_tags[by_nodes],
    )


# The midpoint node of a quadratic triangle's edge between vertices a and b (VTK's order).
_MIDPOINT = np.array([[-1, 3, 5], [3, -1, 4], [5, 4, -1]])


def _canonical(facets: npt.NDArray[np.int64], kind: str) -> npt.NDArray[np.int64]:
    """Each facet's nodes (VTK's order) in one order that does not depend on the cell it came from.

    A line or triangle: its vertices sorted, then the midpoints of its edges in VTK's order for
    those vertices. A quadrilateral keeps its cyclic order, starting at its lowest node and going
    on towards the lower of that node's two neighbours.
    """
    rows = np.arange(len(facets))[:, None]
    if kind == "quad":
        start = np.argmin(facets, axis=1)
        turned = facets[rows, (start[:, None] + np.arange(4)) % 4]
        backwards = turned[:, 3] < turned[:, 1]
        turned[backwards] = turned[backwards][:, [0, 3, 2, 1]]
        return turned
    vertices = 2 if kind.startswith("line") else 3
    order = np.argsort(facets[:, :vertices], axis=1)
    if kind == "line3":
        midpoints = np.full((len(facets), 1), 2)
    elif kind == "triangle6":
        edges = [(0, 1), (1, 2), (2, 0)]
        midpoints = np.column_stack([_MIDPOINT[order[:, a], order[:, b]] for a, b in edges])
    else:
        midpoints = np.zeros((len(facets), 0), dtype=int)
    return facets[rows, np.column_stack([order, midpoints])]


def _save(grid: _Grid | None, path: Path) -> None:
    """Write the gathered arrays with VTK (through pyvista), on the rank that holds them."""
    import pyvista

    assert grid is not None  # on_root runs this on rank 0, where _gathered returned the grid
    blocks = [(grid.cells, grid.kind), (grid.facets, _FACET[grid.kind])]
    connectivity = np.concatenate(
        [np.column_stack([np.full(len(rows), rows.shape[1]), rows]).ravel() for rows, _ in blocks]
    )
    types = np.concatenate([np.full(len(rows), _KINDS[kind][2], dtype=np.uint8) for rows, kind in blocks])
    points = np.zeros((len(grid.points), 3))
    points[:, : grid.gdim] = grid.points[:, : grid.gdim]
    mesh = pyvista.UnstructuredGrid(connectivity, types, points)
    mesh.cell_data[TAGS] = np.concatenate([grid.cell_tags, grid.facet_tags]).astype(np.int32)
    for name, tag in sorted(grid.boundaries.items()):
        mesh.field_data[name] = np.array([tag, _dimension(_FACET[grid.kind])], dtype=np.int64)
    mesh.field_data[DIGEST] = np.frombuffer(grid.digest(), dtype=np.uint8)
    mesh.save(str(path))


def _load(path: Path) -> tuple[_Grid, bytes | None]:
    """The arrays of a ``.vtu`` file (read with meshio) and the digest it stores, if any."""
    import meshio.vtu

    def refuse(why: str) -> GeometryError:
        return GeometryError(f"mesh file '{path}' {why}")

    try:
        data = meshio.vtu.read(str(path))  # meshio.read would print and exit the interpreter on a bad file
    except Exception as e:  # meshio's readers raise many kinds; the message says what is wrong
        raise GeometryError(f"cannot read mesh file '{path}': {e}") from None
    kinds = [b.type for b in data.cells]
    unknown = sorted(set(kinds) - set(_KINDS) - {"vertex"})
    if unknown:
        raise refuse(
            f"has cells of type {', '.join(unknown)}; lungmech reads tetrahedra, hexahedra, triangles and "
            "quadrilaterals (tetrahedra and triangles also quadratic), with their facets"
        )
    tdim = max((_dimension(k) for k in kinds if k in _KINDS), default=0)
    body = sorted({k for k in kinds if k in _KINDS and _dimension(k) == tdim})
    if tdim < 2 or len(body) != 1:
        found = ", ".join(body) if body else "no 2-D or 3-D cells"
        raise refuse(f"must hold one kind of 2-D or 3-D cell (found {found})")
    kind = body[0]
    if TAGS not in data.cell_data:
        raise refuse(f"has no cell data '{TAGS}' (the cell and facet tags lungmech reads)")
    tags = data.cell_data[TAGS]
    if not all(np.issubdtype(np.asarray(t).dtype, np.integer) for t in tags):
        raise refuse(f"has cell data '{TAGS}' that is not integer")

    def rows(wanted: str) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int32]]:
        picked = [i for i, k in enumerate(kinds) if k == wanted]
        nodes = [np.asarray(data.cells[i].data, dtype=np.int64) for i in picked]
        values = [np.asarray(tags[i], dtype=np.int32).ravel() for i in picked]
        empty = (np.zeros((0, _KINDS[wanted][3]), dtype=np.int64), np.zeros(0, dtype=np.int32))
        return (np.concatenate(nodes), np.concatenate(values)) if picked else empty

    cells, cell_tags = rows(kind)
    facets, facet_tags = rows(_FACET[kind])
    if not len(facets):
        raise refuse(f"has no tagged facets ({_FACET[kind]} cells with their '{TAGS}')")
    points = np.asarray(data.points, dtype=np.float64).reshape(len(data.points), -1)
    for block in (cells, facets):
        if block.size and (block.min() < 0 or block.max() >= len(points)):
            raise refuse(f"has cells that name nodes it does not hold (it holds {len(points)} nodes)")
    if tdim == 2 and points.shape[1] > 2:
        z = np.abs(points[:, 2:])
        if z.size and z.max() > 1e-12 * max(1.0, float(np.abs(points).max())):
            raise refuse(f"holds a plane mesh that does not lie in z = 0 (|z| up to {z.max():.3g})")
    padded = np.zeros((len(points), 3))
    padded[:, : min(3, points.shape[1])] = points[:, :3]
    fdim = tdim - 1
    boundaries = {
        str(name): int(value[0])
        for name, value in data.field_data.items()
        if name != DIGEST and np.shape(value) == (2,) and int(value[1]) == fdim
    }
    stored = data.field_data.get(DIGEST)
    digest = bytes(np.asarray(stored, dtype=np.uint8)) if stored is not None else None
    return _Grid(kind, tdim, boundaries, padded, cells, cell_tags, facets, facet_tags), digest
