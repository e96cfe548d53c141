"""Mesh files, read into and written from a :class:`~lungmech.mesh.geometry.Geometry`: gmsh's
``.msh`` (read), VTK's ``.vtu`` with the tags inside (:mod:`lungmech.mesh.vtu`; what lungmech
writes, and what meshio, pyvista and ParaView open), and DOLFINx's ``.xdmf`` (with its ``.h5``
data and a ``.tags.json`` sidecar of boundary names; parallel HDF5, for a mesh too large for
one rank).

Collective: under MPI, call on all ranks.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

from mpi4py import MPI

import dolfinx
import dolfinx.io
import dolfinx.mesh
import numpy as np

from lungmech.errors import GeometryError
from lungmech.mesh import vtu
from lungmech.mesh.builders import gmsh_session
from lungmech.mesh.geometry import Geometry, from_meshdata
from lungmech.parallel import on_root

__all__ = ["companions", "from_file", "is_lungmech_mesh", "write"]


def from_file(
    path: str | Path,
    comm: MPI.Comm = MPI.COMM_WORLD,
    boundaries: Mapping[str, int] | None = None,
    dimension: int | None = None,
) -> Geometry:
    """Read a geometry from a gmsh ``.msh``, a ``.vtu`` or a DOLFINx ``.xdmf`` file.

    A 3-D body (tetrahedra or hexahedra) or a plane one (triangles or quadrilaterals in the
    x–y plane: a 2-D gmsh mesh has z = 0 everywhere, and is read with two coordinates);
    ``dimension`` asks for one of them. Boundary names come from ``boundaries`` if given, else
    from the gmsh physical names of the facets' dimension (surfaces in 3-D, curves in 2-D;
    ``.msh``), the field data (``.vtu``) or the sidecar ``<stem>.tags.json`` written by
    :func:`write` (``.xdmf``); tag values
    without a name are named by their number, e.g. ``"3"``.
    """
    path = Path(path)
    if path.suffix not in READERS:
        raise GeometryError(f"cannot read mesh file '{path}': suffix {path.suffix!r} is not .msh, .vtu or .xdmf")
    if not path.is_file():
        raise GeometryError(f"mesh file '{path}' not found")
    geometry = READERS[path.suffix](path, comm)
    if path.suffix == ".vtu":
        _check_solid(geometry.mesh, path)
    found = geometry.mesh.topology.dim
    if dimension is not None and found != dimension:
        raise GeometryError(
            f"mesh file '{path}' holds a {found}-D mesh ({geometry.mesh.topology.cell_name()} cells); "
            f"a {dimension}-D body is needed here"
        )

    present = _global_values(geometry.facet_tags, comm)
    names = dict(boundaries if boundaries is not None else geometry.boundaries)
    for name, tag in names.items():
        if tag not in present:
            raise GeometryError(
                f"mesh file '{path}': boundary {name!r} has tag {tag}, which no facet carries; "
                f"tags present: {', '.join(map(str, sorted(present)))}"
            )
    names |= {str(tag): tag for tag in sorted(present - set(names.values()))}
    source = f"mesh file '{path}'"
    if path.suffix == ".xdmf" and boundaries is None and not _sidecar(path).is_file():
        source += (
            f" (its boundary names, '{_sidecar(path).name}', are missing, so its boundaries go by tag number; "
            "name them in [geometry] boundaries = {name = tag, ...})"
        )
    return Geometry(geometry.mesh, geometry.facet_tags, names, geometry.cell_tags, source)


def _check_solid(mesh: dolfinx.mesh.Mesh, path: Path) -> None:
    """A 3-D body or a plane one (x, y only), with finite node coordinates (collective)."""
    if mesh.topology.dim not in (2, 3) or mesh.geometry.dim != mesh.topology.dim:
        raise GeometryError(
            f"mesh file '{path}' holds a {mesh.topology.dim}-D mesh ({mesh.topology.cell_name()} cells) "
            f"in {mesh.geometry.dim}-D space; lungmech solves 3-D bodies (tetrahedra or hexahedra) and "
            "plane ones (triangles or quadrilaterals in the x-y plane)"
        )
    finite = mesh.comm.allreduce(bool(np.isfinite(mesh.geometry.x).all()), op=MPI.LAND)
    if not finite:
        raise GeometryError(f"mesh file '{path}' has node coordinates that are not finite numbers (nan or inf)")


def companions(path: str | Path) -> list[Path]:
    """The files that go with a mesh file: an .xdmf's .h5 data and .tags.json boundary names."""
    path = Path(path)
    return [path.with_suffix(".h5"), _sidecar(path)] if path.suffix == ".xdmf" else []


