"""Elastodynamics: the exact modal response against closed forms, implicit Euler against it.

A linear model decouples into modes, so every full-order or reduced implicit Euler run has an
independent per-mode reference: the scalar recurrence
(1 + h(a + bλ) + h²λ) z_{n+1} = (1 + h(a + bλ)) z_n + h v_n + h² f,
and the exact solution of z'' + λ z = f from :func:`modal_response`.
"""

from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import fem, la
from scipy.integrate import solve_ivp

from lungmech.errors import ParameterError, SolverError
from lungmech.fem.constraints import clamp
from lungmech.fem.dynamics import (
    ImplicitEuler,
    full_solver,
    integrate,
    modal_response,
    rest_stiffness,
)
from lungmech.fem.loads import Traction
from lungmech.fem.materials import LinearElastic, NeoHookean
from lungmech.fem.modal import mass_matrix, modal_analysis
from lungmech.fem.model import Model
from lungmech.fem.quantities import Probe, integral, strain_energy
from lungmech.fem.ramp import Ramp
from lungmech.fem.solver import NewtonOptions
from lungmech.mesh import box
from lungmech.parallel.owned import owned_size
from lungmech.rom import modal_basis, pod, reduced_solver

LENGTH, WIDTH, THICKNESS = 10.0, 0.6, 0.4  # a flat section: bending in z is the single softest mode
TIP = [[LENGTH, WIDTH / 2, THICKNESS / 2]]


def beam(comm=MPI.COMM_WORLD, law=None, traction=(0.0, 0.0, -1e-3), cells=(20, 2, 2)) -> Model:
    """A clamped P2 cantilever under a tip traction applied suddenly at t = 0 (constant ramp)."""
    geometry = box(comm, lengths=(LENGTH, WIDTH, THICKNESS), cells=cells)
    loads = [Traction("x1", traction, ramp=Ramp.constant())] if np.any(traction) else []
    return Model(geometry, law or LinearElastic.from_young(1.0, 0.0), degree=2, constraints=[clamp("x0")], loads=loads)


class Modal:
    """Modes of a linear model and the maps full state -> modal coordinates and loads -> modal forces."""

    def __init__(self, model: Model, count: int, density: float):
        modes = modal_analysis(model, count, density=density)
        self.eigenvalues, self.vectors = modes.eigenvalues, modes.vectors
        M = mass_matrix(model, density)
        self.weighted = [M * phi.x.petsc_vec for phi in self.vectors]  # ρM φ_i
        M.destroy()
        self.model = model

    def coordinates(self, function: fem.Function) -> np.ndarray:
        """z_i = φ_iᵀ ρM u (global dot products)."""
        return np.array([function.x.petsc_vec.dot(w) for w in self.weighted])

    def forces(self) -> np.ndarray:
        return modal_forces(self.model, self.vectors)


def modal_forces(model: Model, vectors) -> np.ndarray:
    """f_i = φ_iᵀ F at the model's time: minus the residual of the unloaded state."""
    saved = model.state.x.array.copy()
    model.state.x.array[:] = 0.0
    residual = fem.Function(model.space)
    fem.assemble_vector(residual.x.array, fem.form(model.residual))
    residual.x.scatter_reverse(la.InsertMode.add)
    model.state.x.array[:] = saved
    return np.array([-residual.x.petsc_vec.dot(phi.x.petsc_vec) for phi in vectors])


def euler_recurrence(lam, h, steps, f, z0=0.0, v0=0.0, rayleigh=(0.0, 0.0)) -> np.ndarray:
    """Implicit Euler on z'' + (a + bλ) z' + λ z = f, mode by mode: z at every step."""
    lam = np.asarray(lam, dtype=float)
    c = rayleigh[0] + rayleigh[1] * lam
    z = np.broadcast_to(np.asarray(z0, dtype=float), lam.shape).copy()
    v = np.broadcast_to(np.asarray(v0, dtype=float), lam.shape).copy()
    history = [z.copy()]
    for _ in range(steps):
        new = ((1 + h * c) * z + h * v + h**2 * f) / (1 + h * c + h**2 * lam)
        v, z = (new - z) / h, new
        history.append(z.copy())
    return np.array(history)


# --- modal_response --------------------------------------------------------------------------------


