"""A reduced model of an imaged body at every μ: the inverse motion reduced, then the breath.

The full problem (:mod:`lungmech.fem.inverse_motion`) has two unknowns on the fixed imaged
mesh: the inverse map ξ(μ), the image's equilibrium at the loads of t₀, and the motion w(t; μ)
from the image, with ξ(μ) in its forms. A reduced model reduces both, each on its own basis:

    x_ξ(μ) = x_ξ⁰ + V_ξ a,   V_ξᵀ R_ξ(x_ξ⁰ + V_ξ a; μ) = 0,
    x(t; μ) = x₀(μ) + V q,   x₀(μ) = (w = 0, the other fields of x_ξ(μ)),

x_ξ⁰ the inverse problem's solution at the default parameters (the lung's ξ and Φs there).
The reduced inverse problem is solved by reduced Newton straight at μ from the nearest training
point's coordinates, continuing in μ only where it fails (:func:`lungmech.fem.start.approach`);
its tangent V_ξᵀ K_ξ V_ξ is not symmetric, since R_ξ is no gradient
(:mod:`lungmech.fem.placement`), and is factorised by LU.
The breath then starts at q = 0, the image itself: its deformed volume is the image's at every
μ, and the reference volume ∫ det(I + ∇ξ) dx is what moves with μ.

:class:`ReducedImage` is that start (the :class:`lungmech.fem.start.Start` of a
:class:`~lungmech.rom.reduced.ReducedModel` of an image's motion), :func:`snapshots` the
training of both bases from one pass of the full model's solves
(:class:`~lungmech.fem.inverse_motion.InverseMotion` starts). The reductor
(:mod:`lungmech.rom.reductor`) makes both.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, cast

from mpi4py import MPI

import numpy as np
from dolfinx import fem

from lungmech.errors import ParameterError, SolverError
from lungmech.fem.inverse_motion import Handover, InverseMotion
from lungmech.fem.quantities import Probe
from lungmech.fem.sensitivity import Moved, reduced_state_derivatives, value_derivatives
from lungmech.fem.solver import NewtonOptions, NewtonSolver, StepReport
from lungmech.fem.start import Progress, StartReport, approach
from lungmech.parallel.layout import layout
from lungmech.parallel.linalg import gram
from lungmech.parallel.owned import owned_size
from lungmech.rom import body, load_paths, shaped
from lungmech.rom.basis import Basis, dual, origin
from lungmech.rom.body import cells_of
from lungmech.rom.ecsw import Sample
from lungmech.rom.ecsw_training import Training
from lungmech.rom.exact import Cubic, cubic
from lungmech.rom.galerkin import ReducedSolver
from lungmech.rom.hyper_reduced import HyperReducedSolver
from lungmech.rom.load_paths import LoadPath, Paths
from lungmech.rom.outputs import OnPoints, imposed_directions
from lungmech.rom.pod import pod
from lungmech.rom.whole import OnMesh, Stored, Whole

if TYPE_CHECKING:
    from lungmech.fem.model import Model
    from lungmech.fem.parametric import FullOrderModel, Step

__all__ = ["ImagedSnapshots", "ReducedImage", "snapshots"]


@dataclass(frozen=True)
class ImagedSnapshots:
    """The training of a reduced imaged body (owned rows): ``motion``, the breath's states minus
    their start x₀(μ), one column per accepted step; ``inverse``, the inverse problem's
    solutions minus ``inverse_start`` (x_ξ⁰, at the defaults), one column per training point;
    ``start``, the breath's start x₀ at the defaults (a full local array)."""

    motion: np.ndarray
    inverse: np.ndarray
    inverse_start: np.ndarray
    start: np.ndarray


def snapshots(
    full: FullOrderModel,
    runs: Sequence[tuple[Mapping[str, float], float | Sequence[float]]],
    paths: Paths | None = None,
) -> ImagedSnapshots:
    """The snapshots of both unknowns from ``full``'s solves (an :class:`InverseMotion` start)
    at the defaults (here) and at each (parameter point, load scale) of ``runs``, solved by
    ``paths`` (default: one after another on ``full``; an ensemble's:
    :mod:`lungmech.app.training_paths`). The model is left at its start, at the default
    parameters. Collective."""
    start = full.start
    if not isinstance(start, InverseMotion):
        raise ParameterError("imaged snapshots need a full model started by InverseMotion")
    model, inverse = full.model, start.inverse
    starts: list[np.ndarray] = []  # [x₀ at the defaults, x_ξ⁰]

    def first(step: Step) -> None:
        if step.phase == "start":
            starts[:] = [model.state.x.array.copy(), inverse.state.x.array.copy()]

    full.solve(times=[full.stepping.start], on_step=first)  # at the defaults: both starts
    motion_start, inverse_start = starts
    solved = (paths or load_paths.serial(full, motion_start))(runs, False)
    solutions = [_from_defaults(inverse, path, inverse_start, full.stepping.start) for path in solved]
    full.reset()
    model.set_time(full.stepping.start)
    motion = np.hstack([path.snapshots for path in solved])
    return ImagedSnapshots(motion, np.column_stack(solutions), inverse_start, motion_start)


