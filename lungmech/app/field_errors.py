"""A trade's errors in the energy norm: every candidate's state at t* carried onto the
reference's mesh by non-matching interpolation, and measured there.

At a point μ, with x the candidate's state at t* (the last output time), x_ref the reference's
and x_ref,0 the reference's start state, I the interpolation onto the reference's space (field
by field: the displacement, and each field of the formulation the reference has) and ‖·‖_E the
energy norm of :func:`lungmech.rom.basis.inner_product` on the reference's space (the second
variation of the stored energy at rest and at the default parameters: one norm for every μ, the
norm a reduced model's error indicator is in),

    e(μ) = ‖I x − x_ref‖_E / ‖x_ref − x_ref,0‖_E,

relative to the reference's change of state along the path to t*, as a volume error is
relative to the path's volume change. Full candidates' fields come from lungmech's cache (the
trade's full solves keep them: :func:`lungmech.app.answers.kept_answer`); a model file's are
solved again here on its whole mesh (a reduced solve: its x₀ + V q). The three finest levels'
differences ‖I x_h − I x_h/2‖_E and ‖I x_h/2 − x_ref‖_E give the observed order.

Interpolation between nested meshes is exact for the coarser field; a remeshed geometry's
boundary differs from the reference's by O(h²), and points of the reference up to half a
candidate's cell outside it take its nearest cell's values. A point farther out would be
left at zero: every transfer is checked to carry a field of ones whole, and refused otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
from dolfinx import fem

from lungmech.app import reduce
from lungmech.app.answers import Task, answer, entry
from lungmech.app.cache import Cache
from lungmech.app.ladder import Discretisation, at
from lungmech.app.run import full_order_model
from lungmech.app.scene import Scene
from lungmech.errors import LungmechError, ParameterError
from lungmech.fem.model import Model
from lungmech.parallel.layout import Layout, field_dofs, layout
from lungmech.parallel.linalg import norms
from lungmech.parallel.owned import owned_size, owned_values
from lungmech.parallel.points import PointValues
from lungmech.rom.basis import inner_product, require_positive_definite
from lungmech.trade.convergence import Convergence, order_of_differences

__all__ = ["FieldErrors", "Transfer", "Transfers", "energy_errors", "energy_norm_allowed"]


class Transfer:
    """States of the ``source`` model's space carried onto the ``target`` model's, field by field
    (the target's fields, matched by name): each target field's values at its dofs' points, the
    source's field evaluated there (:class:`~lungmech.parallel.points.PointValues`: the target's
    interpolation, for elements whose dofs are point values: Lagrange, DG). Collective."""

    def __init__(self, source: Model, target: Model) -> None:
        offered = dict(zip(source.field_dofs(), field_dofs(source.space), strict=True))
        self._source, self._target = fem.Function(source.space), fem.Function(target.space)
        fields = list(zip(target.field_dofs(), field_dofs(target.space), strict=True))
        for name, (space, _) in fields:
            if name not in offered:
                raise ParameterError(f"the candidate has no field '{name}' to compare with the reference's")
            if not space.element.interpolation_ident:
                raise ParameterError(f"the reference's field '{name}' is not valued at points: it cannot be carried")
        largest = _largest_cell(source)
        # Points outside the source are searched for within the padding, at a cost that grows
        # with it: the least that covers the target (a nested mesh: none; a remesh: its gap).
        for padding in largest * np.array([1e-9, 1e-4, 1e-2, 0.1, 0.5]):
            self._fields = []
            for name, (space, dofs) in fields:
                from_space, from_dofs = offered[name]
                owned = space.dofmap.index_map.size_local
                points = space.tabulate_dof_coordinates()[:owned]
                at = PointValues(source.geometry.mesh, points, float(padding))
                giver = self._source if from_space is source.space else fem.Function(from_space)
                taker = self._target if space is target.space else fem.Function(space)
                self._fields.append((giver, from_dofs, taker, dofs, owned * space.dofmap.index_map_bs, at))
            if not (missed := self._missed(source)):
                return
        raise LungmechError(
            f"{missed} dofs of the reference lie outside the candidate's mesh by more than half its largest cell: "
            "its field cannot be compared there"
        )

    def __call__(self, state: np.ndarray) -> np.ndarray:
        """The target's owned entries of the source's state ``state`` (owned entries)."""
        self._source.x.array[: state.size] = state
        self._source.x.scatter_forward()
        self._target.x.array[:] = 0.0
        for source, from_dofs, target, dofs, owned, values_at in self._fields:
            if source is not self._source:  # a field of a mixed space: its collapsed copy
                source.x.array[:] = self._source.x.array[from_dofs]
            target.x.array[:] = 0.0
            target.x.array[:owned] = values_at(source).ravel()
            target.x.scatter_forward()
            if target is not self._target:
                self._target.x.array[dofs] = target.x.array
        return owned_values(self._target)

    def _missed(self, source: Model) -> int:
        """The number of the target's dofs the transfer leaves at zero: ones do not come out ones."""
        carried = self(np.ones(owned_size(source.space)))
        return source.geometry.mesh.comm.allreduce(int(np.sum(np.abs(carried - 1.0) > 1e-8)), op=MPI.SUM)