def test_modal_response_step_force_and_free_mode_from_rest():
    lam = np.array([0.0, 0.3, 4.0, 250.0])  # a rigid mode, and ωh from well below to well above 1
    f0 = np.array([0.7, -1.1, 2.0, 0.5])
    times = np.sort(np.random.default_rng(1).uniform(0.0, 3.0, 40))
    times[0] = 0.0
    z, v = modal_response(lam, times, np.tile(f0, (times.size, 1)))
    t, w = times[:, None], np.sqrt(lam[1:])
    assert z[:, 0] == pytest.approx(f0[0] * times**2 / 2, rel=1e-13, abs=1e-14)
    assert v[:, 0] == pytest.approx(f0[0] * times, rel=1e-13, abs=1e-14)
    assert z[:, 1:] == pytest.approx(f0[1:] / lam[1:] * (1 - np.cos(w * t)), rel=1e-11, abs=1e-13)
    assert v[:, 1:] == pytest.approx(f0[1:] / w * np.sin(w * t), rel=1e-11, abs=1e-13)


def test_modal_response_ramp_with_initial_conditions():
    # rigid, soft (series branch: λh² ≪ 1), stable, stiff (ωh > 1) and unstable (λ < 0)
    lam = np.array([0.0, 1e-3, 0.5, 40.0, -2.0])
    slope = np.array([0.3, -0.7, -2.0, 1.5, 0.8])
    z0, v0 = np.array([0.1, -0.2, 0.2, -0.3, 0.05]), np.array([1.0, 0.3, -0.4, 0.0, 0.2])
    times = np.linspace(0.0, 2.5, 7)
    z, v = modal_response(lam, times, slope * times[:, None], z0, v0)
    t = times[:, None]
    w = np.sqrt(lam[1:].astype(complex))  # λ < 0: cos(iμt) = cosh(μt), the same formula
    s, a, b = slope[1:], z0[1:], v0[1:]
    exact_z = np.empty_like(z, dtype=complex)
    exact_v = np.empty_like(v, dtype=complex)
    exact_z[:, 1:] = s / lam[1:] * (t - np.sin(w * t) / w) + a * np.cos(w * t) + b * np.sin(w * t) / w
    exact_v[:, 1:] = s / lam[1:] * (1 - np.cos(w * t)) - a * w * np.sin(w * t) + b * np.cos(w * t)
    exact_z[:, 0] = z0[0] + v0[0] * times + slope[0] * times**3 / 6
    exact_v[:, 0] = v0[0] + slope[0] * times**2 / 2
    assert z == pytest.approx(exact_z.real, rel=1e-10, abs=1e-12)
    assert v == pytest.approx(exact_v.real, rel=1e-10, abs=1e-12)


def test_modal_response_is_exact_for_any_sampling_of_a_piecewise_linear_force():
    lam = np.array([0.0, 0.8, 30.0])
    knots = np.array([0.0, 0.4, 1.5, 1.7, 3.0])
    values = np.array([[0.0, 1.0, -2.0], [1.0, 0.5, 3.0], [-0.5, 2.0, 0.0], [2.0, -1.0, 1.0], [0.0, 0.0, 4.0]])
    z0, v0 = np.array([0.2, -0.1, 0.05]), np.array([0.0, 0.3, -1.0])

    def force(t):
        return np.array([np.interp(t, knots, values[:, i]) for i in range(lam.size)]).T

    coarse_z, coarse_v = modal_response(lam, knots, values, z0, v0)
    fine = np.union1d(knots, np.random.default_rng(7).uniform(0.0, 3.0, 57))
    fine_z, fine_v = modal_response(lam, fine, force(fine), z0, v0)
    at_knots = np.searchsorted(fine, knots)
    scale = np.abs(coarse_z).max(axis=0)
    assert np.all(np.abs(fine_z[at_knots] - coarse_z).max(axis=0) <= 1e-12 * scale)
    assert np.all(np.abs(fine_v[at_knots] - coarse_v).max(axis=0) <= 1e-12 * np.abs(coarse_v).max(axis=0))

    # an independent reference: a tight adaptive ODE integration, interval by interval
    for i in range(lam.size):
        state = [z0[i], v0[i]]
        for n in range(knots.size - 1):
            ode = solve_ivp(
                lambda t, y: [y[1], np.interp(t, knots, values[:, i]) - lam[i] * y[0]],
                knots[n : n + 2],
                state,
                rtol=1e-12,
                atol=1e-13,
                method="DOP853",
            )
            state = ode.y[:, -1]
            assert coarse_z[n + 1, i] == pytest.approx(state[0], rel=1e-8, abs=1e-10)
            assert coarse_v[n + 1, i] == pytest.approx(state[1], rel=1e-8, abs=1e-10)


