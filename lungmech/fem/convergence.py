"""When a Newton solve is done: each field's residual against its own scale, down to round-off.

The unknowns of a model carry different units (the displacement's residual is a force, the
pressure's a volume, the solid fraction's an energy), and one absolute tolerance cannot fit them
all, nor every stiffness from 1 Pa to 1 GPa. So each field b is judged on its own:

    |r_b| <= max(rtol · R_b, atol, floor_b),

where R_b is the field's load scale — the largest load a step of the current load path has put
on the last equilibrium (the residual there at the step's loads: the first step's load, for a
path from rest; not the residual of a predicted state), rows next to imposed displacements left
out — and floor_b the round-off floor of its residual,

    floor_b = ε · ‖(|K| s)_b‖,    s = |x| + h·(1 on the displacement),

the size of the rounding errors made in assembling it: the entries of the tangent |K| times the
magnitudes they multiply. The displacement's entry is |u| + h, with h the cell size, because
F = I + ∇u rounds to ε relative to the identity whatever the displacement. Constrained rows hold
x − g and must vanish to 1000 ε·h.

A residual may stop at its floor only after falling to it quadratically (the last step cut it
tenfold, or the one before already sat within ten floors): a Newton solve that merely stalls is
not called converged. One that stalls — no field's residual falls by STALL_GAIN (1 %) in
STALL_ITERATIONS (5) iterations in a row — is stopped as diverged: a damped Newton crawling
along a curved valley (a nearly incompressible solid asked for too large a step) rarely arrives
within the iteration limit, and a shorter load step is cheaper. A solve that does not converge
says which field failed which test.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np

if TYPE_CHECKING:
    import dolfinx.mesh
    from dolfinx import fem

    from lungmech.fem.model import Model

__all__ = ["Fields", "absolute_product"]

EPS = float(np.finfo(float).eps)
STALL_GAIN, STALL_ITERATIONS = 0.01, 5  # a Newton solve gaining less, that many times in a row, has stalled
# The loosest linear solve of an inexact Newton: each Newton iteration reassembles the tangent and
# rebuilds AMG, dearer than Krylov iterations; on the lung cube 1e-3 beat 0.1 and 1e-2 (and 1e-9).
FORCING_MAX = 1e-3


@dataclass(frozen=True)
class Field:
    name: str
    unit: str  # of its residual
    rows: np.ndarray  # owned local rows of the free (unconstrained) dofs


class Fields:
    """The fields of a model's state vector (free owned rows each), its constrained rows, and the
    free rows coupled to them (where moving an imposed displacement shows in the residual)."""

    def __init__(self, model: Model) -> None:
        comm = model.geometry.mesh.comm
        constrained = model.constrained_dofs()
        units = {"u": "N" if model.plane is None else "N/m", **getattr(model.formulation, "residual_units", {})}
        self.fields = [
            Field(name, units.get(name, "?"), np.setdiff1d(rows, constrained))
            for name, rows in model.field_dofs().items()
        ]
        self.constrained = constrained
        self.lifted = _coupled(model.space, constrained)
        self.comm = comm
        self.cell_size = comm.allreduce(_cell_size(model.geometry.mesh), op=MPI.MIN)
        self.displacement = self.fields[0].rows

    def norms(self, vector: PETSc.Vec, leave_out: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """Global 2-norms of each field's free rows (but ``leave_out``), and the max-norm of the
        constrained rows."""
        a = vector.getArray(readonly=True)
        if leave_out is not None and leave_out.size:
            a = a.copy()
            a[leave_out] = 0.0
        local = np.array([float(np.dot(a[f.rows], a[f.rows])) for f in self.fields])
        squares = np.empty_like(local)
        self.comm.Allreduce(local, squares, op=MPI.SUM)
        worst = self.comm.allreduce(float(np.abs(a[self.constrained]).max(initial=0.0)), op=MPI.MAX)
        return np.sqrt(squares), worst

    def magnitudes(self, x: PETSc.Vec) -> PETSc.Vec:
        """s = |x| + h on the displacement: what each entry of the tangent multiplies."""
        s = x.duplicate()
        values = np.abs(x.getArray(readonly=True))
        values[self.displacement] += self.cell_size
        s.setArray(values)  # type: ignore[arg-type]  # petsc4py's stub wants a Sequence; an ndarray works
        return s

    def rounding(self, K: PETSc.Mat, x: PETSc.Vec) -> PETSc.Vec:
        """ε |K| s: the size of the rounding errors in each entry of the residual."""
        s = self.magnitudes(x)
        product = absolute_product(K, s)
        product.scale(EPS)
        s.destroy()
        return product

    def floors(self, K: PETSc.Mat, x: PETSc.Vec) -> np.ndarray:
        """ε ‖(|K| s)_b‖ per field: the round-off floors of the residuals."""
        rounding = self.rounding(K, x)
        floors = self.norms(rounding)[0]
        rounding.destroy()
        return floors


def absolute_product(K: PETSc.Mat, s: PETSc.Vec) -> PETSc.Vec:
    """|K| s, the matrix with the absolute values of K's entries applied to s (collective)."""
    A = K.duplicate(copy=True)
    rows, columns, values = A.getValuesCSR()
    A.setValuesCSR(rows, columns, np.abs(values))  # type: ignore[arg-type]  # petsc4py's stub wants Sequences; ndarrays work
    A.assemble()
    result = s.duplicate()
    A.mult(s, result)
    A.destroy()
    return result


