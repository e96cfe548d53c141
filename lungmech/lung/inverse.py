"""The inverse problem: the unloaded reference configuration of an imaged, loaded body.

A lung is imaged under load (at end-expiration the pleural pressure already pulls on it).
Given that geometry x̂ and the loads at the imaging time, find the reference X whose deformed
configuration X + u(X) is x̂. We use the backward-displacement fixed point (Sellier 2011;
Bols et al. 2013): from X_0 = x̂, solve the direct problem on X_k and correct the reference by
the mismatch, X_{k+1} = X_k + ω_k (x̂ − X_k − u_k), with Aitken's dynamic relaxation ω_k
(Küttler & Wall 2008). Every iteration is a direct solve with the model's own forms — the
mesh nodes move, nothing is recompiled — started from the previous iteration's displacement.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from time import perf_counter
from typing import TYPE_CHECKING

from mpi4py import MPI

import numpy as np

from lungmech import checks
from lungmech.errors import ParameterError, SolverError
from lungmech.fem.quantities import integral
from lungmech.fem.solver import NewtonOptions, NewtonSolver, Solver, Stepping, StepReport, solve
from lungmech.fem.start import Progress, StartReport
from lungmech.mesh import nodes as mesh_nodes

if TYPE_CHECKING:
    from lungmech.fem.model import Model
    from lungmech.fem.sensitivity import Moved
    from lungmech.lung.poromechanics import ImagedPorosity


@dataclass
class InverseReport:
    """Mismatch after each iteration — max |X + u − x̂| / size, or the imaged porosity's max
    |φf − φ̂f| where that is larger — and the totals."""

    mismatch: list[float] = field(default_factory=list)
    porosity: list[float] = field(default_factory=list)  # max |φf − φ̂f| (with an imaged porosity)
    newton_iterations: int = 0
    seconds: float = 0.0

    @property
    def iterations(self) -> int:
        return len(self.mismatch)


def node_displacements(model: Model) -> Callable[[], np.ndarray]:
    """A function that returns u at the mesh's geometry nodes (owned and ghost), shape (nodes, 3)."""
    sample = mesh_nodes.sampler(model.geometry.mesh)
    return lambda: sample(model.displacement())


@dataclass(frozen=True)
class InverseOptions:
    """Stop when max |X + u − x̂| ≤ ``tolerance`` × the body's size, or fail after ``max_iterations``."""

    tolerance: float = 1e-9
    max_iterations: int = 50

    def __post_init__(self) -> None:
        checks.real("tolerance", self.tolerance)
        if not 0 < self.tolerance < 1:
            raise ParameterError(f"tolerance must lie in (0, 1) (got {self.tolerance})")
        if isinstance(self.max_iterations, bool) or not (
            isinstance(self.max_iterations, int) and self.max_iterations >= 1
        ):
            raise ParameterError(f"max_iterations must be a positive integer (got {self.max_iterations!r})")


def unloaded_reference(
    model: Model,
    time: float = 0.0,
    options: InverseOptions = InverseOptions(),
    stepping: Stepping | None = None,
    newton: NewtonOptions | None = None,
    solver: Solver | None = None,
    monitor: Callable[[InverseReport], None] | None = None,
    imaged: ImagedPorosity | None = None,
) -> InverseReport:
    """Move ``model``'s mesh from the imaged (loaded at ``time``) geometry to the unloaded reference.

    On return the mesh holds the reference X and ``model.state`` the loaded state at ``time``,
    whose nodes X + u match the imaged ones to ``options.tolerance`` × the body's size. A lung
    given its imaged porosity (``Poromechanics(imaged_porosity=...)``) has its reference solid
    fraction Φs0 found with X, each iteration correcting both, until the loaded porosity matches
    the imaged one to ``options.tolerance`` as well (see
    :class:`lungmech.lung.poromechanics.ImagedPorosity`). ``stepping``
    raises the loads of ``time`` from zero (a load factor from 0 to 1) for the first direct solve;
    imposed displacements keep their values at ``time``. ``monitor(report)`` is called after
    every iteration (progress). ``imaged``: the data matched besides the geometry, made once by
    the caller (default: the formulation's ``imaged(model)``, made anew). Raises
    :class:`SolverError` when the iteration does not converge.
    """
    tic = perf_counter()
    mesh = model.geometry.mesh
    gdim, comm = mesh.geometry.dim, mesh.comm
    nodes = mesh.geometry.x[:, :gdim].copy()  # imaged
    owned = mesh.geometry.index_map().size_local
    size = model.geometry.size
    displacement = node_displacements(model)
    solver = solver or NewtonSolver(model, newton)
    report = InverseReport()
    if imaged is None:  # data beside the geometry
        imaged = getattr(model.formulation, "imaged", lambda model: None)(model)

    def dot(a: np.ndarray, b: np.ndarray) -> float:
        return comm.allreduce(float(a @ b), op=MPI.SUM)

    model.reset()  # first direct solve: the loads of ``time``, raised from zero
    first = solve(
        model,
        stepping or Stepping(initial_step=0.25),
        solver=solver,
        drive=lambda s: model.set_time(time, s),
        monitor=None if monitor is None else lambda step: None,
    )
    report.newton_iterations += first.newton_iterations
    raising = stepping or Stepping(initial_step=0.25)
    relaxation, previous = 1.0, None
    while True:
        residual = nodes - mesh.geometry.x[:, :gdim] - displacement()
        worst = comm.allreduce(float(np.abs(residual[:owned]).max(initial=0.0)), op=MPI.MAX) / size
        # The fixed point's step, relative: node moves per size, and ln Φs0 where imaged data adds it.
        step = np.concatenate([residual[:owned].ravel() / size, imaged.correction() if imaged else []])
        if imaged is not None:
            report.porosity.append(imaged.mismatch())
            worst = max(worst, report.porosity[-1])
        report.mismatch.append(worst)
        if monitor is not None:
            monitor(report)
        if worst <= options.tolerance:
            break
        if report.iterations >= options.max_iterations:
            raise SolverError(
                f"inverse: no unloaded reference within {options.max_iterations} iterations (mismatch "
                f"{worst:.2e} of the body's size, asked {options.tolerance:.0e}); the loads may be too large "
                "for the material, or the imaged geometry is not a deformed state of it"
            )
        if previous is not None:  # Aitken: the relaxation that would have cancelled the last change
            change = step - previous
            relaxation = -relaxation * dot(previous, change) / dot(change, change)
        if imaged is not None:
            imaged.apply(relaxation * step[residual[:owned].size :])
        mesh_nodes.move(mesh, relaxation * residual)
        previous = step
        model.set_time(time)
        report.newton_iterations += _direct(model, solver, time, raising)
    report.seconds = perf_counter() - tic
    return report