def test_modal_response_errors():
    with pytest.raises(ParameterError, match="increase strictly"):
        modal_response([1.0], [0.0, 1.0, 1.0], np.zeros((3, 1)))
    with pytest.raises(ParameterError, match="shape"):
        modal_response([1.0, 2.0], [0.0, 1.0], np.zeros((2, 1)))
    with pytest.raises(ParameterError, match="eigenvalues"):
        modal_response([np.nan], [0.0, 1.0], np.zeros((2, 1)))
    with pytest.raises(ParameterError, match="z0"):
        modal_response([1.0], [0.0, 1.0], np.zeros((2, 1)), z0=[1.0, 2.0])


# --- implicit Euler, full order --------------------------------------------------------------------


@pytest.mark.slow
def test_implicit_euler_is_first_order_against_the_exact_modal_response():
    """Suddenly loaded beam: its first modal coordinate against the exact z = f/λ (1 − cos ωt)."""
    density = 1.5
    model = beam()
    modal = Modal(model, 1, density)
    lam, f = modal.eigenvalues[0], modal.forces()[0]
    horizon = np.pi / np.sqrt(lam)  # half a period: the first peak
    errors = []
    for steps in (20, 40, 80):
        model.reset()
        model.set_time(0.0)
        h = horizon / steps
        history = [0.0]
        integrate(model, density, h, steps, on_step=lambda scheme, _: history.append(modal.coordinates(model.state)[0]))
        history = np.array(history)
        times = np.linspace(0.0, horizon, steps + 1)
        exact, _ = modal_response([lam], times, np.full((steps + 1, 1), f))
        # The full-order run projects exactly onto the scalar recurrence (modes decouple)...
        recurrence = euler_recurrence(lam, h, steps, f)
        assert history == pytest.approx(recurrence, rel=1e-7, abs=1e-9 * np.abs(exact).max())
        errors.append(np.abs(history - exact[:, 0]).max() / np.abs(exact).max())
    # ...whose global error is first order in h.
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(orders >= 0.8), (errors, orders)
    assert errors[-1] < 0.05


@pytest.mark.slow
def test_rayleigh_damping_matches_the_modal_recurrence_and_dissipates():
    """Free vibration from an initial velocity: each mode follows the damped recurrence, and the
    energy decays at every step, faster with damping."""
    density = 1.0
    model = beam(traction=(0.0, 0.0, 0.0))
    modal = Modal(model, 3, density)
    lam = modal.eigenvalues
    h = 2 * np.pi / np.sqrt(lam[0]) / 24
    steps = 12
    v0 = fem.Function(model.space)
    v0.interpolate(lambda x: np.vstack([0 * x[0], 0.01 * (x[0] / LENGTH) ** 2, -0.02 * (x[0] / LENGTH) ** 2]))
    z_dot0 = modal.coordinates(v0)
    stored = strain_energy(model)
    omega = np.sqrt(lam[0])
    energies = {}
    for rayleigh in ((0.0, 0.0), (0.1 * omega, 0.0), (0.0, 0.1 / omega)):
        model.reset()
        model.set_time(0.0)
        history, energy = [np.zeros(lam.size)], []

        def record(scheme, _):
            history.append(modal.coordinates(model.state))
            energy.append(scheme.kinetic_energy() + stored())

        scheme, report = integrate(model, density, h, steps, rayleigh=rayleigh, velocity=v0, on_step=record)
        assert len(report.accepted) == steps and scheme.time == pytest.approx(steps * h)
        expected = euler_recurrence(lam, h, steps, 0.0, 0.0, z_dot0, rayleigh)
        scale = np.abs(expected).max()
        assert np.array(history) == pytest.approx(expected, abs=1e-7 * scale)
        initial = 0.5 * density * integral(ufl.inner(v0, v0) * ufl.dx, model.geometry.mesh.comm)()
        energies[rayleigh] = np.array([initial, *energy])
    undamped, *damped = energies.values()
    assert np.all(np.diff(undamped) < 0)  # implicit Euler alone is dissipative
    for curve in damped:
        assert np.all(np.diff(curve) < 0)
        assert np.all(curve[1:] < undamped[1:])  # and damping takes more


