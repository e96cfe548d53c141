"""Meshes DOLFINx makes itself, structured: an axis-aligned box, and in 2-D a rectangle, Cook's
membrane and a quarter annulus (a structured square mapped onto them). Each has named
boundaries. Re-exported by :mod:`lungmech.mesh.builders`, where every builder is found.

Collective: under MPI, call a builder on all ranks.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping

from mpi4py import MPI

import dolfinx
import dolfinx.mesh
import numpy as np
import numpy.typing as npt

from lungmech.errors import GeometryError
from lungmech.mesh.geometry import Geometry
from lungmech.mesh.nodes import place

__all__ = ["box", "cook_membrane", "quarter_annulus", "rectangle"]


# --- Built-in box -------------------------------------------------------------------------


def box(
    comm: MPI.Comm,
    lengths: tuple[float, float, float] = (1.0, 1.0, 1.0),
    cells: tuple[int, int, int] = (4, 4, 4),
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    cell_type: str = "tetrahedron",
) -> Geometry:
    """Axis-aligned box with faces ``x0, x1, y0, y1, z0, z1`` (tags 1..6).

    ``x0`` is the face at ``x = origin[0]``, ``x1`` the one at ``x = origin[0] + lengths[0]``.
    ``cell_type`` is ``"tetrahedron"`` or ``"hexahedron"``.
    """
    lower = np.asarray(origin, dtype=np.float64)
    upper = lower + np.asarray(lengths, dtype=np.float64)
    if lower.shape != (3,) or upper.shape != (3,) or not np.all(upper > lower):
        raise GeometryError(f"box needs three positive lengths and a 3D origin, got {lengths=}, {origin=}")
    if len(cells) != 3 or any(int(n) != n or n < 1 for n in cells):
        raise GeometryError(f"box needs three positive integer cell counts, got cells={cells}")
    if cell_type not in ("tetrahedron", "hexahedron"):
        raise GeometryError(f"unknown cell_type {cell_type!r}; use 'tetrahedron' or 'hexahedron'")

    cell = dolfinx.mesh.CellType[cell_type]
    mesh = dolfinx.mesh.create_box(comm, [lower, upper], [int(n) for n in cells], cell)
    fdim = mesh.topology.dim - 1
    tol = 1e-10 * float(np.max(upper - lower))
    boundaries: dict[str, int] = {}
    found: list[tuple[npt.NDArray[np.int32], int]] = []
    for axis, letter in enumerate("xyz"):
        for side, plane in enumerate((lower[axis], upper[axis])):
            tag = 2 * axis + side + 1
            boundaries[f"{letter}{side}"] = tag
            facets = dolfinx.mesh.locate_entities_boundary(
                mesh, fdim, lambda x, a=axis, p=plane: np.abs(x[a] - p) < tol
            )
            found.append((facets, tag))
    return Geometry(mesh, _facet_tags(mesh, found), boundaries)


def _facet_tags(mesh: dolfinx.mesh.Mesh, found: list[tuple[npt.NDArray[np.int32], int]]) -> dolfinx.mesh.MeshTags:
    """Facet MeshTags from (facets, tag) pairs; MeshTags wants sorted, unique indices."""
    indices = np.concatenate([facets for facets, _ in found]).astype(np.int32)
    values = np.concatenate([np.full(len(facets), tag, dtype=np.int32) for facets, tag in found])
    order = np.argsort(indices)
    tags = dolfinx.mesh.meshtags(mesh, mesh.topology.dim - 1, indices[order], values[order])
    tags.name = "facet_tags"
    return tags


# --- 2-D shapes: a structured square mapped onto the shape -----------------------------------


def rectangle(
    comm: MPI.Comm,
    lengths: tuple[float, float] = (1.0, 1.0),
    cells: tuple[int, int] = (4, 4),
    origin: tuple[float, float] = (0.0, 0.0),
    cell_type: str = "triangle",
) -> Geometry:
    """Axis-aligned rectangle (2-D) with edges ``x0, x1, y0, y1`` (tags 1..4)."""
    lower = np.asarray(origin, dtype=np.float64)
    size = np.asarray(lengths, dtype=np.float64)
    if lower.shape != (2,) or size.shape != (2,) or not np.all(size > 0):
        raise GeometryError(f"rectangle needs two positive lengths and a 2-D origin, got {lengths=}, {origin=}")
    return _mapped_square(comm, cells, cell_type, lambda xi: lower + xi * size, {}, "rectangle")


def cook_membrane(comm: MPI.Comm, cells: tuple[int, int] = (16, 16), cell_type: str = "triangle") -> Geometry:
    """Cook's membrane: the trapezoid (0, 0), (48, 44), (48, 60), (0, 44) (m), with edges
    ``clamped`` (x = 0), ``loaded`` (x = 48), ``bottom`` and ``top``; ``cells`` along x and
    across. The benchmark clamps x = 0 and shears x = 48 (see VERIFICATION.md)."""

    def trapezoid(xi: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        s, t = xi[:, 0], xi[:, 1]
        return np.column_stack([48.0 * s, 44.0 * s + t * (44.0 - 28.0 * s)])

    names = {"clamped": "x0", "loaded": "x1", "bottom": "y0", "top": "y1"}
    return _mapped_square(comm, cells, cell_type, trapezoid, names, "cook_membrane")


def quarter_annulus(
    comm: MPI.Comm,
    inner: float = 1.0,
    outer: float = 2.0,
    cells: tuple[int, int] = (8, 16),
    cell_type: str = "triangle",
) -> Geometry:
    """The quarter annulus inner ≤ r ≤ outer (m), x, y ≥ 0, with edges ``inner``, ``outer``,
    ``x0`` (on the y axis) and ``y0`` (on the x axis); ``cells`` across the wall and around.
    The arcs are polygons through the nodes."""
    if not 0 < inner < outer:
        raise GeometryError(f"quarter_annulus needs 0 < inner < outer, got {inner=}, {outer=}")

    def annulus(xi: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        radius, angle = inner + (outer - inner) * xi[:, 0], 0.5 * math.pi * xi[:, 1]
        return np.column_stack([radius * np.cos(angle), radius * np.sin(angle)])

    names = {"inner": "x0", "outer": "x1", "y0": "y0", "x0": "y1"}
    return _mapped_square(comm, cells, cell_type, annulus, names, "quarter_annulus")


def _mapped_square(
    comm: MPI.Comm,
    cells: tuple[int, int],
    cell_type: str,
    mapping: Callable[[npt.NDArray[np.float64]], npt.NDArray[np.float64]],
    names: Mapping[str, str],
    builder: str,
) -> Geometry:
    """The unit square, ``cells`` structured, its nodes moved by ``mapping`` (n, 2) → (n, 2); its
    edges ξ = 0, 1 and η = 0, 1 named by ``names`` (new name → x0, x1, y0, y1; default the same)."""
    if len(cells) != 2 or any(int(n) != n or n < 1 for n in cells):
        raise GeometryError(f"{builder} needs two positive integer cell counts, got cells={cells}")
    if cell_type not in ("triangle", "quadrilateral"):
        raise GeometryError(f"unknown cell_type {cell_type!r}; use 'triangle' or 'quadrilateral'")
    nx, ny = (int(n) for n in cells)
    mesh = dolfinx.mesh.create_unit_square(comm, nx, ny, dolfinx.mesh.CellType[cell_type])
    found, edges = [], {}
    for axis, letter in enumerate("xy"):
        for side in (0, 1):
            tag = 2 * axis + side + 1
            edges[f"{letter}{side}"] = tag
            facets = dolfinx.mesh.locate_entities_boundary(
                mesh, 1, lambda x, a=axis, p=float(side): np.abs(x[a] - p) < 1e-12
            )
            found.append((facets, tag))
    tags = _facet_tags(mesh, found)  # found on the square, kept by the mapping
    place(mesh, mapping(mesh.geometry.x[:, :2].copy()))
    boundaries = {new: edges[old] for new, old in names.items()} if names else edges
    return Geometry(mesh, tags, boundaries)
