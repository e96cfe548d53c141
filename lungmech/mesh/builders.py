"""Meshes made here: an axis-aligned box (DOLFINx); in 2-D a rectangle, Cook's membrane and a
quarter annulus (a structured square mapped onto them); and gmsh OpenCASCADE shapes (sphere,
ellipsoid, lung phantom). Each has named boundaries.

Collective: under MPI, call a builder on all ranks. Gmsh models are built on rank 0 only and the
mesh is then distributed; a failure there is raised on every rank.
"""

from __future__ import annotations

import contextlib
import math
import signal
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

from mpi4py import MPI

import dolfinx
import dolfinx.io
import dolfinx.mesh
import numpy as np
import numpy.typing as npt

from lungmech.errors import GeometryError
from lungmech.mesh.geometry import Geometry, from_meshdata
from lungmech.mesh.lung_shape import LungShape
from lungmech.mesh.nodes import place

__all__ = [
    "box",
    "cook_membrane",
    "ellipsoid",
    "gmsh_session",
    "lung_phantom",
    "quarter_annulus",
    "rectangle",
    "sphere",
]


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


# --- Gmsh-built shapes --------------------------------------------------------------------

# Single-threaded, seeded meshing, so the same call gives the same mesh on every machine.
_GMSH_OPTIONS = {
    "General.Terminal": 0,
    "General.NumThreads": 1,
    "Mesh.RandomSeed": 1,
    "Mesh.Algorithm": 6,  # Frontal-Delaunay surfaces
    "Mesh.Algorithm3D": 1,  # Delaunay volumes
    "Mesh.OptimizeNetgen": 1,  # removes the slivers that Delaunay leaves near sharp CAD edges
    "Mesh.MeshSizeMin": 0.0,
}

# A rule says whether a face, given as the coordinates of its mesh nodes, is that boundary.
_Rule = Callable[[npt.NDArray[np.float64]], bool]
# A surface test says which points lie on a primitive surface.
_Surface = Callable[[npt.NDArray[np.float64]], npt.NDArray[np.bool_]]


@contextlib.contextmanager
def _signal_handlers_kept() -> Iterator[None]:
    """Put the Python handlers of SIGINT and SIGTERM back after the block (main thread only)."""
    kept = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in kept.items():
            if handler is not None:
                with contextlib.suppress(ValueError):  # not the main thread: nothing was ours
                    signal.signal(s, handler)


@contextlib.contextmanager
def gmsh_session(options: Mapping[str, float]) -> Iterator[Any]:
    """A fresh gmsh model with quiet, reproducible options; leaves gmsh as it was found, and the
    process's SIGINT and SIGTERM handlers as they were (gmsh resets them to the default action —
    ``gmsh.finalize`` does, with gmsh 4.15 — which would end a run without a word and leave its
    staging folder; both ends are guarded)."""
    import gmsh

    started = not gmsh.isInitialized()
    if started:
        with _signal_handlers_kept():
            gmsh.initialize(interruptible=False)
    previous = None if started else gmsh.model.getCurrent()
    settings = {**_GMSH_OPTIONS, **options}
    saved = {key: gmsh.option.getNumber(key) for key in settings}
    for key, value in settings.items():
        gmsh.option.setNumber(key, value)
    gmsh.model.add("lungmech")
    try:
        yield gmsh
    finally:
        gmsh.model.remove()
        for key, value in saved.items():
            gmsh.option.setNumber(key, value)
        if started:
            with _signal_handlers_kept():
                gmsh.finalize()
        elif previous:
            gmsh.model.setCurrent(previous)