class Transfers:
    """Transfers onto one ``target``, made once per source mesh and element: a source numbered
    as one before it (the same fingerprint, the same canonical index of every owned dof on every
    rank: a model file of the same mesh, loaded again) takes that source's transfer, whose point
    search is most of its cost. Collective."""

    def __init__(self, target: Model) -> None:
        self.target = target
        self._made: dict[str, tuple[np.ndarray, Transfer]] = {}  # by the source's fingerprint

    def __call__(self, source: Model) -> Transfer:
        """The transfer of ``source``'s states onto the target."""
        where = layout(source.space)
        known = self._made.get(where.fingerprint)
        alike = known is not None and np.array_equal(known[0], where.index)
        if known is not None and where.comm.allreduce(alike, op=MPI.LAND):
            return known[1]
        transfer = Transfer(source, self.target)
        self._made[where.fingerprint] = (where.index, transfer)
        return transfer


@dataclass(frozen=True)
class FieldErrors:
    """A trade's energy-norm errors: per candidate name, one relative error per point (nan where
    the candidate or the reference failed), the reference's ``convergence`` (None without three
    nested levels that all solved) and ``notes`` on what was not measured."""

    errors: dict[str, np.ndarray]
    convergence: Convergence | None
    notes: tuple[str, ...] = ()


def energy_norm_allowed(model: Model) -> None:
    """Refuse, in one line, a reference whose energy is no norm of its states (a saddle point,
    a body free to move rigidly). Collective: one factorisation."""
    try:
        require_positive_definite(model, "energy")
    except ParameterError:
        raise ParameterError(
            "--quantity energy: the energy at rest is no norm of this scene's states (a saddle point, as a mixed "
            "formulation's pressure, or a body nothing holds): compare volume, pv or probes instead"
        ) from None


def energy_errors(
    scene_path: str | Path,
    scene: Scene,
    points: Sequence[dict[str, float]],
    times: Sequence[float],
    reference: Discretisation,
    candidates: dict[str, dict],
    cache: Cache,
    ladder: Sequence[str] = (),
    solved: dict[str, tuple[Model, list[np.ndarray | None]]] | None = None,
) -> FieldErrors:
    """The energy-norm errors (see the module's doc) of the ``candidates`` (name → request, as
    :mod:`lungmech.app.measure` takes them: a full model at a discretisation, whose fields the
    trade's solves kept in ``cache`` at ``points`` and ``times``, or a model file) against the
    full model at ``reference``; ``ladder``: the names of the three finest nested levels (the
    last the reference) for the observed order, expected to be the elements' degree.
    ``solved``: the model files' last states on their own meshes by path, filled here and read
    by a later call at the same points and times (a reduced model is solved once, whatever mesh
    it is judged on). Collective on the cache's communicator."""
    comm = cache.comm
    target = full_order_model(at(scene, reference, cache, comm), comm, start="inverse_motion").model
    known = solved if solved is not None else {}
    tasks = _Tasks(str(scene_path), scene, tuple(float(t) for t in times), cache, known, Transfers(target))
    energy_norm_allowed(target)
    norm = _EnergyNorm(inner_product(target, "energy"), comm)
    try:
        where = layout(target.space)
        kept = [tasks.kept(where, point, reference) for point in points]
        ends = [end for _, end in kept]
        scales = [math.nan if end is None else _positive(norm(end - start)) for start, end in kept]

        def relative(x: np.ndarray | None, x_ref: np.ndarray | None, scale: float) -> float:
            return math.nan if x is None or x_ref is None else norm(x - x_ref) / scale

        errors: dict[str, np.ndarray] = {}
        levels: dict[str, list[np.ndarray | None]] = {ladder[-1]: ends} if ladder else {}
        for name, request in candidates.items():
            full = request["kind"] == "full"
            if full and Discretisation(**request["discretisation"]) == reference:
                errors[name] = np.array([relative(x, x, s) for x, s in zip(ends, scales, strict=True)])
                continue
            fields = tasks.carried(request, points)
            errors[name] = np.array([relative(x, x_ref, s) for x, x_ref, s in zip(fields, ends, scales, strict=True)])
            if name in ladder:
                levels[name] = fields  # kept for the observed order only
        convergence, notes = None, []
        if len(ladder) == 3 and all(name in levels for name in ladder):
            coarse, middle, fine = (levels[name] for name in ladder)
            first = [relative(a, b, s) for a, b, s in zip(coarse, middle, scales, strict=True)]
            second = [relative(b, c, s) for b, c, s in zip(middle, fine, scales, strict=True)]
            if np.all(np.isfinite(first + second)):
                convergence = order_of_differences(max(first), max(second), float(scene.degree))
            else:
                notes.append("no observed order of energy: a level failed at a point")
    finally:
        norm.W.destroy()
    return FieldErrors(errors, convergence, tuple(notes))