def _from_defaults(inverse: Model, path: LoadPath, inverse_start: np.ndarray, time: float) -> np.ndarray:
    """The inverse problem's solution of ``path`` minus its solution at the defaults x_ξ⁰, with
    the imposed displacements of the path's μ at t₀ (as online): one column, owned rows."""
    assert path.inverse is not None  # (an imaged body's path)
    inverse.set_parameters(path.solution.parameters)
    inverse.set_time(time)
    return path.inverse - origin(inverse, inverse_start)[: path.inverse.size]


def bases(
    full: FullOrderModel,
    trained: ImagedSnapshots,
    runs: Sequence[tuple[Mapping[str, float], float | Sequence[float]]],
    inner: str,
    size: int,
) -> tuple[Basis, Basis, list[tuple[Mapping[str, float], np.ndarray]]]:
    """The breath's every POD direction, the inverse motion's POD basis of at most ``size``
    vectors, and each training run's point with its coordinates in that basis (where a reduced
    inverse solve near it starts), from the snapshots of :func:`snapshots`. Collective."""
    start = full.start
    assert isinstance(start, InverseMotion)  # (snapshots needs it)
    comm = full.model.geometry.mesh.comm
    if comm.allreduce(float(np.abs(trained.inverse).max(initial=0.0)), op=MPI.MAX) == 0.0:
        raise ParameterError(
            "every training point has the unloaded reference of the defaults (no parameter reaches the imaged "
            "state): one reference serves them all; start the full model from it (an Equilibrium start)"
        )
    source = {"training": [dict(point) for point, _ in runs]}
    modes = pod(full.model, trained.motion, inner=inner, source=source)
    inverse = pod(start.inverse, trained.inverse, inner=inner, source=source)
    inverse = inverse.truncate(min(size, inverse.size))
    coordinates = gram(dual(start.inverse, inverse), trained.inverse, comm)
    return modes, inverse, [(point, coordinates[:, i]) for i, (point, _) in enumerate(runs)]


def ecsw_training(
    full: FullOrderModel,
    breath: Training,
    basis: Basis,
    runs: Sequence[tuple[Mapping[str, float], float | Sequence[float]]],
) -> Training:
    """ECSW's training of an imaged body from one more pass of ``full``'s solves at ``runs``:
    every Newton iterate of the breath into ``breath``, and of the inverse motion into the
    training returned (on its ``basis``; its residual alone: its answer is ξ, not outputs).
    The tangents at each run's first load step of each problem: spread over the box, as a
    replay's are (one at every step costs k assemblies and a compression each). Collective."""
    start = full.start
    assert isinstance(start, InverseMotion)  # (an imaged body's full model)
    inverse = Training(start.inverse, basis.vectors, outputs=False)
    fresh = {"breath": True, "inverse": True}

    def first(problem: str) -> Callable[[], bool]:
        return lambda: fresh.pop(problem, False)

    try:
        with (
            breath.watching(cast(NewtonSolver, full.solver), first("breath")),
            inverse.watching(start.solver, first("inverse")),
        ):
            for point, scale in runs:
                fresh.update(breath=True, inverse=True)
                full.solve(point, scale=scale)
    except BaseException:
        inverse.destroy()
        raise
    return inverse