def is_lungmech_mesh(path: str | Path) -> bool:
    """Whether ``path`` is a mesh file that lungmech wrote, unchanged since: a ``.vtu`` whose
    digest matches, or an ``.xdmf`` with its ``.h5`` (its boundary-names file says so and holds
    their SHA-256)."""
    path = Path(path)
    if path.suffix == ".vtu":
        return vtu.written_by_lungmech(path)
    try:
        names = json.loads(_sidecar(path).read_text())
        written = names["sha256"]
        return (
            path.suffix == ".xdmf"
            and names["written_by"] == "lungmech"
            and all(_sha256(path.with_name(name)) == sha for name, sha in written.items())
            and set(written) == {path.name, path.with_suffix(".h5").name}
        )
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return False


def _sha256(path: Path) -> str:
    with open(path, "rb") as stream:
        return hashlib.sha256(stream.read()).hexdigest()


def _global_values(tags: dolfinx.mesh.MeshTags, comm: MPI.Comm) -> set[int]:
    """All tag values in use, on any rank."""
    return set().union(*comm.allgather({int(v) for v in np.unique(tags.values)}))


def _read_msh(path: Path, comm: MPI.Comm) -> Geometry:
    """Read a .msh file quietly (dolfinx.io.gmsh.read_from_msh is not quiet, and finalizes gmsh)."""
    root = 0
    if comm.rank != root:
        failure, gdim = comm.bcast(None, root=root)
        if failure:
            raise GeometryError(failure)
        return _to_geometry(path, lambda: dolfinx.io.gmsh.model_to_mesh(None, comm, root, gdim=gdim))
    with gmsh_session({}) as gmsh:
        try:
            gmsh.merge(str(path))
            gdim = _gmsh_dimension(gmsh, path)
        except Exception as e:
            failure = str(e) if isinstance(e, GeometryError) else f"cannot read mesh file '{path}': {e}"
            comm.bcast((failure, None), root=root)
            raise GeometryError(failure) from e
        comm.bcast((None, gdim), root=root)
        return _to_geometry(path, lambda: dolfinx.io.gmsh.model_to_mesh(gmsh.model, comm, root, gdim=gdim))


def _gmsh_dimension(gmsh: Any, path: Path) -> int:
    """The space dimension to read a gmsh model in: its own (the highest of its elements), with
    a 2-D mesh required to lie in the plane z = 0."""
    dimension = gmsh.model.getDimension()
    if dimension == 2:
        _, coordinates, _ = gmsh.model.mesh.getNodes()
        z = np.abs(np.asarray(coordinates).reshape(-1, 3)[:, 2])
        if z.size and z.max() > 1e-12 * max(1.0, float(np.abs(coordinates).max())):
            raise GeometryError(
                f"mesh file '{path}' holds a 2-D mesh that does not lie in the plane z = 0 "
                f"(|z| up to {z.max():.3g}): a plane body is meshed in the x-y plane"
            )
    return dimension


def _to_geometry(path: Path, read: Callable[[], Any]) -> Geometry:
    try:
        data = read()
    except RuntimeError as e:  # raised on all ranks alike (model_to_mesh broadcasts its checks)
        raise GeometryError(f"cannot read mesh file '{path}': {e}") from e
    _check_solid(data.mesh, path)
    if data.facet_tags is None:
        fdim = data.mesh.topology.dim - 1
        kind = "surfaces" if fdim == 2 else "curves"
        raise GeometryError(f"mesh file '{path}' has no facet tags (no physical groups of {kind}, dimension {fdim})")
    return from_meshdata(data)