def _gmsh_geometry(
    comm: MPI.Comm,
    build: Callable[[Any], tuple[int, dict[str, _Rule], str]],
    mesh_size: float,
    order: int,
    msh_file: str | Path | None = None,
    options: Mapping[str, float] | None = None,
) -> Geometry:
    """Mesh the OCC volume made by ``build`` on rank 0, name its faces, distribute the mesh.

    ``build(occ)`` adds one volume and returns ``(volume_tag, rules, cell_name)``; boundary
    tags are numbered 1, 2, ... in the order of ``rules``.
    """
    root = 0
    if comm.rank != root:
        if failure := comm.bcast(None, root=root):
            raise GeometryError(failure)
        return from_meshdata(dolfinx.io.gmsh.model_to_mesh(None, comm, root, gdim=3))

    with gmsh_session({"Mesh.MeshSizeMax": mesh_size, **(options or {})}) as gmsh:
        try:
            volume, rules, cell_name = build(gmsh.model.occ)
            gmsh.model.occ.synchronize()
            gmsh.model.mesh.generate(3)
            faces = [face for _, face in gmsh.model.getBoundary([(3, volume)], oriented=False)]
            named = _name_faces(gmsh.model, faces, rules)
            for tag, (name, group) in enumerate(named.items(), start=1):
                gmsh.model.addPhysicalGroup(2, group, tag, name)
            gmsh.model.addPhysicalGroup(3, [volume], 1, cell_name)
            if order > 1:
                gmsh.model.mesh.setOrder(order)
            if msh_file is not None:
                gmsh.write(str(msh_file))
        except Exception as e:
            message = str(e) if isinstance(e, GeometryError) else f"gmsh could not build the mesh: {e}"
            # Tell the other ranks before raising, or they would wait forever in model_to_mesh.
            comm.bcast(message, root=root)
            raise GeometryError(message) from e
        comm.bcast(None, root=root)
        return from_meshdata(dolfinx.io.gmsh.model_to_mesh(gmsh.model, comm, root, gdim=3))


def _name_faces(model: Any, faces: list[int], rules: Mapping[str, _Rule]) -> dict[str, list[int]]:
    """Group faces by the one rule that their mesh nodes satisfy.

    Going by where the meshed faces actually are, not by the order OCC returns them, keeps the
    names right whatever the boolean operations did to the face numbering.
    """
    named: dict[str, list[int]] = {name: [] for name in rules}
    for face in faces:
        _, coords, _ = model.mesh.getNodes(2, face, includeBoundary=True)
        x = np.reshape(coords, (-1, 3))
        matches = [name for name, rule in rules.items() if rule(x)]
        if len(matches) != 1:
            found = " and ".join(matches) or "none"
            raise GeometryError(f"surface {face} looks like {found} of the boundaries {', '.join(rules)}")
        named[matches[0]].append(face)
    if empty := [name for name, group in named.items() if not group]:
        raise GeometryError(f"no surface found for boundary {', '.join(empty)}")
    return named


def _ellipsoid_surface(axes: npt.ArrayLike, centre: npt.ArrayLike = (0.0, 0.0, 0.0)) -> _Surface:
    axes, centre = np.asarray(axes, dtype=np.float64), np.asarray(centre, dtype=np.float64)
    return lambda x: np.abs(np.sum(((x - centre) / axes) ** 2, axis=1) - 1.0) < 1e-6


def _plane(axis: int, value: float, tol: float) -> _Surface:
    return lambda x: np.abs(x[:, axis] - value) < tol


def _all_on(surface: _Surface) -> _Rule:
    return lambda x: bool(np.all(surface(x)))


def _add_ellipsoid(occ: Any, axes: npt.NDArray[np.float64], octant: bool) -> int:
    """An OCC ellipsoid at the origin (or its x, y, z >= 0 eighth); a true sphere if it is one."""
    angles = {"angle1": 0.0, "angle2": math.pi / 2, "angle3": math.pi / 2} if octant else {}
    if np.all(axes == axes[0]):
        return occ.addSphere(0.0, 0.0, 0.0, axes[0], **angles)
    # Scaling turns the sphere into a B-spline surface: keep true spheres unscaled.
    tag = occ.addSphere(0.0, 0.0, 0.0, 1.0, **angles)
    occ.dilate([(3, tag)], 0.0, 0.0, 0.0, *axes)
    return tag


def _check_order(order: int) -> None:
    if order not in (1, 2):
        raise GeometryError(f"mesh order must be 1 or 2, got {order}")


def _check_mesh_size(mesh_size: float | None, default: float) -> float:
    if mesh_size is None:
        return default
    if not mesh_size > 0:
        raise GeometryError(f"mesh_size must be positive, got {mesh_size}")
    return float(mesh_size)