class ReducedImage:
    """The start of a reduced model of an image's motion (``model``, ``Image.motion``): at μ,
    the reduced inverse problem on ``basis`` (relative to ``start``, x_ξ⁰, a full local array
    of the inverse problem's state), then the breath's start x₀(μ) = (0, its other fields) and
    ξ(μ) in the breath's forms. With an ECSW ``sample`` of the inverse problem (trained on
    ``basis``) the inverse problem is hyper-reduced. ``known``: parameter points with their
    coordinates a (the training's projected solutions): each solve starts from the nearest in
    the unit box, the defaults' a = 0 among them. ``newton``: the reduced Newton settings
    (full steps or a backtracking on ‖r‖, never an energy's line search). ``body``: the body's
    name in messages. It is also the breath's :class:`~lungmech.rom.outputs.Reference`: the
    reference volume, a cubic in the reduced coordinates, and ξ at probe points, both of the
    whole body (``whole``, :mod:`lungmech.rom.whole`: computed on ``model``'s mesh by default,
    given back from a model file on a body of sampled cells). Collective."""

    kind = "imaged"
    refuses_sensitivities: str | None = None

    def __init__(
        self,
        model: Model,
        basis: Basis,
        start: np.ndarray,
        newton: NewtonOptions | None = None,
        body: str = "body",
        sample: Sample | None = None,
        known: Sequence[tuple[Mapping[str, float], np.ndarray]] = (),
        whole: Whole | None = None,
    ) -> None:
        image = model.image
        if image is None or image.unknown != "motion":
            raise ParameterError(
                "ReducedImage starts a model of an image's motion (Model(..., image=Image.motion(t0)))"
            )
        self.image, self.body, self.basis, self.start = image, body, basis, np.array(start, dtype=float)
        self.inverse = inverse = model.variant(replace(image, unknown="inverse"))
        self.whole = whole if whole is not None else OnMesh(imposed_directions(inverse, self.start))
        self.solver: ReducedSolver | HyperReducedSolver = (
            ReducedSolver(inverse, basis, newton, start=self.start)
            if sample is None
            else HyperReducedSolver(inverse, basis, sample, newton, self.start, whole=self.whole)
        )
        # x_ξ = r + Z z, z = (a, the imposed factors): the reference volume is a cubic in z (and
        # in the shape coefficients with them, on a template: lungmech.rom.shaped)
        self._r, imposed, self._constraints = self.whole.imposed()
        self._directions = np.hstack([basis.vectors, imposed[: basis.vectors.shape[0]]])

        def volume() -> tuple[np.ndarray, ...]:
            at_rest = fem.Constant(model.geometry.mesh, 1.0) * inverse.dx
            if inverse.shape is None:
                return cubic(inverse, at_rest, self._r, self._directions).arrays()
            return shaped.volume(inverse, at_rest, self._r, self._directions).arrays()

        self._volume = Cubic.of(self.whole.get("reference_volume", volume))
        # the image's volume (m³, m³/m in 2-D; the whole body's on a body): on a template, a cubic in a
        self._imaged_volume: Callable[[], float]
        if model.shape is None:
            fixed = model.geometry.volume()
            self._imaged_volume = lambda: fixed
        else:
            imaged = Cubic.of(self.whole.get("imaged_volume", lambda: shaped.mesh_volume(model).arrays()))
            self._imaged_volume = lambda: imaged(self._shape())
        self._a = np.zeros(basis.size)  # the reduced inverse problem's solution now
        self.placed_at: dict[str, float] | None = None  # the parameters of the last placement
        box = inverse.parameters
        self._known = [(dict(box.defaults), np.zeros(basis.size))]
        self._known += [(box.values(point), np.array(a, dtype=float)) for point, a in known]
        self._handover = Handover(model, inverse)
        self._derivative: tuple[np.ndarray, np.ndarray] | None = None  # (dz/dμ, dx_ξ/dμ) once asked

    def reset(self, model: Model) -> None:
        """The breath's model at its start at the default parameters: ξ(defaults), the image."""
        self.placed_at = None
        self.inverse.set_parameters(self.inverse.parameters.defaults)
        self._solved(np.zeros(self.basis.size))
        model.set_parameters(model.parameters.defaults)
        self._handover.hand_over(self.inverse, model)

    def place(
        self,
        model: Model,
        solver: ReducedSolver | HyperReducedSolver,
        values: Mapping[str, float],
        time: float,
        progress: Progress | None = None,
        on_step: Callable[[StepReport], None] | None = None,
    ) -> StartReport:
        """ξ(μ) for ``values`` from the reduced inverse problem at ``time`` = t₀, and ``solver``
        (the breath's reduced solver) at its start there, q = 0 (collective)."""
        self.image.check_start(time, self.body)
        inverse, reduced = self.inverse, self.solver
        nearest, a = self._nearest(values)

        def at(point: Mapping[str, float]) -> None:  # the inverse problem at ``point``, from the nearest's a
            inverse.set_parameters(point)
            inverse.set_time(time)
            if isinstance(reduced, HyperReducedSolver):
                reduced.set_state(a.copy())
            else:
                reduced.reconstruct(a)

        self.placed_at, self._derivative = None, None
        try:
            at(values)  # reduced Newton straight at μ (a continuation's first step would be a Newton step more)
            result = reduced.solve()
            iterations = result.iterations
            if not result.converged:  # continuing in μ from the nearest known point
                at(nearest)
                iterations += approach(inverse, reduced, values, nearest, time, first_step=0.5)
        except SolverError as error:
            raise SolverError(
                f"reduced inverse motion: no unloaded reference of the {self.body} at these parameters ({error})"
            ) from None
        if isinstance(reduced, HyperReducedSolver):
            self._solved(reduced.state.copy())  # the inverse problem's full state: O(the mesh's dofs · k)
        else:
            self._a = reduced.project()
        model.set_parameters(values)
        self._handover.hand_over(inverse, model)
        model.set_time(time)
        solver.set_start(model.state.x.array)  # and q = 0 there: the image
        self.placed_at = dict(values)
        details = {
            "newton_iterations": iterations,
            "imaged_volume": self.volume,
            "reference_volume": self.reference_volume(),
        }
        description = f"the imaged {self.body} (its unloaded reference from the reduced inverse motion at μ)"
        return StartReport("imaged", description, iterations, details)

    @property
    def volume(self) -> float:
        """The image's volume (m³; m³/m in 2-D): on a template, at the shape a now."""
        return self._imaged_volume()

    def reference_volume(self) -> float:
        """∫ det(I + ∇ξ) dx of the reference now (m³; m³/m in 2-D), from its cubic."""
        return self._volume(np.concatenate([self._coordinates(), self._shape()]))

    def _shape(self) -> np.ndarray:
        """The inverse problem's shape coefficients a now (none without a shape map)."""
        return np.zeros(0) if self.inverse.shape is None else self.inverse.shape.values()

    def moved(self, model: Model) -> Moved:
        """dξ/dμ and the image's other fields' d/dμ at the last placement, from the reduced
        inverse problem's own sensitivities:
        da/dμ = −(V_ξᵀ K_ξ V_ξ)⁻¹ V_ξᵀ (∂R_ξ/∂μ + K_ξ dx_ξ⁰/dμ) (Galerkin, or on its sample),
        and dx_ξ/dμ = Z dz/dμ with z = (a, the imposed factors). Once per placement. Collective."""
        if self._derivative is None:
            inverse, reduced = self.inverse, self.solver
            if isinstance(reduced, HyperReducedSolver):
                own = value_derivatives(inverse, update=reduced.update_coefficients)
                da = reduced.sensitivities.state(own)
            else:
                own = value_derivatives(inverse)
                da = reduced_state_derivatives(inverse, self.basis.vectors, reduced.jacobian_form, own)
            dz = np.vstack([da, own.amplitudes[self._constraints]])
            self._derivative = (dz, self._directions @ dz)
        return self._handover.moved(self.inverse, self._derivative[1])

    def reference_map_at(self, probe: Callable[[], Probe]) -> OnPoints:
        """ξ at the points of ``probe()`` (points, 3; m) now, linear in z, and its derivative
        at the last placement: k + 2 evaluations on the whole body (``probe`` is called only
        there)."""
        inverse, owned = self.inverse, self._directions.shape[0]

        def located() -> tuple[np.ndarray, ...]:
            at = probe()

            def reference_map(x: np.ndarray) -> np.ndarray:
                inverse.state.x.array[:] = x
                inverse.state.x.scatter_forward()
                return -at(inverse.displacement())  # u = −ξ in the inverse problem

            with inverse.kept_state():
                at_r = reference_map(self._r)
                each = []
                for column in self._directions.T:
                    x = np.zeros_like(self._r)
                    x[:owned] = column
                    each.append(reference_map(x))
            return at_r, np.stack(each, axis=-1)

        at_r, columns = self.whole.get("reference_probes", located)
        return OnPoints(lambda: at_r + columns @ self._coordinates(), lambda: columns @ self._dz())

    def _dz(self) -> np.ndarray:
        """dz/dμ at the last placement (:meth:`derivatives` computes it)."""
        if self._derivative is None:
            raise ParameterError("the reference's derivatives are asked before they were computed (derivatives)")
        return self._derivative[0]

    def _nearest(self, values: Mapping[str, float]) -> tuple[dict[str, float], np.ndarray]:
        """The known point nearest ``values`` in the unit box, and its coordinates (a copy)."""
        box = self.inverse.parameters
        if not len(box):
            return self._known[0][0], self._known[0][1].copy()
        target = box.to_unit(values)
        point, a = min(self._known, key=lambda known: float(np.linalg.norm(box.to_unit(known[0]) - target)))
        return point, a.copy()

    def _coordinates(self) -> np.ndarray:
        """z = (a, the imposed factors of the inverse problem's constraints now)."""
        return np.concatenate([self._a, self.inverse.imposed_amplitudes()[self._constraints]])

    def _solved(self, a: np.ndarray) -> None:
        """The inverse problem's state x_ξ⁰ + V_ξ a, as a full field (for the hand-over)."""
        self._a = np.array(a, dtype=float)
        self.solver.reconstruct(self._a)


