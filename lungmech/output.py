"""Results on disk: VTX fields for ParaView, JSON summaries, and atomic output folders."""

from __future__ import annotations

import contextlib
import json
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import ufl
from dolfinx import fem
from dolfinx.io import VTXWriter
from mpi4py import MPI

from lungmech import lung


def cell_fields(model) -> dict[str, ufl.core.expr.Expr]:
    """Cellwise scalar fields worth looking at: J, von Mises and mean Cauchy stress (plus the lung's)."""
    sigma = model.cauchy()
    deviator = ufl.dev(sigma)
    fields = {
        "J": ufl.det(model.F),
        "von_mises": ufl.sqrt(1.5 * ufl.inner(deviator, deviator)),
        "mean_stress": ufl.tr(sigma) / 3,
    }
    if isinstance(model.formulation, lung.Poromechanics):
        fields |= lung.fields(model)
    return fields


class FieldWriter:
    """Time series of the displacement and the cell fields, as two VTX (.bp) folders.

    VTX keeps the displacement in its own (possibly quadratic) Lagrange space; cell fields are
    evaluated at cell midpoints into DG0.
    """

    def __init__(self, model, folder: Path):
        mesh = model.geometry.mesh
        self._model = model
        self._u = model.displacement()
        self._u.name = "displacement"
        dg0 = fem.functionspace(mesh, ("DG", 0))
        self._fields = []
        for name, expr in cell_fields(model).items():
            function = fem.Function(dg0, name=name)
            self._fields.append((function, fem.Expression(expr, dg0.element.interpolation_points)))
        folder = Path(folder)
        self._writers = [
            VTXWriter(mesh.comm, folder / "displacement.bp", [self._u], engine="BP4"),
            VTXWriter(mesh.comm, folder / "cell_fields.bp", [f for f, _ in self._fields], engine="BP4"),
        ]

    def write(self, t: float) -> None:
        self._u.x.array[:] = self._model.displacement().x.array
        for function, expression in self._fields:
            function.interpolate(expression)
        for writer in self._writers:
            writer.write(t)

    def close(self) -> None:
        for writer in self._writers:
            writer.close()


def write_json(path: Path, data: dict, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
    """Write ``data`` as JSON from rank 0 (numpy values converted)."""
    if comm.rank == 0:
        Path(path).write_text(json.dumps(data, indent=2, default=_plain) + "\n")
    comm.Barrier()


def _plain(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} to JSON")


@contextlib.contextmanager
def atomic_folder(target: Path, comm: MPI.Comm = MPI.COMM_WORLD) -> Iterator[Path]:
    """Yield a fresh staging folder that replaces ``target`` only if the block succeeds.

    A failed run leaves the previous results in ``target`` untouched.
    """
    target = Path(target).resolve()
    staging = None
    if comm.rank == 0:
        target.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    staging = comm.bcast(staging, root=0)
    try:
        yield staging
    except BaseException:
        comm.Barrier()
        if comm.rank == 0:
            shutil.rmtree(staging, ignore_errors=True)
        raise
    comm.Barrier()
    if comm.rank == 0:
        if target.exists():
            shutil.rmtree(target)
        staging.rename(target)
    comm.Barrier()