def sphere(
    comm: MPI.Comm,
    inner_radius: float = 1.0,
    outer_radius: float = 2.0,
    mesh_size: float | None = None,
    octant: bool = True,
    order: int = 1,
    *,
    msh_file: str | Path | None = None,
) -> Geometry:
    """Thick-walled sphere (``inner_radius > 0``) or ball (``inner_radius == 0``) at the origin.

    Boundaries ``outer`` (+ ``inner`` when hollow); ``octant=True`` keeps the x, y, z >= 0
    eighth and adds the symmetry planes ``x0, y0, z0``. ``order=2`` gives curved quadratic
    tetrahedra. ``msh_file`` also saves the gmsh mesh there.
    """
    if not 0.0 <= inner_radius < outer_radius:
        radii = f"inner_radius={inner_radius}, outer_radius={outer_radius}"
        raise GeometryError(f"sphere needs 0 <= inner_radius < outer_radius, got {radii}")
    return ellipsoid(
        comm,
        (outer_radius,) * 3,
        (inner_radius,) * 3 if inner_radius > 0 else None,
        mesh_size,
        octant,
        order,
        msh_file=msh_file,
    )


def ellipsoid(
    comm: MPI.Comm,
    semi_axes: tuple[float, float, float] = (1.0, 0.8, 0.6),
    inner_semi_axes: tuple[float, float, float] | None = None,
    mesh_size: float | None = None,
    octant: bool = False,
    order: int = 1,
    *,
    msh_file: str | Path | None = None,
) -> Geometry:
    """Solid or hollow ellipsoid centred at the origin, axes along x, y, z.

    Boundaries ``outer`` (+ ``inner`` when hollow, + ``x0, y0, z0`` with ``octant``).
    """
    outer = np.asarray(semi_axes, dtype=np.float64)
    inner = None if inner_semi_axes is None else np.asarray(inner_semi_axes, dtype=np.float64)
    if outer.shape != (3,) or not np.all(outer > 0):
        raise GeometryError(f"ellipsoid needs three positive semi-axes, got {semi_axes}")
    if inner is not None and (inner.shape != (3,) or not np.all((0 < inner) & (inner < outer))):
        raise GeometryError(f"inner semi-axes must be positive and below {semi_axes}, got {inner_semi_axes}")
    _check_order(order)
    wall = outer.min() if inner is None else (outer - inner).min()
    volume = 4 / 3 * math.pi * (np.prod(outer) - (0 if inner is None else np.prod(inner)))
    volume /= 8 if octant else 1
    # A few cells across the wall, but no more than ~4000 cells (gmsh makes ~7 V / h^3 tetrahedra).
    default = max(min(outer.min() / 5, wall / 4), (7 * volume / 4000) ** (1 / 3))
    h = _check_mesh_size(mesh_size, default)

    def build(occ: Any) -> tuple[int, dict[str, _Rule], str]:
        solid = _add_ellipsoid(occ, outer, octant)
        if inner is not None:
            hole = _add_ellipsoid(occ, inner, octant)
            [(_, solid)], _ = occ.cut([(3, solid)], [(3, hole)])
        tol = 1e-6 * outer.max()
        rules: dict[str, _Rule] = {}
        if inner is not None:
            rules["inner"] = _all_on(_ellipsoid_surface(inner))
        rules["outer"] = _all_on(_ellipsoid_surface(outer))
        if octant:
            rules |= {f"{letter}0": _all_on(_plane(axis, 0.0, tol)) for axis, letter in enumerate("xyz")}
        return solid, rules, "solid"

    return _gmsh_geometry(comm, build, h, order, msh_file)