def _direct(model: Model, solver: Solver, time: float, stepping: Stepping) -> int:
    """The direct problem on the corrected reference: Newton from the last state, or, when the
    correction was too large for that (a soft material), the loads raised again from zero."""
    result = solver.solve()
    if result.converged:
        return result.iterations
    model.reset()
    try:
        again = solve(
            model, stepping, solver=solver, drive=lambda s: model.set_time(time, s), monitor=lambda step: None
        )
    except SolverError as error:
        raise SolverError(
            f"inverse: the direct solve on the corrected reference failed ({result.reason}), and so did raising "
            f"the loads again on it ({error})"
        ) from None
    model.set_time(time)
    return result.iterations + again.newton_iterations


class Imaged:
    """The start of an imaged body (a scene with [inverse]): its mesh is the loaded state at the
    start time *for every μ*. :meth:`place` puts the nodes back at the imaged positions (and
    imaged data's unknowns, Φs0 of an imaged porosity, at their first guess), sets μ and finds
    the unloaded reference at μ (:func:`unloaded_reference`): the mesh then holds X(μ), the state
    the equilibrium whose deformed nodes are the imaged ones. The answer at μ is a function of μ
    alone: no solve depends on the one before. Built on the imaged mesh, before any move."""

    kind = "imaged"
    refuses_sensitivities: str | None = (  # here the reference is the mesh's nodes, which no sensitivity follows
        "sensitivities of an imaged body follow its reference on the fixed image (the inverse motion: "
        "FullOrderModel(..., start=InverseMotion(model)) on a model of Image.motion), not the moving mesh"
    )

    def __init__(self, model: Model, options: InverseOptions = InverseOptions(), body: str = "body") -> None:
        mesh = model.geometry.mesh
        self.nodes = mesh.geometry.x[:, : mesh.geometry.dim].copy()
        self._volume = integral(model.mesh_volume(), mesh.comm)  # compiled once (on a template, at its shape)
        self.volume = self._volume()  # m³ (m³/m in 2-D), of the image at the current parameters
        self.options, self.body = options, body
        self._data = getattr(model.formulation, "imaged", lambda model: None)(model)  # beside the geometry

    def reset(self, model: Model) -> None:
        """The imaged mesh, unloaded (u = 0) at the default parameters."""
        mesh_nodes.place(model.geometry.mesh, self.nodes)
        if self._data is not None:
            self._data.reset()
        model.set_parameters(model.parameters.defaults)
        model.reset()

    def place(
        self,
        model: Model,
        solver: Solver,
        values: Mapping[str, float],
        time: float,
        progress: Progress | None = None,
        on_step: Callable[[StepReport], None] | None = None,
    ) -> StartReport:
        """The unloaded reference at ``values`` and the imaged state on it (collective)."""
        self.reset(model)
        model.set_parameters(values)
        self.volume = self._volume()  # the image's (at these parameters' shape, on a template)
        tolerance, most = self.options.tolerance, self.options.max_iterations

        def show(report: InverseReport) -> None:
            assert progress is not None  # the monitor only with a progress
            first, mismatch = report.mismatch[0], report.mismatch[-1]
            done = np.log(first / max(mismatch, tolerance)) / np.log(first / tolerance) if first > tolerance else 1.0
            progress(
                float(done),
                f"iteration {report.iterations}/{most}: mismatch {mismatch:.2e} of the {self.body}'s size "
                f"(target {tolerance:.0e})",
            )

        report = unloaded_reference(
            model, time, self.options, solver=solver, monitor=show if progress else None, imaged=self._data
        )
        details = {
            "iterations": report.iterations,
            "mismatch": report.mismatch,
            "newton_iterations": report.newton_iterations,
            "seconds": report.seconds,
            "imaged_volume": self.volume,
            "reference_volume": self._volume(),
        } | ({"porosity_mismatch": report.porosity} if report.porosity else {})
        return StartReport(
            "imaged",
            f"the imaged {self.body} (its unloaded reference found for these parameters in {report.iterations} "
            "iterations)",
            report.newton_iterations,
            details,
        )

    def moved(self, model: Model) -> Moved | None:
        """Refused (:attr:`refuses_sensitivities`)."""
        raise ParameterError(self.refuses_sensitivities)