def _cell_size(mesh: dolfinx.mesh.Mesh) -> float:
    """The shortest first edge of this rank's cells: a length on the scale of the cells (the
    minimum over ranks does not depend on the partition)."""
    cells = mesh.topology.index_map(mesh.topology.dim).size_local
    if cells == 0:
        return np.inf
    x = mesh.geometry.x[mesh.geometry.dofmaps[0][:cells]]
    return float(np.linalg.norm(x[:, 1] - x[:, 0], axis=1).min())


def _coupled(space: fem.FunctionSpace, constrained: np.ndarray) -> np.ndarray:
    """Owned rows that share a cell with a constrained dof (collective)."""
    from dolfinx import fem, la

    marks = fem.Function(space)
    bs = space.dofmap.index_map_bs
    owned = space.dofmap.index_map.size_local * bs
    hit = np.zeros(len(marks.x.array), dtype=bool)
    hit[constrained] = True
    cells = space.dofmap.list  # blocks of each local cell
    touched = hit.reshape(-1, bs).any(axis=1)[cells].any(axis=1)
    blocks = np.unique(cells[touched])
    marks.x.array[(blocks[:, None] * bs + np.arange(bs)).ravel()] = 1.0
    marks.x.scatter_reverse(la.InsertMode.add)  # a cell on another rank may couple a row owned here
    return np.flatnonzero(marks.x.array[:owned] > 0)


