"""Results on disk: field time series that every viewer opens, and JSON summaries.

Fields are written as VTK XML: ``fields.pvd`` lists one file per output time, a ``.vtu`` in a
serial run, a ``.pvtu`` with one ``.vtu`` piece per rank under MPI. ParaView, pyvista and meshio
(the ``.vtu`` files) read them. Each file holds the model's mesh (its reference configuration;
for a model of an image's motion, the image), the displacement from it (``Model.motion``: u, or
the motion w from the image) and the pressure of the mixed formulation at the nodes of the displacement's
Lagrange space, quadratic cells included, and cellwise fields (J, stresses, the lung's
fractions): "warp by vector" shows the deformed body. ``format="vtx"`` writes ADIOS2 ``.bp``
folders instead (ParaView's ADIOS2 reader).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING
from xml.sax.saxutils import quoteattr

from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem, plot

from lungmech import jit
from lungmech.mesh import nodes
from lungmech.mesh import write as write_geometry
from lungmech.parallel import on_root, together

if TYPE_CHECKING:
    from lungmech.fem.model import Model

__all__ = ["FORMATS", "FieldWriter", "cell_fields", "write_json", "write_reference"]

FORMATS = ("vtk", "vtx")


def cell_fields(model: Model) -> dict[str, ufl.core.expr.Expr]:
    """Cellwise scalar fields worth looking at: J, von Mises and mean Cauchy stress, plus those the
    formulation names (``formulation.output_fields(model)``, e.g. the lung's fractions)."""
    sigma = model.cauchy()
    deviator = ufl.dev(sigma)
    fields = {
        "J": ufl.det(model.F),
        "von_mises": ufl.sqrt(1.5 * ufl.inner(deviator, deviator)),
        "mean_stress": ufl.tr(sigma) / 3,
    }
    if hasattr(model.formulation, "output_fields"):
        fields |= model.formulation.output_fields(model)
    return fields


class FieldWriter:
    """Time series of the displacement, the formulation's ``point_fields`` (at the displacement's
    nodes) and the cell fields of ``model`` in ``folder``, on the mesh's nodes at construction
    (make it once the reference is in place: an inverse problem moves it).

    Collective: construct, :meth:`write` and :meth:`close` on every rank.
    """

    def __init__(self, model: Model, folder: Path, format: str = "vtk") -> None:
        if format not in FORMATS:
            raise ValueError(f"field format must be one of {', '.join(FORMATS)} (got {format!r})")
        mesh = model.geometry.mesh
        self._model, self._folder, self._format = model, Path(folder), format
        self._u = model.motion()  # from the mesh's nodes: warped by it, the mesh is the current body
        self._u.name = "displacement"
        self._point = [self._u]
        # The formulation's scalar fields at the displacement's nodes (the mixed pressure, say).
        nodal = fem.functionspace(mesh, ("Lagrange", model.degree))
        self._nodal = [
            (fem.Function(nodal, name=name), jit.expression(expr, nodal.element.interpolation_points))
            for name, expr in getattr(model.formulation, "point_fields", lambda model: {})(model).items()
        ]
        self._point += [function for function, _ in self._nodal]
        dg0 = fem.functionspace(mesh, ("DG", 0))
        self._cells = [
            (fem.Function(dg0, name=name), jit.expression(expr, dg0.element.interpolation_points))
            for name, expr in cell_fields(model).items()
        ]
        owned = mesh.topology.index_map(mesh.topology.dim).size_local
        self._cell_dofs = dg0.dofmap.list[:owned, 0]
        self._times: list[float] = []
        self._vtx = None
        if format == "vtx":
            from dolfinx.io import VTXWriter

            self._vtx = [
                VTXWriter(mesh.comm, self._folder / "displacement.bp", self._point, engine="BP4"),
                VTXWriter(mesh.comm, self._folder / "cell_fields.bp", [f for f, _ in self._cells], engine="BP4"),
            ]
        else:
            self._grid = _grid(self._u.function_space)

    def write(self, t: float) -> None:
        self._u.x.array[:] = self._model.motion().x.array
        for function, expression in (*self._nodal, *self._cells):
            function.interpolate(expression)
        if self._vtx is not None:
            for writer in self._vtx:
                writer.write(t)
            return
        self._write_vtk(t)

    def _write_vtk(self, t: float) -> None:
        comm = self._u.function_space.mesh.comm
        step = len(self._times)
        self._times.append(float(t))
        cells, points = self._grid
        point_data = {f.name: _as_vtk(f.x.array.reshape(len(points), -1)) for f in self._point}
        cell_data = {f.name: [f.x.array[self._cell_dofs]] for f, _ in self._cells}
        name = f"fields_{step:06d}"
        piece = f"{name}.vtu" if comm.size == 1 else f"{name}_p{comm.rank}.vtu"
        import meshio  # here: a run that writes no fields (a real-time rom solve) need not load it

        mesh = meshio.Mesh(points, [cells], point_data=point_data, cell_data=cell_data)
        with together(comm):  # a rank that cannot write its piece stops them all
            meshio.write(self._folder / piece, mesh, file_format="vtu", binary=True, compression="zlib")
        on_root(comm, lambda: self._write_collection(name, point_data, cell_data, comm.size))

    def _write_collection(self, name: str, point_data: dict, cell_data: dict, ranks: int) -> None:
        """The .pvtu of this step (under MPI) and the .pvd listing every step."""
        if ranks > 1:
            pieces = "".join(f'<Piece Source="{name}_p{r}.vtu"/>' for r in range(ranks))
            (self._folder / f"{name}.pvtu").write_text(
                '<?xml version="1.0"?>\n<VTKFile type="PUnstructuredGrid" version="1.0" byte_order="LittleEndian" '
                'header_type="UInt64">\n<PUnstructuredGrid GhostLevel="0">'
                f'<PPoints><PDataArray type="Float64" NumberOfComponents="3"/></PPoints>'
                f"<PPointData>{_declare(point_data)}</PPointData>"
                f"<PCellData>{_declare({k: v[0] for k, v in cell_data.items()})}</PCellData>"
                f"{pieces}</PUnstructuredGrid>\n</VTKFile>\n"
            )
        suffix = ".vtu" if ranks == 1 else ".pvtu"
        entries = "\n".join(
            f'    <DataSet timestep="{t!r}" part="0" file="fields_{i:06d}{suffix}"/>' for i, t in enumerate(self._times)
        )
        (self._folder / "fields.pvd").write_text(
            '<?xml version="1.0"?>\n<VTKFile type="Collection" version="1.0">\n  <Collection>\n'
            f"{entries}\n  </Collection>\n</VTKFile>\n"
        )

    def close(self) -> None:
        for writer in self._vtx or ():
            writer.close()


def _declare(data: dict[str, np.ndarray]) -> str:
    """The .pvtu declarations of the data arrays of the pieces."""
    return "".join(
        f'<PDataArray type="Float64" Name={quoteattr(name)} NumberOfComponents="{np.shape(a)[1] if np.ndim(a) > 1 else 1}"/>'
        for name, a in data.items()
    )


def _grid(space: fem.FunctionSpace) -> tuple[tuple[str, np.ndarray], np.ndarray]:
    """This rank's owned cells (meshio type, connectivity) and the node coordinates of ``space``
    (owned and ghost)."""
    mesh = space.mesh
    owned = mesh.topology.index_map(mesh.topology.dim).size_local
    topology, types, points = plot.vtk_mesh(space, np.arange(owned, dtype=np.int32))  # type: ignore[arg-type]  # the FunctionSpace overload (singledispatch) is not in the hints
    vtk_type = int(types[0]) if len(types) else 10
    per_cell = int(topology[0]) if len(topology) else 4
    connectivity = topology.reshape(-1, per_cell + 1)[:, 1:]
    kind = _MESHIO_TYPES.get((vtk_type, per_cell))
    if kind is None:
        raise ValueError(f"no VTK cell type for {per_cell}-node cells of VTK type {vtk_type}")
    name, order = kind
    return (name, connectivity[:, order] if order is not None else connectivity), points


# VTK's Lagrange cells of order 2 are its quadratic cells, up to the order of two hexahedron edges.
_HEX27 = [*range(18), 19, 18, *range(20, 27)]
_MESHIO_TYPES = {
    (5, 3): ("triangle", None),
    (69, 6): ("triangle6", None),
    (9, 4): ("quad", None),
    (70, 9): ("quad9", None),
    (10, 4): ("tetra", None),
    (71, 10): ("tetra10", None),
    (12, 8): ("hexahedron", None),
    (72, 27): ("hexahedron27", _HEX27),
}


def _as_vtk(values: np.ndarray) -> np.ndarray:
    """Point data as VTK reads vectors: an in-plane (2-D) vector gets its zero z component."""
    return np.column_stack([values, np.zeros(len(values))]) if values.shape[1] == 2 else values


def write_reference(model: Model, path: Path) -> None:
    """The model's unloaded reference as a mesh file (``reference.vtu``, :func:`lungmech.mesh.write`):
    its mesh, or for a model of an image's motion the image moved by its reference map ξ
    (the nodes are put back afterwards). Collective."""
    if model.reference_map is None:
        write_geometry(model.geometry, path)
        return
    xi = fem.Function(nodes.displacement_space(model.geometry.mesh)[0])
    xi.interpolate(model.reference_map)
    with nodes.deformed(xi):
        write_geometry(model.geometry, path)


def write_json(path: Path, data: dict, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
    """Collective: write ``data`` as JSON from rank 0 (numpy values converted); an error is
    raised on every rank."""
    on_root(comm, lambda: Path(path).write_text(json.dumps(data, indent=2, default=_plain) + "\n"))


def _plain(value: object) -> object:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} to JSON")