def _read_xdmf(path: Path, comm: MPI.Comm) -> Geometry:
    try:
        grids = {grid.get("Name") for grid in ET.parse(path).iter("Grid")}
    except ET.ParseError as e:
        raise GeometryError(f"cannot read mesh file '{path}': not valid XDMF ({e})") from None
    if "mesh" not in grids:
        raise GeometryError(f"mesh file '{path}' has no grid named 'mesh'")
    if "facet_tags" not in grids:
        raise GeometryError(f"mesh file '{path}' has no facet tags (no grid named 'facet_tags')")
    for data in _data_files(path):
        if not data.is_file():
            raise GeometryError(f"mesh file '{path}': its data file '{data}' is missing")
    try:
        with dolfinx.io.XDMFFile(comm, str(path), "r") as file:
            mesh = file.read_mesh(name="mesh")
            mesh.topology.create_connectivity(mesh.topology.dim - 1, mesh.topology.dim)
            facet_tags = file.read_meshtags(mesh, name="facet_tags")
            cell_tags = file.read_meshtags(mesh, name="cell_tags") if "cell_tags" in grids else None
    except RuntimeError as e:  # HDF5 or XDMF errors, raised on every rank alike
        raise GeometryError(f"cannot read mesh file '{path}': {str(e).strip().splitlines()[-1]}") from None
    _check_solid(mesh, path)

    boundaries: dict[str, int] = {}
    sidecar = _sidecar(path)
    if sidecar.is_file():
        try:
            boundaries = {str(k): int(v) for k, v in json.loads(sidecar.read_text())["boundaries"].items()}
        except (ValueError, KeyError, TypeError, AttributeError) as e:
            message = f"""expected {{"boundaries": {{name: tag, ...}}}} ({e!r})"""
            raise GeometryError(f"cannot read boundary names from '{sidecar}': {message}") from None
    return Geometry(mesh, facet_tags, boundaries, cell_tags)


READERS: dict[str, Callable[[Path, MPI.Comm], Geometry]] = {".msh": _read_msh, ".vtu": vtu.read, ".xdmf": _read_xdmf}


def _data_files(path: Path) -> set[Path]:
    """The HDF5 files an XDMF file refers to (``file.h5:/dataset``), relative to it."""
    names = {
        item.text.strip().split(":")[0]
        for item in ET.parse(path).iter("DataItem")
        if item.get("Format") == "HDF" and item.text
    }
    return {path.parent / name for name in names}


def _sidecar(path: Path) -> Path:
    return path.with_suffix(".tags.json")


@contextlib.contextmanager
def _named(obj: Any, name: str) -> Iterator[None]:
    """Temporarily rename a mesh or mesh tags: XDMF stores them under their current name."""
    old, obj.name = obj.name, name
    try:
        yield
    finally:
        obj.name = old


def write(geometry: Geometry, path: str | Path) -> None:
    """Collective: write ``geometry`` to ``path``: a ``.vtu`` (:mod:`lungmech.mesh.vtu`), or an
    ``.xdmf`` with ``.h5`` data and a ``.tags.json`` sidecar."""
    path = Path(path)
    if path.suffix not in (".vtu", ".xdmf"):
        raise GeometryError(f"cannot write '{path}': geometries are written as .vtu (or .xdmf)")
    mesh, comm = geometry.mesh, geometry.mesh.comm
    on_root(comm, lambda: path.parent.mkdir(parents=True, exist_ok=True))
    if path.suffix == ".vtu":
        vtu.write(geometry, path)
        return
    with dolfinx.io.XDMFFile(comm, str(path), "w") as file:
        with _named(mesh, "mesh"):
            file.write_mesh(mesh)
        with _named(geometry.facet_tags, "facet_tags"):
            file.write_meshtags(geometry.facet_tags, mesh.geometry)
        if geometry.cell_tags is not None:
            with _named(geometry.cell_tags, "cell_tags"):
                file.write_meshtags(geometry.cell_tags, mesh.geometry)

    def sidecar() -> None:
        files = {p.name: _sha256(p) for p in (path, path.with_suffix(".h5"))}
        names = {"boundaries": dict(geometry.boundaries), "written_by": "lungmech", "sha256": files}
        _sidecar(path).write_text(json.dumps(names, indent=2) + "\n")

    on_root(comm, sidecar)  # collective: no rank reads the sidecar before it exists
