"""Elastodynamics: exact modal responses and implicit Euler as incremental energy minimisation.

Modal dynamics. For M-orthonormal modes (K φ = λ ρM φ, φᵀ ρM φ = 1) a linear model decouples
into z'' + λ z = f(t), one equation per mode, f = φᵀ F. For f linear in time on each interval
[t_n, t_n + h], f = f_n + s τ, the Duhamel integral has a closed form (``modal_response``):

    z_{n+1} = c z_n + S₁ v_n + C₂ f_n + C₃ s,    v_{n+1} = −λ S₁ z_n + c v_n + S₁ f_n + C₂ s,

with c = cos ωh, S₁ = sin ωh / ω, C₂ = (1 − cos ωh)/λ, C₃ = (h − S₁)/λ. All four are entire
functions of λh², evaluated by their series near 0: so λ = 0 (a rigid mode, z = f t²/2 from
rest) and λ < 0 (an unstable mode: cosh, sinh) need no special case.

Implicit Euler. Each step minimises the incremental potential

    ½ ‖x − x̃‖²_ρM / h² + Π(x) + ½ (x − x_n)ᵀ C (x − x_n) / h,    x̃ = x_n + h v_n,

with Rayleigh damping C = a ρM + b K₀ (K₀: the stored energy's Hessian at rest), then
v_{n+1} = (x_{n+1} − x_n)/h. Its stationarity condition is the model's residual plus

    ρ/h² (u − u_n − h v_n)·δu dX + a ρ/h (u − u_n)·δu dX + b/h K₀(u − u_n, δu),

so the same Newton solver (full, :class:`lungmech.fem.solver.NewtonSolver`, or reduced,
:class:`lungmech.rom.galerkin.ReducedSolver`, made by :func:`lungmech.rom.galerkin.reduced_solver`) solves a static step and a dynamic one. On a
linear model each mode follows (1 + h(a + bλ) + h²λ) z_{n+1} = (1 + h(a + bλ)) z_n + h v_n + h² f_{n+1}:
unconditionally stable, first-order accurate, and dissipative (the discrete energy never grows).
"""

from __future__ import annotations

import math
import numbers
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, TypeGuard

from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem

from lungmech import jit
from lungmech.errors import ParameterError, SolverError
from lungmech.fem.solver import (
    NewtonOptions,
    NewtonResult,
    NewtonSolver,
    Solver,
    SolveReport,
    StepReport,
    steps_model_state,
)

if TYPE_CHECKING:
    from lungmech.fem.model import Model

__all__ = [
    "ImplicitEuler",
    "full_solver",
    "integrate",
    "march",
    "modal_response",
    "rest_stiffness",
]

# --- exact modal response ------------------------------------------------------------------------

_SERIES_TERMS = 12  # |λh²| ≤ 1: the first omitted term is below 1/24! ≈ 2e-24


def _propagator(eigenvalues: np.ndarray, steps: np.ndarray) -> tuple[np.ndarray, ...]:
    """(c, S₁, C₂, C₃) for every step (rows) and mode (columns).

    Written as functions of y = λh², c = Σ (−y)^k/(2k)!, S₁ = h Σ (−y)^k/(2k+1)!,
    C₂ = h² Σ (−y)^k/(2k+2)!, C₃ = h³ Σ (−y)^k/(2k+3)!: the series where |y| ≤ 1 (no
    cancellation in 1 − cos or h − sin/ω), trigonometric or hyperbolic closed forms elsewhere.
    """
    h = steps[:, None] * np.ones_like(eigenvalues)[None, :]
    y = eigenvalues[None, :] * h**2
    small = np.abs(y) <= 1.0
    series = np.zeros((4, *y.shape))
    term = np.ones_like(y)  # (−y)^k / (2k)!, then divided on to (2k+1)!, (2k+2)!, (2k+3)!
    for k in range(_SERIES_TERMS):
        if k:
            term = term * (-y) / ((2 * k - 1) * (2 * k))
        series[0] += term
        series[1] += term / (2 * k + 1)
        series[2] += term / ((2 * k + 1) * (2 * k + 2))
        series[3] += term / ((2 * k + 1) * (2 * k + 2) * (2 * k + 3))
    c, s1, c2, c3 = series[0], h * series[1], h**2 * series[2], h**3 * series[3]

    for positive in (True, False):
        mask = ~small & ((y > 0) if positive else (y < 0))
        if not mask.any():
            continue
        r, hm = np.sqrt(np.abs(y[mask])), h[mask]
        if positive:  # ωh = r
            cr, sr = np.cos(r), np.sin(r)
            c[mask], s1[mask] = cr, hm * sr / r
            c2[mask] = hm**2 * 2 * np.sin(r / 2) ** 2 / r**2
            c3[mask] = hm**3 * (r - sr) / r**3
        else:  # an unstable mode, λ = −μ², μh = r
            cr, sr = np.cosh(r), np.sinh(r)
            c[mask], s1[mask] = cr, hm * sr / r
            c2[mask] = hm**2 * 2 * np.sinh(r / 2) ** 2 / r**2
            c3[mask] = hm**3 * (sr - r) / r**3
    return c, s1, c2, c3