class Test:
    """The convergence test of a solver's Newton solves. :meth:`start_path` when a load path
    begins (the scales start again), :meth:`new_step` when a load step begins, :meth:`load`
    with its load, :meth:`start` before each Newton solve.

    A field's scale R_b is the largest step load of the path, leaving out the rows next to
    imposed displacements, where a moved constraint shows as a residual that is no load (a rigid
    translation imposed on a body, say).
    """

    def __init__(self, fields: Fields, rtol: float, atol: float) -> None:
        self.fields, self.rtol, self.atol = fields, rtol, atol
        self.start_path()

    def start_path(self) -> None:
        self.scale = np.zeros(len(self.fields.fields))
        self.new_step()

    def new_step(self) -> None:
        self.floor: np.ndarray | None = None  # from the step's first tangent
        self.start()

    def load(self, residual: PETSc.Vec) -> None:
        """A Newton solve's load: its starting residual at the last equilibrium (collective)."""
        self.scale = np.maximum(self.scale, self.fields.norms(residual, leave_out=self.fields.lifted)[0])

    def start(self) -> None:
        self.history: list[np.ndarray] = []
        self.constrained = 0.0
        self.stalled = False

    def __call__(self, residual: PETSc.Vec, iteration: int, jacobian: PETSc.Mat | None, x: PETSc.Vec) -> int:
        """0 (go on) or a PETSc converged reason (> 0) for the residual at ``iteration``."""
        norms, self.constrained = self.fields.norms(residual)
        self.history.append(norms)
        if iteration == 0 or jacobian is None:
            return PETSc.SNES.ConvergedReason.CONVERGED_FNORM_ABS if not norms.any() and not self.constrained else 0
        if self.floor is None:
            self.floor = self.fields.floors(jacobian, x)
        if self.constrained > 1e3 * EPS * self.fields.cell_size:
            return 0
        below = norms <= self.targets()
        previous = self.history[-2]
        at_floor = (norms <= self.floor) & ((norms <= 0.1 * previous) | (previous <= 10 * self.floor))
        if np.all(below | at_floor):
            return (
                PETSc.SNES.ConvergedReason.CONVERGED_FNORM_RELATIVE
                if np.all(below)
                else PETSc.SNES.ConvergedReason.CONVERGED_FNORM_ABS
            )
        recent = np.array(self.history[-STALL_ITERATIONS - 1 :])
        if len(recent) > STALL_ITERATIONS and np.all(recent[1:] > (1 - STALL_GAIN) * recent[:-1]):
            self.stalled = True
            return PETSc.SNES.ConvergedReason.DIVERGED_DTOL
        return 0

    def targets(self) -> np.ndarray:
        """Each field's tolerance but the round-off floor: max(rtol · R_b, atol)."""
        return np.maximum(self.rtol * self.scale, self.atol)

    def forcing(self) -> float:
        """The relative tolerance of the next linear solve of an inexact Newton: η = min(η_max, q),
        q = max over fields of |r_b|/|r_b,0| (η → 0 with the residual: superlinear, Dembo–Eisenstat–
        Steihaug), but never below a tenth of what the test still asks, min_b(target_b/|r_b|):
        a linear solve more exact than that would not change when Newton stops."""
        norms, first = self.history[-1], self.history[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            progress = np.where(first > 0, norms / first, 0.0).max(initial=0.0)
            targets = self.targets()
            if self.floor is not None:
                targets = np.maximum(targets, self.floor)
            needed = np.where(norms > 0, targets / norms, np.inf).min(initial=np.inf)
        return float(min(max(min(FORCING_MAX, progress), 0.1 * needed, 1e-12), FORCING_MAX))

    def describe(self) -> str:
        """What the last residual lacked, field by field (for a failure message)."""
        if not self.history:
            return "the residual is not a finite number (nan or inf)"
        if self.stalled:
            return (
                f"stalled: no residual fell by {STALL_GAIN:.0%} in {STALL_ITERATIONS} iterations in a row "
                f"({', '.join(f'{f.name} {n:.2e} {f.unit}' for f, n in zip(self.fields.fields, self.history[-1]))})"
            )
        norms = self.history[-1]
        floors = self.floor if self.floor is not None else [None] * len(norms)
        parts = []
        for f, norm, big, target, floor in zip(self.fields.fields, norms, self.scale, self.targets(), floors):
            if not np.isfinite(norm):
                parts.append(f"{f.name} residual is not a finite number")
            elif norm > max(target, floor or 0.0):
                shown = f"{floor:.1e} {f.unit}" if floor is not None else "not known yet"
                parts.append(
                    f"{f.name} residual {norm:.2e} {f.unit} > {target:.2e} {f.unit} ({self.rtol:.0e} of "
                    f"{big:.2e} {f.unit}; round-off floor {shown})"
                )
        if self.constrained > 1e3 * EPS * self.fields.cell_size:
            parts.append(f"imposed displacements missed by {self.constrained:.2e} m")
        return "; ".join(parts) or "every field met its test"