def test_rest_stiffness_is_the_hessian_at_rest_whatever_the_state():
    model = beam(law=NeoHookean.from_young(1.0, 0.3), cells=(4, 1, 1))
    w = fem.Function(model.space)
    w.interpolate(lambda x: np.vstack([np.sin(x[0]), x[1] * x[2], np.cos(x[1])]))

    def apply(form) -> np.ndarray:
        vector = fem.Function(model.space)
        fem.assemble_vector(vector.x.array, fem.form(ufl.action(form, w)))
        vector.x.scatter_reverse(la.InsertMode.add)
        return vector.x.array.copy()

    at_rest = apply(model.jacobian)  # no follower loads: the model's tangent at u = 0
    model.state.interpolate(lambda x: np.vstack([0.1 * x[0] ** 2 / LENGTH, 0 * x[0], -0.05 * x[0]]))
    scale = np.abs(at_rest).max()
    assert apply(rest_stiffness(model)) == pytest.approx(at_rest, rel=1e-12, abs=1e-12 * scale)
    assert np.abs(apply(model.jacobian) - at_rest).max() > 1e-3 * scale  # the tangent moved


def test_nonlinear_implicit_euler_converges_and_matches_the_linear_limit():
    """A neo-Hookean beam: a large load converges with damping; a tiny load moves like the linear beam."""
    density, steps = 1.0, 4
    h = 2 * np.pi / np.sqrt(modal_analysis(beam(cells=(10, 2, 2)), 1, density).eigenvalues[0]) / 16
    law = NeoHookean.from_young(1.0, 0.0)  # ν = 0 : the same small-strain limit as LinearElastic(1, 0)
    model = beam(law=law, traction=(0.0, 0.0, -4e-5), cells=(10, 2, 2))
    tips = []
    probe = Probe(model.geometry.mesh, TIP)
    scheme, report = integrate(
        model, density, h, steps, rayleigh=(1e-3, 1.0), on_step=lambda s, r: tips.append(probe(model.state)[0, 2])
    )
    assert all(s.converged for s in report.steps) and len(report.steps) == steps
    assert max(s.iterations for s in report.steps) >= 3  # genuinely nonlinear
    assert tips[-1] < -0.5  # a large deflection: 5 % of the length and more

    def small_load_tip(law) -> np.ndarray:
        model = beam(law=law, traction=(0.0, 0.0, -1e-7), cells=(10, 2, 2))  # a 1e-4 L deflection
        history = []
        integrate(model, density, h, steps, on_step=lambda s, r: history.append(probe(model.state)[0]))
        return np.array(history)

    nonlinear, linear = small_load_tip(law), small_load_tip(LinearElastic.from_young(1.0, 0.0))
    assert np.abs(linear[:, 2]).max() > 1e-4  # the comparison is not empty
    assert nonlinear == pytest.approx(linear, rel=1e-3, abs=1e-3 * np.abs(linear).max())


def test_a_failed_step_raises_and_keeps_the_last_state():
    model = beam(law=NeoHookean.from_young(1.0, 0.3), traction=(0.0, 0.0, -1e-4), cells=(6, 1, 1))
    with pytest.raises(SolverError, match="implicit Euler"):
        integrate(model, 1.0, 200.0, 3, solver_factory=full_solver(NewtonOptions(max_iterations=1)))
    assert np.all(model.state.x.array == 0.0) and model.time == 0.0


# --- reduced implicit Euler ------------------------------------------------------------------------


def test_reduced_implicit_euler_on_the_modal_basis_is_the_modal_recurrence():
    """Galerkin on k modes: each mode steps alone with the damped recurrence, also with ρ ≠ 1."""
    density, rayleigh, steps = 2.0, (2e-3, 0.5), 10
    model = beam(traction=(0.0, 2e-4, -1e-3))
    basis = modal_basis(model, 4, density)
    phis = basis.vectors / np.sqrt(density)  # ρM-orthonormal mode shapes (owned rows)
    lam = basis.values
    vectors = [fem.Function(model.space) for _ in range(basis.size)]
    owned = phis.shape[0]
    for phi, column in zip(vectors, phis.T):
        phi.x.array[:owned] = column
        phi.x.scatter_forward()
    f = modal_forces(model, vectors)
    assert np.all(np.abs(f) > 1e-6 * np.abs(f).max())  # every mode is loaded
    h = 2 * np.pi / np.sqrt(lam[0]) / 20
    states = []
    integrate(
        model,
        density,
        h,
        steps,
        rayleigh=rayleigh,
        solver_factory=reduced_solver(basis),
        on_step=lambda s, r: states.append(model.state.x.array[:owned].copy()),
    )
    z = euler_recurrence(lam, h, steps, f, rayleigh=rayleigh)
    expected = z[1:] @ phis.T
    assert np.array(states) == pytest.approx(expected, abs=1e-8 * np.abs(expected).max())