def lung_phantom(
    comm: MPI.Comm,
    height: float = 0.24,
    width: float = 0.11,
    depth: float = 0.17,
    mesh_size: float | None = None,
    side: str = "right",
    order: int = 1,
    *,
    msh_file: str | Path | None = None,
    shape: LungShape | None = None,
) -> Geometry:
    """A generic adult lung, in metres.

    Axes: x towards the patient's right, y anterior, z superior. The mediastinal face is the
    plane x = 0 (the right lung lies at x > 0, the left at x < 0) and z = 0 is near the base.
    The body is an egg-like ellipsoid, tapered towards the apex; a sphere from below carves
    the diaphragmatic dome; the left lung has a cardiac notch (part of ``mediastinum``).

    ``shape`` gives the lung's full description (:class:`lungmech.mesh.lung_shape.LungShape`:
    apex taper, dome height, mediastinal flattening, cardiac notch); ``height``, ``width``,
    ``depth`` and ``side`` then stay at their defaults or repeat the shape's values.

    Boundaries: ``pleura`` (costal and apical surface), ``diaphragm``, ``mediastinum``
    (medial face without the hilum), ``hilum`` (an elliptic patch on the medial face at about
    60 % of the height). Cells are tagged 1, named ``lung``.
    """
    if shape is None:
        shape = LungShape(height, width, depth, side)
    else:  # the size and side arguments may keep their defaults or repeat the shape's values
        given, default = {"height": height, "width": width, "depth": depth, "side": side}, LungShape()
        clash = [f"{k}={v!r}" for k, v in given.items() if v not in (getattr(default, k), getattr(shape, k))]
        if clash:
            raise GeometryError(f"lung_phantom got a shape and {', '.join(clash)}, which differ from it")
    _check_order(order)
    H, W, D = shape.height, shape.width, shape.depth
    h = _check_mesh_size(mesh_size, 0.16 * min(H, W, D))
    body_centre, upper_axes, lower_axes = shape.body_centre, shape.upper_axes, shape.lower_axes
    dome_centre, dome_radius = shape.dome_centre, shape.dome_radius
    notch_centre, notch_radius = shape.notch_centre, shape.notch_radius
    hilum_centre, hilum_radii = shape.hilum_centre, shape.hilum_radii  # radii along (z, y)

    def build(occ: Any) -> tuple[int, dict[str, _Rule], str]:
        up = occ.addSphere(*body_centre, 1.0, angle1=0.0)
        occ.dilate([(3, up)], *body_centre, *upper_axes)
        down = occ.addSphere(*body_centre, 1.0, angle2=0.0)
        occ.dilate([(3, down)], *body_centre, *lower_axes)
        [(_, lung)], _ = occ.fuse([(3, up)], [(3, down)])
        big = 2.0 * max(H, W, D)
        # Everything on the far side of the mediastinal plane x = 0 goes.
        midline = occ.addBox(-big if shape.side == "right" else 0.0, -big / 2, -big / 2, big, big, 2 * big)
        dome = occ.addSphere(*dome_centre, dome_radius)
        tools = [(3, midline), (3, dome)]
        if notch_radius > 0:
            tools.append((3, occ.addSphere(*notch_centre, notch_radius)))
        [(_, lung)], _ = occ.cut([(3, lung)], tools)
        # Imprint the hilum on the mediastinal face; OCC wants the major axis first.
        major = [0.0, 0.0, 1.0] if hilum_radii[0] >= hilum_radii[1] else [0.0, 1.0, 0.0]
        radii = sorted(hilum_radii, reverse=True)
        disk = occ.addDisk(*hilum_centre, *radii, zAxis=[1.0, 0.0, 0.0], xAxis=major)
        out, _ = occ.fragment([(3, lung)], [(2, disk)])
        [lung] = [tag for dim, tag in out if dim == 3]

        upper = _all_on(_ellipsoid_surface(upper_axes, body_centre))
        lower = _all_on(_ellipsoid_surface(lower_axes, body_centre))
        medial = _all_on(_plane(0, 0.0, 1e-6 * H))
        notch = _all_on(_ellipsoid_surface([notch_radius] * 3, notch_centre))

        def hilum(x: npt.NDArray[np.float64]) -> bool:
            r2 = np.sum(((x[:, [2, 1]] - hilum_centre[[2, 1]]) / hilum_radii) ** 2, axis=1)
            return medial(x) and bool(np.all(r2 < 1.0 + 1e-6))

        rules: dict[str, _Rule] = {
            "pleura": lambda x: upper(x) or lower(x),
            "diaphragm": _all_on(_ellipsoid_surface([dome_radius] * 3, dome_centre)),
            "mediastinum": lambda x: (medial(x) and not hilum(x)) or (notch_radius > 0 and notch(x)),
            "hilum": hilum,
        }
        return lung, rules, "lung"

    # Curvature-based sizing resolves the small hilum ellipse without refining the rest.
    return _gmsh_geometry(comm, build, h, order, msh_file, {"Mesh.MeshSizeFromCurvature": 12})