@dataclass(frozen=True)
class _EnergyNorm:
    """‖v‖_E = √(vᵀ W v) of owned rows v, W the energy product (summed over all ranks)."""

    W: PETSc.Mat
    comm: MPI.Comm

    def __call__(self, vector: np.ndarray) -> float:
        return float(norms(vector[:, None], self.W, self.comm)[0])


@dataclass(frozen=True)
class _Tasks:
    """The trade's full tasks at its points (their fields kept), and candidates' states."""

    scene_path: str
    scene: Scene
    times: tuple[float, ...]
    cache: Cache
    solved: dict[str, tuple[Model, list[np.ndarray | None]]]  # a model file's states, by its path
    transfers: Transfers  # onto the reference

    def kept(
        self, where: Layout, point: dict[str, float], discretisation: Discretisation
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The start and last states of the full solve at ``point``, from the cache, on this
        rank's owned rows of ``where`` ((None, None): it failed, and nothing was kept)."""
        task = Task(self.scene_path, point, discretisation, self.times, fields=True)
        arrays = self.cache.read_arrays("fields", entry(self.scene, task))
        comm = self.cache.comm
        fingerprint = comm.bcast(None if arrays is None else str(arrays["fingerprint"]), root=0)
        if fingerprint is None:
            return None, None
        if fingerprint != where.fingerprint:
            raise LungmechError(f"the fields kept for full {discretisation.name} at {point} are of another mesh")
        return where.scatter(None if arrays is None else arrays["start"]), where.scatter(
            None if arrays is None else arrays["end"]
        )

    def carried(self, request: dict, points: Sequence[dict[str, float]]) -> list[np.ndarray | None]:
        """A candidate's last states at ``points``, on the reference's space (None: it failed)."""
        comm = self.cache.comm
        states: list[np.ndarray | None] = []
        if request["kind"] == "full":
            discretisation = Discretisation(**request["discretisation"])
            scene = at(self.scene, discretisation, self.cache, comm)
            source = full_order_model(scene, comm, start="inverse_motion").model
            where = layout(source.space)
            states = [self.kept(where, point, discretisation)[1] for point in points]
        else:
            source, states = self.solved.get(request["path"]) or self._solved(request["path"], points)
        transfer = self.transfers(source)
        return [None if state is None else transfer(state) for state in states]

    def _solved(self, path: str, points: Sequence[dict[str, float]]) -> tuple[Model, list[np.ndarray | None]]:
        """The last states of the model file at ``path`` at ``points`` (None: it failed there),
        solved on its whole mesh, and kept in ``solved``."""
        model = reduce.load(path, self.cache.comm, fields=True)  # on its whole mesh
        states: list[np.ndarray | None] = []
        for point in points:
            fields: list[np.ndarray] = []
            found = answer(model, point, self.times, fields)
            states.append(fields[1] if found["failed"] is None else None)
        self.solved[path] = (model.model, states)
        return self.solved[path]


def _positive(scale: float) -> float:
    return scale if scale > 0 else 1.0


def _largest_cell(model: Model) -> float:
    """The largest cell diameter of the model's mesh (m, over all ranks)."""
    mesh = model.geometry.mesh
    tdim = mesh.topology.dim
    count = mesh.topology.index_map(tdim).size_local
    local = float(mesh.h(tdim, np.arange(count, dtype=np.int32)).max(initial=0.0))
    return mesh.comm.allreduce(local, op=MPI.MAX)