def test_reduced_implicit_euler_on_the_pod_of_the_trajectory_is_the_full_one():
    density, rayleigh, steps = 1.0, (1e-3, 0.2), 12
    model = beam(traction=(0.0, 1e-4, -1e-3))
    h = 2 * np.pi / np.sqrt(modal_analysis(model, 1, density).eigenvalues[0]) / 30
    owned = owned_size(model.space)
    full, reduced = [], []
    integrate(
        model,
        density,
        h,
        steps,
        rayleigh=rayleigh,
        on_step=lambda s, r: full.append(model.state.x.array[:owned].copy()),
    )
    basis = pod(model, np.column_stack(full), inner="l2")
    assert 1 < basis.size <= steps
    model.reset()
    model.set_time(0.0)
    integrate(
        model,
        density,
        h,
        steps,
        rayleigh=rayleigh,
        solver_factory=reduced_solver(basis),
        on_step=lambda s, r: reduced.append(model.state.x.array[:owned].copy()),
    )
    full = np.array(full)
    assert np.array(reduced) == pytest.approx(full, abs=1e-6 * np.abs(full).max())
    # and a basis that misses part of the trajectory does not reproduce it
    model.reset()
    model.set_time(0.0)
    truncated = []
    integrate(
        model,
        density,
        h,
        steps,
        rayleigh=rayleigh,
        solver_factory=reduced_solver(basis.truncate(1)),
        on_step=lambda s, r: truncated.append(model.state.x.array[:owned].copy()),
    )
    assert np.abs(np.array(truncated) - full).max() > 1e-3 * np.abs(full).max()


# --- inputs ----------------------------------------------------------------------------------------


def test_input_errors():
    model = beam(MPI.COMM_SELF, cells=(2, 1, 1))
    for bad in (0.0, -1.0, np.nan, np.inf, "1", True):
        with pytest.raises(ParameterError, match="density"):
            ImplicitEuler(model, bad, 1.0)
        with pytest.raises(ParameterError, match="step"):
            ImplicitEuler(model, 1.0, bad)
    for bad in ((-1.0, 0.0), (0.0, -1e-3), (np.nan, 0.0), (0.0, np.inf)):
        with pytest.raises(ParameterError, match="Rayleigh"):
            ImplicitEuler(model, 1.0, 1.0, rayleigh=bad)
    for bad in ((1.0,), 1.0, (0.0, 0.0, 0.0)):
        with pytest.raises(ParameterError, match="pair"):
            ImplicitEuler(model, 1.0, 1.0, rayleigh=bad)
    with pytest.raises(ParameterError, match="number of steps"):
        integrate(model, 1.0, 1.0, -1)
    with pytest.raises(ParameterError, match="velocity"):
        integrate(model, 1.0, 1.0, 1, velocity=3.0)
    mixed = Model(box(MPI.COMM_SELF, cells=(1, 1, 1)), NeoHookean.from_young(1.0, 0.3), degree=2, mixed=True)
    with pytest.raises(ParameterError, match="displacement formulation"):
        ImplicitEuler(mixed, 1.0, 1.0)


# --- MPI -------------------------------------------------------------------------------------------


def _damped_run(comm, reduced: bool) -> np.ndarray:
    """Tip displacement and velocity and the kinetic energy after a few damped steps."""
    density, steps = 1.3, 5
    model = beam(comm, traction=(0.0, 1e-6, -1e-5), cells=(10, 2, 2))
    factory = reduced_solver(modal_basis(model, 4, density)) if reduced else None
    scheme, _ = integrate(model, density, 40.0, steps, rayleigh=(1e-3, 0.5), solver_factory=factory)
    probe = Probe(model.geometry.mesh, TIP)
    tip = [probe(model.state).ravel(), probe(scheme.velocity).ravel()]
    return np.concatenate([*tip, [scheme.kinetic_energy()]])


@pytest.mark.mpi
@pytest.mark.parametrize("reduced", [False, True], ids=["full", "reduced"])
def test_implicit_euler_same_on_all_ranks_as_on_one(reduced):
    parallel, serial = _damped_run(MPI.COMM_WORLD, reduced), _damped_run(MPI.COMM_SELF, reduced)
    assert np.abs(serial).min() > 0
    assert np.allclose(parallel, serial, rtol=1e-8, atol=1e-10 * np.abs(serial).max())