# A reduced image in a model file (:mod:`lungmech.rom.store`): its arrays, canonical and
# gathered on rank 0, are named image/… (its basis, values and start; its ECSW sample
# image_ecsw/…; what its whole body gives, image_whole/…); its record holds the training points'
# coordinates; on a body of sampled cells (:mod:`lungmech.rom.body`) its columns are body/image_….
PREFIX = "image/"


def exported(image: ReducedImage) -> tuple[dict, dict[str, np.ndarray | None]]:
    """(record, arrays) of ``image`` for a model file (arrays on rank 0; collective)."""
    model, owned = image.inverse, image.basis.vectors.shape[0]
    where = layout(model.space)
    arrays: dict[str, np.ndarray | None] = {
        PREFIX + "basis": where.gather(image.basis.vectors),
        PREFIX + "values": image.basis.values,
        PREFIX + "start": where.gather(image.start[:owned]),
    }
    sample = image.solver.sample if isinstance(image.solver, HyperReducedSolver) else None
    if sample is not None:
        arrays |= {f"image_ecsw/{name}": data for name, data in sample.export(model.geometry.mesh).items()}
        assert isinstance(image.whole, OnMesh)  # (built on the full model)
        arrays |= {f"image_whole/{name}": data for name, data in image.whole.arrays().items()}
    record = {
        "body": image.body,
        "inner": image.basis.inner_product,
        "tolerance": None if sample is None else sample.tolerance,
        "known": [[dict(point), a.tolist()] for point, a in image._known[1:]],
    }
    return record, arrays


