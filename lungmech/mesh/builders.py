"""Every mesh builder: gmsh OpenCASCADE shapes made here (sphere, ellipsoid, lung phantom), and
DOLFINx's structured box, rectangle, Cook's membrane and quarter annulus
(:mod:`lungmech.mesh.structured`). Each has named boundaries.

Collective: under MPI, call a builder on all ranks. Gmsh models are built on rank 0 only and the
mesh is then distributed; a failure there is raised on every rank.
"""

from __future__ import annotations

import contextlib
import inspect
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
from lungmech.mesh.structured import box, cook_membrane, quarter_annulus, rectangle

__all__ = [
    "box",
    "cook_membrane",
    "default_mesh_size",
    "ellipsoid",
    "gmsh_session",
    "lung_phantom",
    "plate_with_holes",
    "quarter_annulus",
    "rectangle",
    "sphere",
]


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
    dim: int = 3,
) -> Geometry:
    """Mesh the OCC volume (a surface when ``dim`` is 2) made by ``build`` on rank 0, name its
    faces (curves), distribute the mesh.

    ``build(occ)`` adds one volume and returns ``(volume_tag, rules, cell_name)``; boundary
    tags are numbered 1, 2, ... in the order of ``rules``.
    """
    root = 0
    if comm.rank != root:
        if failure := comm.bcast(None, root=root):
            raise GeometryError(failure)
        return from_meshdata(dolfinx.io.gmsh.model_to_mesh(None, comm, root, gdim=dim))

    with gmsh_session({"Mesh.MeshSizeMax": mesh_size, **(options or {})}) as gmsh:
        try:
            volume, rules, cell_name = build(gmsh.model.occ)
            gmsh.model.occ.synchronize()
            gmsh.model.mesh.generate(dim)
            faces = [face for _, face in gmsh.model.getBoundary([(dim, volume)], oriented=False)]
            named = _name_faces(gmsh.model, faces, rules, dim - 1)
            for tag, (name, group) in enumerate(named.items(), start=1):
                gmsh.model.addPhysicalGroup(dim - 1, group, tag, name)
            gmsh.model.addPhysicalGroup(dim, [volume], 1, cell_name)
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
        return from_meshdata(dolfinx.io.gmsh.model_to_mesh(gmsh.model, comm, root, gdim=dim))


def _name_faces(model: Any, faces: list[int], rules: Mapping[str, _Rule], fdim: int = 2) -> dict[str, list[int]]:
    """Group faces by the one rule that their mesh nodes satisfy.

    Going by where the meshed faces actually are, not by the order OCC returns them, keeps the
    names right whatever the boolean operations did to the face numbering.
    """
    named: dict[str, list[int]] = {name: [] for name in rules}
    for face in faces:
        _, coords, _ = model.mesh.getNodes(fdim, face, includeBoundary=True)
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


def _ellipsoid_mesh_size(outer: npt.NDArray[np.float64], inner: npt.NDArray[np.float64] | None, octant: bool) -> float:
    """A few cells across the wall, but no more than ~4000 cells (gmsh makes ~7 V / h^3 tetrahedra)."""
    wall = outer.min() if inner is None else (outer - inner).min()
    volume = 4 / 3 * math.pi * (np.prod(outer) - (0 if inner is None else np.prod(inner)))
    volume /= 8 if octant else 1
    return float(max(min(outer.min() / 5, wall / 4), (7 * volume / 4000) ** (1 / 3)))


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
    h = _check_mesh_size(mesh_size, _ellipsoid_mesh_size(outer, inner, octant))

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


def _lung_mesh_size(shape: LungShape) -> float:
    return 0.16 * min(shape.height, shape.width, shape.depth)


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
    h = _check_mesh_size(mesh_size, _lung_mesh_size(shape))
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