def modal_response(
    eigenvalues: Sequence[float] | np.ndarray,
    times: Sequence[float] | np.ndarray,
    forces: Sequence[Sequence[float]] | np.ndarray,
    z0: Sequence[float] | np.ndarray | None = None,
    v0: Sequence[float] | np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact z and ż of z'' + λ z = f(t), mode by mode, at the sample ``times``.

    ``forces`` (shape (len(times), k)) are the modal forces at the sample times; between two
    samples f is taken linear, and within that assumption the result is exact (no time
    integration error): a reference for time-stepping schemes, and the response of a modal
    reduced model. Any real λ is allowed (λ = 0: rigid mode, λ < 0: unstable mode). Returns
    ``(z, v)``, each of shape (len(times), k), starting from ``z0`` and ``v0`` (default 0) at
    ``times[0]``.
    """
    lam = np.atleast_1d(np.asarray(eigenvalues, dtype=float))
    t = np.atleast_1d(np.asarray(times, dtype=float))
    if lam.ndim != 1 or lam.size == 0 or not np.all(np.isfinite(lam)):
        raise ParameterError("modal_response: eigenvalues must be a non-empty 1-D array of finite numbers")
    k = lam.size
    if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)):
        raise ParameterError("modal_response: times must be a non-empty 1-D array of finite numbers")
    if np.any(np.diff(t) <= 0):
        raise ParameterError("modal_response: times must increase strictly")
    f = np.asarray(forces, dtype=float)
    if f.ndim == 1 and k == 1:
        f = f[:, None]
    if f.shape != (t.size, k):
        raise ParameterError(
            f"modal_response: forces must have shape (len(times), modes) = ({t.size}, {k}) (got {f.shape})"
        )
    if not np.all(np.isfinite(f)):
        raise ParameterError("modal_response: forces must be finite")
    start = []
    for name, value in (("z0", z0), ("v0", v0)):
        array = np.zeros(k) if value is None else np.asarray(value, dtype=float).reshape(-1)
        if array.shape != (k,) or not np.all(np.isfinite(array)):
            raise ParameterError(f"modal_response: {name} must hold one finite value per mode ({k})")
        start.append(array)

    z, v = np.empty((t.size, k)), np.empty((t.size, k))
    z[0], v[0] = start
    if t.size == 1:
        return z, v
    h = np.diff(t)
    c, s1, c2, c3 = _propagator(lam, h)
    slope = np.diff(f, axis=0) / h[:, None]
    for n in range(t.size - 1):
        z[n + 1] = c[n] * z[n] + s1[n] * v[n] + c2[n] * f[n] + c3[n] * slope[n]
        v[n + 1] = -lam * s1[n] * z[n] + c[n] * v[n] + s1[n] * f[n] + c2[n] * slope[n]
    return z, v


# --- implicit Euler --------------------------------------------------------------------------------


def rest_stiffness(model: Model) -> ufl.Form:
    """K₀: the second variation of the stored energy ∫ψ dX at rest (u = 0), a bilinear form.

    This is the stiffness of Rayleigh damping C = a M + b K₀. It is the Hessian of the stored
    energy only, frozen at the unloaded state: load stiffnesses (follower pressures) depend on
    the load value and would make the damping change with time, and the current tangent would
    make it change with the state, which is not Rayleigh damping.
    """
    _require_displacement_only(model)
    rest = fem.Function(model.space, name="rest")  # u = 0: the unloaded displacement-only state
    stored = model.energy_density * model.dx
    hessian = ufl.derivative(
        ufl.derivative(stored, model.state, ufl.TestFunction(model.space)),
        model.state,
        ufl.TrialFunction(model.space),
    )
    return ufl.replace(hessian, {model.state: rest})


class ImplicitEuler:
    """One implicit Euler step as the minimiser of the incremental potential (module docstring).

    Holds the previous displacement u_n (``previous``) and velocity v_n (``velocity``), both
    ``fem.Function`` objects of the model's space, and the forms ``residual`` and ``jacobian`` a
    Newton solver is built with. The start is the model's current state and time, at rest
    unless ``velocity`` is set before the first step. Density, step and damping live in
    ``fem.Constant`` objects, so schemes that differ only in those share their compiled kernels.

    Args:
        model: a displacement-only :class:`lungmech.fem.model.Model` (the mixed formulations have
            no mass for their extra fields; they are refused).
        density: ρ, mass per unit reference volume.
        step: the time step h.
        rayleigh: (a, b), damping C = a ρM + b K₀; a term that is 0 is left out of the forms.
    """

    def __init__(self, model: Model, density: float, step: float, rayleigh: tuple[float, float] = (0.0, 0.0)) -> None:
        _require_displacement_only(model)
        _positive("density", density)
        _positive("step", step)
        try:
            pair = tuple(rayleigh)
        except TypeError:
            pair = ()
        if len(pair) != 2:
            raise ParameterError(f"rayleigh must be a pair (a, b) of damping coefficients (got {rayleigh!r})")
        for name, value in zip(("a (mass-proportional)", "b (stiffness-proportional)"), pair):
            if not (_real(value) and math.isfinite(value) and value >= 0):
                raise ParameterError(
                    f"Rayleigh damping coefficient {name} must be a finite number >= 0 (got {value!r})"
                )
        self.model = model
        self.density, self.step = float(density), float(step)
        self.rayleigh = (float(pair[0]), float(pair[1]))
        self.time = float(model.time)

        mesh = model.geometry.mesh
        self.previous = model.state.copy()
        self.previous.name = "previous displacement"
        self.velocity = fem.Function(model.space, name="velocity")
        rho, h = fem.Constant(mesh, self.density), fem.Constant(mesh, self.step)
        a, b = fem.Constant(mesh, self.rayleigh[0]), fem.Constant(mesh, self.rayleigh[1])
        # The consistent mass, integrated exactly as in lungmech.fem.modal.mass_matrix (not with the
        # law's quadrature, which may under-integrate it), so the modes decouple the steps.
        dx = ufl.dx(domain=mesh)
        u, test = model.u, ufl.TestFunction(model.space)
        increment = u - self.previous
        residual = model.residual + rho / h**2 * ufl.inner(increment - h * self.velocity, test) * dx
        if self.rayleigh[0] > 0:
            residual += a * rho / h * ufl.inner(increment, test) * dx
        if self.rayleigh[1] > 0:
            stiffness = rest_stiffness(model)
            residual += b / h * (ufl.action(stiffness, model.state) - ufl.action(stiffness, self.previous))
        self.residual = residual
        self.jacobian = ufl.derivative(residual, model.state, ufl.TrialFunction(model.space))
        self._kinetic = jit.form(0.5 * rho * ufl.inner(self.velocity, self.velocity) * dx)

    def advance(self, solver: Solver) -> NewtonResult:
        """One step from t to t + h with ``solver`` (built on ``residual`` and ``jacobian``).

        Loads and imposed displacements take their values at t + h; Newton starts from the
        inertial prediction x̃ = x_n + h v_n. On success u_n, v_n and the time move on; on a
        failure the model is put back at (x_n, t), as the static solver does.
        """
        model, state = self.model, self.model.state.x
        target = self.time + self.step
        model.set_time(target)
        state.array[:] = self.previous.x.array + self.step * self.velocity.x.array
        state.scatter_forward()
        result = solver.solve()
        if result.converged:
            self.velocity.x.array[:] = (state.array - self.previous.x.array) / self.step
            self.previous.x.array[:] = state.array
            self.velocity.x.scatter_forward()
            self.previous.x.scatter_forward()
            self.time = target
        else:
            state.array[:] = self.previous.x.array
            state.scatter_forward()
            model.set_time(self.time)
        return result

    def kinetic_energy(self) -> float:
        """½ ∫ ρ v_n·v_n dX over all ranks."""
        comm = self.model.geometry.mesh.comm
        return comm.allreduce(fem.assemble_scalar(self._kinetic), op=MPI.SUM)

    def set_velocity(self, velocity: fem.Function | Callable[[np.ndarray], np.ndarray]) -> None:
        """Set v_n from a Function of the model's space or a callable of the coordinates (3, n)."""
        if isinstance(velocity, fem.Function):
            if velocity.function_space != self.model.space:
                raise ParameterError("the initial velocity must be a Function of the model's space")
            self.velocity.x.array[:] = velocity.x.array
        elif callable(velocity):
            self.velocity.interpolate(velocity)
        else:
            raise ParameterError(f"velocity must be a Function or a callable (got {type(velocity).__name__})")
        self.velocity.x.scatter_forward()


SolverFactory = Callable[[ImplicitEuler], Solver]


def full_solver(options: NewtonOptions | None = None) -> SolverFactory:
    """A factory of full-order Newton solvers on a scheme's forms (the default of ``integrate``).

    Without ``options``, Newton uses the critical-point line search: the residual is the
    gradient of the incremental potential, and "cp" looks for the zero of its directional
    derivative. The static default "bt" judges a step by ‖R‖ instead, which the first Newton
    step of a slender body from rest multiplies by 10³ (the axial residual of a pure bending
    guess), so it cuts the step again and again and stalls.
    """
    options = options or NewtonOptions(line_search="cp")
    return lambda scheme: NewtonSolver(scheme.model, options, residual=scheme.residual, jacobian=scheme.jacobian)


def march(
    scheme: ImplicitEuler,
    solver: Solver,
    steps: int,
    on_step: Callable[[ImplicitEuler, StepReport], None] | None = None,
) -> SolveReport:
    """``steps`` implicit Euler steps of fixed size; ``on_step(scheme, report)`` after each.

    The step is never cut: a different h is a different discrete dynamics. A failed step
    raises :class:`SolverError` with the model left at the last converged state.
    """
    if not (isinstance(steps, numbers.Integral) and not isinstance(steps, bool) and steps >= 0):
        raise ParameterError(f"the number of steps must be an integer >= 0 (got {steps!r})")
    report = SolveReport()
    started = time.perf_counter()
    for _ in range(steps):
        tic = time.perf_counter()
        result = scheme.advance(solver)
        converged, residuals = result.converged, result.residuals
        step = StepReport(
            scheme.time + (0.0 if converged else scheme.step),
            scheme.step,
            result.iterations,
            residuals,
            result.reason,
            time.perf_counter() - tic,
            converged,
        )
        report.steps.append(step)
        if not converged:
            report.seconds = time.perf_counter() - started
            history = ", ".join(f"{r:.3e}" for r in residuals[-6:]) or "none"
            raise SolverError(
                f"implicit Euler: Newton did not converge from t = {scheme.time:.6g} with step "
                f"{scheme.step:.3g} (reason {result.reason}; last residual norms: {history}). The state at "
                f"t = {scheme.time:.6g} is kept. Try a smaller step or check the loads."
            )
        if on_step is not None:
            on_step(scheme, step)
    report.seconds = time.perf_counter() - started
    return report


def integrate(
    model: Model,
    density: float,
    step: float,
    steps: int,
    *,
    rayleigh: tuple[float, float] = (0.0, 0.0),
    velocity: fem.Function | Callable[[np.ndarray], np.ndarray] | None = None,
    solver_factory: SolverFactory | None = None,
    on_step: Callable[[ImplicitEuler, StepReport], None] | None = None,
) -> tuple[ImplicitEuler, SolveReport]:
    """Implicit Euler from the model's current state and time, ``steps`` steps of size ``step``.

    ``velocity`` is the initial velocity (default: at rest). ``solver_factory(scheme)`` builds
    the solver (default :func:`full_solver`; :func:`reduced_solver` for a reduced model); the
    solver is destroyed at the end. Returns the scheme (final u_n, v_n, time) and the report.
    """
    scheme = ImplicitEuler(model, density, step, rayleigh)
    if velocity is not None:
        scheme.set_velocity(velocity)
    solver = (solver_factory or full_solver())(scheme)
    if not steps_model_state(solver):
        raise ParameterError(
            f"integrate steps the model's state; this solver ({solver.description}) iterates on reduced "
            "coordinates (a hyper-reduced solver is for static load paths)"
        )
    try:
        report = march(scheme, solver, steps, on_step)
    finally:
        if hasattr(solver, "destroy"):
            solver.destroy()
    return scheme, report


# --- checks ----------------------------------------------------------------------------------------


def _require_displacement_only(model: Model) -> None:
    if model.multi_field:
        raise ParameterError(
            "dynamics needs the displacement formulation: the extra fields of a multi-field model have "
            "no inertia, and implicit Euler for the constrained system is not implemented"
        )


def _real(value: object) -> TypeGuard[float]:  # a real number, as float stands for one in type hints
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _positive(name: str, value: object) -> None:
    if not (_real(value) and math.isfinite(value) and value > 0):
        raise ParameterError(f"dynamics: {name} must be a finite number > 0 (got {value!r})")