def body_columns(image: ReducedImage) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The cells a body must hold for ``image``'s sample (local) and its columns there (owned
    rows, by name)."""
    assert isinstance(image.solver, HyperReducedSolver)  # (a body is a hyper-reduced model's)
    owned = image.basis.vectors.shape[0]
    reference, imposed, _ = image.whole.imposed()
    columns = {"basis": image.basis.vectors, "start": image.start[:owned], "reference": reference[:owned]}
    columns |= {"imposed": imposed[:owned]}
    return cells_of(image.solver.sample), {f"image_{name}": values for name, values in columns.items()}


def placed(
    model: Model,
    record: dict,
    arrays: Mapping[str, np.ndarray | None],
    newton: NewtonOptions | None,
    source: str,
    on_body: bool = False,
) -> ReducedImage:
    """The reduced image a model file holds (``record``, ``arrays`` on rank 0), on ``model``: the
    full model's mesh, or with ``on_body`` a body of the sampled cells (collective)."""
    comm, space = model.geometry.mesh.comm, model.space
    owned = owned_size(space)
    values = comm.bcast(arrays[PREFIX + "values"])
    data = comm.bcast({n[len("image_ecsw/") :]: a for n, a in arrays.items() if n.startswith("image_ecsw/")})
    whole = None
    if on_body:
        local = {
            name: body.place(space, arrays, f"image_{name}") for name in ("basis", "start", "reference", "imposed")
        }
        vectors, start = local["basis"][:owned], local["start"][:, 0]
        operators = comm.bcast({n[len("image_whole/") :]: a for n, a in arrays.items() if n.startswith("image_whole/")})
        whole = Stored(operators, local["reference"][:, 0], local["imposed"], source)
        cells = comm.bcast(arrays[body.PREFIX + "cells"])  # the body's cells: a sample's are positions in it
        data = {name: np.searchsorted(cells, a) if name.endswith("_cells") else a for name, a in data.items()}
    else:
        where = layout(space)
        vectors = where.scatter(arrays[PREFIX + "basis"])
        function = fem.Function(space)
        function.x.array[:owned] = where.scatter(arrays[PREFIX + "start"])
        function.x.scatter_forward()
        start = function.x.array.copy()
    basis = Basis(np.ascontiguousarray(vectors), values, "pod", record["inner"], layout(space).fingerprint)
    sample = Sample.place(model.geometry.mesh, data, record["tolerance"]) if record["tolerance"] is not None else None
    known = [(point, np.asarray(a, dtype=float)) for point, a in record["known"]]
    return ReducedImage(model, basis, start, newton, record["body"], sample, known, whole)
