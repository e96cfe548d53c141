"""Adaptive load stepping: drive a model from ``stepping.start`` to ``stepping.end`` with Newton.

A step that fails (no convergence, a NaN, a linear-solver breakdown) is undone: the last
converged state is restored and the step is cut. Easy steps make the next one longer. Below the
minimum step the solve stops with a :class:`SolverError` that says where and why. An unconverged
state is never returned as a result. Each step starts from a prediction
(:mod:`lungmech.fem.prediction`); the first step's length comes from the tangent."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np

from lungmech import checks
from lungmech.errors import Interrupted, ParameterError, SolverError
from lungmech.fem import limits
from lungmech.fem.newton import NewtonSolver
from lungmech.fem.prediction import Path
from lungmech.fem.solver_interface import Solver
from lungmech.fem.solver_options import NewtonOptions

if TYPE_CHECKING:
    from lungmech.fem.model import Model

__all__ = ["FIRST_STRAIN_INCREMENT", "SolveReport", "StepReport", "Stepping", "first_step", "solve"]

log = logging.getLogger("lungmech")


@dataclass(frozen=True)
class Stepping:
    """Adaptive pseudo-time stepping from ``start`` to ``end``.

    Steps grow by ``growth`` after a Newton solve of at most ``easy_iterations`` iterations and
    are halved after a failure; ``times`` (and every ramp breakpoint) are hit exactly, so outputs
    can be requested there. ``initial_step`` None (the default) chooses the first step from the
    tangent: the first interval, shortened until one linear solve predicts a displacement-gradient
    increment of at most :data:`FIRST_STRAIN_INCREMENT` anywhere.
    """

    end: float = 1.0
    start: float = 0.0
    initial_step: float | None = None
    min_step: float = 1e-5
    max_step: float = 1.0
    growth: float = 1.5
    easy_iterations: int = 5
    times: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        for name in ("end", "start", "min_step", "growth"):
            checks.real(name, getattr(self, name))
        if self.initial_step is not None:
            checks.real("initial_step", self.initial_step)
        checks.real("max_step", self.max_step, infinite=True)
        checks.integer("easy_iterations", self.easy_iterations, minimum=0)
        if not isinstance(self.times, tuple):
            raise ParameterError(f"times must be a list of output times (got {self.times!r})")
        object.__setattr__(self, "times", tuple(checks.real(f"times[{i}]", t) for i, t in enumerate(self.times)))
        if not self.end > self.start:
            raise ParameterError(f"end ({self.end}) must be after start ({self.start})")
        if outside := [t for t in self.times if not self.start < t <= self.end]:
            raise ParameterError(
                f"times {outside} lie outside (start, end] = ({self.start:g}, {self.end:g}]: "
                "outputs can only be asked for inside the run"
            )
        if (
            not 0
            < self.min_step
            <= (self.min_step if self.initial_step is None else self.initial_step)
            <= self.max_step
        ):
            given = "automatic" if self.initial_step is None else f"{self.initial_step:g}"
            raise ParameterError(
                f"need 0 < min_step <= initial_step <= max_step (got {self.min_step:g}, {given}, {self.max_step:g})"
            )
        if not self.growth >= 1:
            raise ParameterError(f"growth must be >= 1 (got {self.growth:g})")


@dataclass(frozen=True)
class StepReport:
    time: float
    step: float
    iterations: int
    residuals: tuple[float, ...]
    reason: str
    seconds: float
    converged: bool


@dataclass
class SolveReport:
    """Every attempted step, accepted or not, and the totals."""

    steps: list[StepReport] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def accepted(self) -> list[StepReport]:
        return [s for s in self.steps if s.converged]

    @property
    def newton_iterations(self) -> int:
        return sum(s.iterations for s in self.steps)

    @property
    def failures(self) -> int:
        return sum(not s.converged for s in self.steps)


def solve(
    model: Model,
    stepping: Stepping | None = None,
    options: NewtonOptions | None = None,
    on_step: Callable[[StepReport], None] | None = None,
    solver: Solver | None = None,
    drive: Callable[[float], None] | None = None,
    monitor: Callable[[StepReport], None] | None = None,
    breakpoints: Sequence[float] | None = None,
) -> SolveReport:
    """Drive ``model`` from ``stepping.start`` to ``stepping.end`` with adaptive steps.

    ``on_step`` is called after every accepted step (outputs, P–V curves, snapshots), and
    ``monitor`` after every attempt, accepted or cut back (default: a log line). Pass a
    ``solver`` to reuse its compiled forms across calls. The stepped variable is the time,
    unless ``drive(s)`` is given to apply it otherwise (e.g. as a load factor). Steps land on
    ``breakpoints`` (default: the model's ramp breakpoints, unless ``drive`` is given). Raises
    :class:`SolverError` when a step below ``stepping.min_step`` still fails; the model then
    holds the last converged state. The path starts from the solver's state (:attr:`Solver.state`)
    and ends there: a hyper-reduced solver iterates on q and writes the model's state only when
    asked (``update_model()``), so that no step touches the full mesh.
    """
    stepping = stepping or Stepping()
    solver = solver or NewtonSolver(model, options)
    if breakpoints is None:
        breakpoints = model.breakpoints if drive is None else []
    drive = drive or model.set_time
    targets = sorted({t for t in (*stepping.times, *breakpoints, stepping.end) if stepping.start < t <= stepping.end})
    report = SolveReport()
    started = time.perf_counter()

    t = stepping.start
    drive(t)
    first = solver.state.copy()  # where the load path starts (for a diagnosis of where it ends)
    solver.start_path()
    dt, rate = stepping.initial_step, None
    if dt is None:
        dt, rate = first_step(model, solver, drive, t, min(stepping.max_step, targets[0] - t), stepping.min_step)
    kinks = [b for b in breakpoints if stepping.start < b < stepping.end]
    path = Path(t, solver.state)
    for target in targets:
        while t < target - 1e-12 * (stepping.end - stepping.start):
            dt = min(dt, stepping.max_step, target - t)
            drive(t + dt)
            tic = time.perf_counter()
            prediction, linear_solves = path.predict(t + dt, solver, rate)
            result = solver.solve(start=prediction)
            converged = result.converged
            step = StepReport(
                t + dt,
                dt,
                linear_solves + result.iterations,
                result.residuals,
                result.reason,
                time.perf_counter() - tic,
                converged,
            )
            report.steps.append(step)
            (monitor or _log_step)(step)
            if converged:
                t += dt
                rate = None  # the tangent at the start predicts the first step only
                if any(abs(t - kink) <= 1e-12 * (stepping.end - stepping.start) for kink in kinks):
                    path = Path(t, solver.state)  # the load turns here: extrapolating across it would mislead
                else:
                    path.append(t, solver.state)
                if on_step is not None:
                    on_step(step)
                if step.iterations <= stepping.easy_iterations:
                    dt *= stepping.growth
                continue
            final = dt <= stepping.min_step * (1 + 1e-12)
            if final:  # the diagnosis judges full states, each at its own loads
                solver.update_model()
                smallest_J = limits.min_jacobian(model)()  # of the failed iterate
                drive(stepping.start)
                solver.set_state(first)
                solver.update_model()
                began = model.state.x.array.copy()
            solver.set_state(path.last)
            if final:
                drive(t)
                solver.update_model()
                cause = limits.diagnose(model, solver, drive, t, (began, stepping.start), smallest_J, t + dt)
                report.seconds = time.perf_counter() - started
                raise SolverError(_failure_message(t, dt, step, cause, getattr(solver, "options", None)))
            dt = max(dt / 2, stepping.min_step)
    report.seconds = time.perf_counter() - started
    return report


FIRST_STRAIN_INCREMENT = 0.1  # the largest |ΔF| the tangent may predict for an automatic first step


def first_step(
    model: Model, solver: Solver, drive: Callable[[float], None], t: float, interval: float, min_step: float
) -> tuple[float, np.ndarray | None]:
    """The first step from t, and the tangent's rate of change of the state there.

    The step is ``interval``, shortened to interval · s/|ΔF|_max when one linear solve of the
    tangent at the start state predicts a displacement-gradient increment |ΔF|_max (Frobenius, at
    the quadrature points) above s = FIRST_STRAIN_INCREMENT. Newton converges from the linearised
    response of small strain increments; the estimate is conservative for stiffening laws. The
    rate Δx/interval (None if the tangent was singular) predicts the first step's state: the loads
    are linear in t within the interval, so the tangent's response is too. The state and the loads
    are left as they were."""
    rate = None
    before, start = solver.deformation_gradient(), solver.state.copy()
    drive(t + interval)
    try:
        solver.linear_step()
        change = np.linalg.norm(solver.deformation_gradient() - before, axis=(-2, -1))
        local = float(change.max()) if change.size else 0.0
        if not np.isfinite(change).all():
            local = np.inf
        rate = (solver.state - start) / interval
    except PETSc.Error:  # a singular tangent at the start: no estimate, the stepping adapts
        Interrupted.raise_pending()  # or a Ctrl-C that arrived inside a PETSc callback
        local = 0.0
    finally:
        solver.set_state(start)
        drive(t)
    largest = model.geometry.mesh.comm.allreduce(local, op=MPI.MAX)
    if not np.isfinite(largest) or model.geometry.mesh.comm.allreduce(rate is None, op=MPI.LOR):
        rate = None
    if largest <= FIRST_STRAIN_INCREMENT:
        return interval, rate
    return max(min_step, interval * FIRST_STRAIN_INCREMENT / largest), rate


def _log_step(step: StepReport) -> None:
    status = "ok" if step.converged else f"not converged ({step.reason}): step cut back"
    log.info(
        "t = %.6g s  dt = %.3g s  Newton %2d  %.2f s  %s", step.time, step.step, step.iterations, step.seconds, status
    )


def _failure_message(t: float, dt: float, step: StepReport, cause: str, options: NewtonOptions | None = None) -> str:
    where = f"the load path stopped at t = {t:.6g} s"
    if cause:
        return (
            f"{where}: {cause}. Newton could not take even the minimum step ({dt:.3g} s) beyond it "
            f"({step.reason}). The last converged state, at t = {t:.6g} s, is kept."
        )
    linear = {k: v for k, v in (options.petsc_options if options else {}).items() if k.startswith(("ksp_", "pc_"))}
    if linear:  # the user's linear solver, not the body, is then the first suspect
        shown = ", ".join(f"{k} = {v!r}" for k, v in linear.items())
        return (
            f"{where}: Newton did not converge even at the minimum step ({dt:.3g} s; {step.reason}) with the linear "
            f"solver that solver.petsc_options set ({shown}): a linear solver that does not solve Newton's systems "
            "accurately enough is the likely cause; leave these options out to use lungmech's own. The last "
            "converged state is kept."
        )
    return (
        f"{where}: the minimum step ({dt:.3g} s) was reached and Newton still did not converge ({step.reason}). "
        "The last converged state is kept. Try a smaller min_step or another line search, or check the loads "
        "and material parameters."
    )
