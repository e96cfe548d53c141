"""Global quantities and point values, MPI-safe: every reduction happens in here."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import ufl
from dolfinx import fem, geometry as dgeometry
from mpi4py import MPI

from lungmech.errors import ParameterError


def integral(form: ufl.Form, comm: MPI.Comm) -> Callable[[], float]:
    """A function returning the global value of a scalar form (compiled once, summed over ranks)."""
    compiled = fem.form(form)
    return lambda: comm.allreduce(fem.assemble_scalar(compiled), op=MPI.SUM)


def deformed_volume(model) -> Callable[[], float]:
    """∫ J dX: the current volume of the body."""
    return integral(ufl.det(model.F) * model.dx, model.geometry.mesh.comm)


def strain_energy(model) -> Callable[[], float]:
    """∫ ψ dX (the energy density of the model's formulation)."""
    return integral(model.energy_density * model.dx, model.geometry.mesh.comm)


class Probe:
    """Values of a Function at fixed reference points, the same on every rank."""

    def __init__(self, mesh, points: Sequence[Sequence[float]]):
        self.points = np.atleast_2d(np.asarray(points, dtype=float))
        if self.points.shape[1] != 3:
            raise ParameterError(f"probe points need 3 coordinates each (got shape {self.points.shape})")
        tree = dgeometry.bb_tree(mesh, mesh.topology.dim)
        candidates = dgeometry.compute_collisions_points(tree, self.points)
        colliding = dgeometry.compute_colliding_cells(mesh, candidates, self.points)
        found = np.array([len(colliding.links(i)) > 0 for i in range(len(self.points))])
        comm = mesh.comm
        # The lowest rank holding a point answers for it.
        owner = np.empty(len(self.points), dtype=np.int64)
        comm.Allreduce(np.where(found, comm.rank, comm.size).astype(np.int64), owner, op=MPI.MIN)
        missing = np.flatnonzero(owner == comm.size)
        if missing.size:
            point = ", ".join(f"{v:g}" for v in self.points[missing[0]])
            raise ParameterError(f"probe point ({point}) lies outside the mesh")
        self._mine = np.flatnonzero(owner == comm.rank)
        self._cells = np.array([colliding.links(i)[0] for i in self._mine], dtype=np.int32)
        self._comm = comm

    def __call__(self, function: fem.Function) -> np.ndarray:
        """Values at the points, shape (number of points, value size)."""
        values = np.zeros((len(self.points), function.function_space.value_size))
        if self._mine.size:
            values[self._mine] = function.eval(self.points[self._mine], self._cells).reshape(len(self._mine), -1)
        total = np.empty_like(values)
        self._comm.Allreduce(values, total, op=MPI.SUM)
        return total