def plate_with_holes(
    comm: MPI.Comm,
    lengths: tuple[float, float] = (10.0, 10.0),
    holes: tuple[tuple[float, float, float], ...] = ((2.5, 2.5, 1.0), (5.0, 7.5, 5.0 / 3.0), (7.5, 2.5, 0.5)),
    mesh_size: float | None = None,
    order: int = 1,
    *,
    msh_file: str | Path | None = None,
) -> Geometry:
    """A plate [0, Lx] × [0, Ly] (2-D) with circular holes, each (x, y, r), inside it and apart.

    Boundaries ``x0``, ``x1``, ``y0``, ``y1`` (its edges) and ``holes`` (every hole's edge);
    cells tagged 1, named ``plate``. The default is the anchor plate of NeuROM's NN-PGD (a
    10 × 10 square with three holes); the default mesh size is a fiftieth of its shorter side.
    """
    _check_order(order)
    width, height = (float(v) for v in lengths)
    if not (width > 0 and height > 0):
        raise GeometryError(f"plate_with_holes: lengths must be positive, got {lengths}")
    circles = [tuple(float(v) for v in hole) for hole in holes]
    for i, (x, y, r) in enumerate(circles):
        if not (r > 0 and r < x < width - r and r < y < height - r):
            raise GeometryError(f"plate_with_holes: hole {i + 1} ({x:g}, {y:g}, r = {r:g}) is not inside the plate")
        for j, (a, b, q) in enumerate(circles[:i]):
            if math.hypot(x - a, y - b) <= r + q:
                raise GeometryError(f"plate_with_holes: holes {j + 1} and {i + 1} overlap")
    h = _check_mesh_size(mesh_size, min(width, height) / 50)

    def build(occ: Any) -> tuple[int, dict[str, _Rule], str]:
        plate = occ.addRectangle(0.0, 0.0, 0.0, width, height)
        if circles:
            disks = [(2, occ.addDisk(x, y, 0.0, r, r)) for x, y, r in circles]
            [(_, plate)], _ = occ.cut([(2, plate)], disks)
        tol = 1e-6 * max(width, height)

        def on_a_hole(x: npt.NDArray[np.float64]) -> bool:
            return any(bool(np.all(np.abs(np.hypot(x[:, 0] - a, x[:, 1] - b) - r) < tol)) for a, b, r in circles)

        rules: dict[str, _Rule] = {
            "x0": _all_on(_plane(0, 0.0, tol)),
            "x1": _all_on(_plane(0, width, tol)),
            "y0": _all_on(_plane(1, 0.0, tol)),
            "y1": _all_on(_plane(1, height, tol)),
        }
        if circles:
            rules["holes"] = on_a_hole
        return plate, rules, "plate"

    return _gmsh_geometry(comm, build, h, order, msh_file, dim=2)


def default_mesh_size(builder: Callable[..., Geometry], given: Mapping[str, Any]) -> float | None:
    """The mesh size (m) a gmsh ``builder`` (:func:`sphere`, :func:`ellipsoid`,
    :func:`lung_phantom`) uses when ``given`` its keyword arguments without ``mesh_size``; None
    for a builder that has none (a box or a mapped square: give it ``cells``)."""
    arguments = inspect.signature(builder).bind_partial(None, **given)
    arguments.apply_defaults()
    values = arguments.arguments
    if builder is lung_phantom:
        shape = values["shape"] or LungShape(values["height"], values["width"], values["depth"], values["side"])
        return _lung_mesh_size(shape)
    if builder is ellipsoid:
        inner = values["inner_semi_axes"]
        return _ellipsoid_mesh_size(
            np.asarray(values["semi_axes"], dtype=np.float64),
            None if inner is None else np.asarray(inner, dtype=np.float64),
            bool(values["octant"]),
        )
    if builder is sphere:
        outer, inner = float(values["outer_radius"]), float(values["inner_radius"])
        return _ellipsoid_mesh_size(np.full(3, outer), np.full(3, inner) if inner > 0 else None, bool(values["octant"]))
    return None
