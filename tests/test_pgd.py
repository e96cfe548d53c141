"""The a priori PGD (lungmech.pgd): parameter axes, a linear model's separated terms, and the
greedy decomposition against the full model at random points of the box."""

from __future__ import annotations

from mpi4py import MPI

import numpy as np
import pytest

from lungmech.errors import ParameterError
from lungmech.fem.constraints import Displacement, clamp
from lungmech.fem.laws import LinearElastic
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.newton import NewtonSolver
from lungmech.fem.parameters import Parameter, Parameters
from lungmech.fem.ramp import Ramp
from lungmech.fem.solver_options import NewtonOptions
from lungmech.fem.stepping import Stepping, solve
from lungmech.lung.gravity import Gravity
from lungmech.mesh import box
from lungmech.parallel.linalg import norms
from lungmech.parallel.owned import owned_size
from lungmech.pgd import Axis, Options, pgd, separated_terms
from lungmech.pgd.axes import horner
from lungmech.pgd.indicator import effectivity, indicator
from lungmech.rom.basis import inner_product

STIFFNESS = Parameter("E", "material.E", 3.0, (1.0, 10.0), log=True)  # Pa, a factor 10
PITCH = Parameter("pitch", "loads.gravity.pitch", 0.0, (-180.0, 180.0))  # degrees, a full turn
ROLL = Parameter("roll", "loads.gravity.roll", 0.0, (-30.0, 30.0))


def beam(parameters, comm=MPI.COMM_WORLD, cells=(8, 3, 3), law=None, constraints=None, balanced=()) -> Model:
    """A linear elastic beam 2 × 0.5 × 0.5 m clamped at x = 0 under its own weight (1 kg/m³,
    9.81 m/s² along −z before the posture turns it)."""
    model = Model(
        box(comm, cells=cells, lengths=(2.0, 0.5, 0.5)),
        law or (lambda c: LinearElastic.from_young(c["E"], 0.3)),
        constraints=constraints or [clamp("x0")],
        loads=[Gravity(1.0, (0.0, 0.0, -9.81), balanced_on=balanced, name="gravity", ramp=Ramp.constant())],
        parameters=parameters,
    )
    model.set_time(1.0)
    return model


def full_solution(model: Model, point: dict, solver: NewtonSolver) -> np.ndarray:
    """The full model's own answer at ``point`` (its Newton solver, to round-off)."""
    model.set_parameters(point)
    model.reset()
    solve(model, Stepping(start=0.0, end=1.0, max_step=1.0), solver=solver, monitor=lambda r: None)
    return model.state.x.array[: owned_size(model.space)].copy()


def relative_errors(model: Model, decomposition, points: list[dict]) -> np.ndarray:
    """‖u_PGD − u‖_E / ‖u‖_E at each of ``points``, E the energy product at the defaults (E(μ)
    scales both norms alike)."""
    comm, found = model.geometry.mesh.comm, []
    W = inner_product(model, "energy")
    solver = NewtonSolver(model, NewtonOptions(rtol=1e-13, atol=1e-16))
    for point in points:
        u = full_solution(model, point, solver)
        e = decomposition.state(point) - u
        found.append(float(norms(e[:, None], W, comm)[0] / norms(u[:, None], W, comm)[0]))
    W.destroy()
    return np.array(found)


def indicator_effectivity(model: Model, decomposition, points: list[dict], errors: np.ndarray) -> tuple[float, float]:
    """(smallest, largest) ratio of the indicator η (the residual at the answer in the energy
    product's dual norm, that product at the defaults) to the true ``errors`` at ``points``."""
    W = inner_product(model, "energy")
    try:
        return effectivity(indicator(model, decomposition, W, points), errors)
    finally:
        W.destroy()


# --- Axes -------------------------------------------------------------------------------------


def test_a_clamped_axis_holds_cubics_exactly_and_means_integrate_exactly():
    axis = Axis(STIFFNESS, 5)
    assert not axis.periodic and axis.size == 8 and np.isclose(axis.weights.sum(), 1.0)
    cubic = lambda s: 2 * s**3 - s + 0.5  # noqa: E731
    x = axis.fit(cubic(axis.nodes))
    s = np.linspace(0.0, 1.0, 41)
    assert np.abs(axis.spline(x)(s) - cubic(s)).max() < 1e-13
    square = (np.polynomial.Polynomial([0.5, -1.0, 0.0, 2.0]) ** 2).integ()
    assert axis.weights @ cubic(axis.nodes) ** 2 == pytest.approx(
        square(1.0) - square(0.0), rel=1e-12
    )  # degree 6: exact
    slope = axis.spline(x, 1)(s)
    assert np.abs(slope - (6 * s**2 - 1)).max() < 1e-12


def test_a_full_turn_is_periodic_and_its_modes_close_smoothly():
    axis = Axis(PITCH, 12)
    assert axis.periodic and axis.size == 12
    x = axis.fit(np.cos(2 * np.pi * axis.nodes) + 0.3 * np.sin(4 * np.pi * axis.nodes))
    curve = lambda s, d=0: axis.spline(x, d)(axis.unit(s))  # noqa: E731
    for d in (0, 1, 2):  # C² across the seam s = 0 ≡ 1
        assert curve(np.array([0.0]), d)[0] == pytest.approx(curve(np.array([1.0 - 1e-12]), d)[0], abs=1e-6)
    s = np.linspace(0.0, 1.0, 97)
    assert np.abs(curve(s) - (np.cos(2 * np.pi * s) + 0.3 * np.sin(4 * np.pi * s))).max() < 2e-3
    assert not Axis(Parameter("tilt", "loads.gravity.pitch", 0.0, (-90.0, 0.0)), 4).periodic


def test_the_online_cubics_are_the_splines():
    """Axis.polynomials read by horner: the splines' values and slopes, on a clamped and a
    periodic axis, at random points, the ends and the seam."""
    rng = np.random.default_rng(3)
    for axis in (Axis(STIFFNESS, 5), Axis(PITCH, 8)):
        X = rng.standard_normal((axis.size, 3))  # three curves at once
        P = axis.polynomials(X)
        for s in (0.0, 1.0, 0.5, *rng.uniform(0.0, 1.0, 20)):
            at = axis.unit(np.array([s]))
            for d in (0, 1):
                assert np.allclose(horner(P, float(at[0]), d), axis.spline(X, d)(at)[0], rtol=1e-12, atol=1e-12)


def test_bad_axes_are_refused_in_one_line():
    with pytest.raises(ParameterError, match="intervals"):
        Axis(STIFFNESS, 0)
    with pytest.raises(ParameterError, match="periodic axis needs at least 4"):
        Axis(PITCH, 3)
    with pytest.raises(ParameterError, match="outside its range"):
        Axis(STIFFNESS, 4).unit(np.array([1.5]))


# --- Separated terms --------------------------------------------------------------------------


def test_the_separated_terms_are_the_models_residual_at_the_nodes():
    """R(u; μ) assembled by the model against Σ κ_T(μ) K_T u − Σ φ_S(μ) f_S, at points of the
    axes' node grid, with stiffness, pitch and roll (a gravity component moved by two)."""
    model = beam([STIFFNESS, PITCH, ROLL], cells=(4, 2, 2))
    axes = (Axis(STIFFNESS, 3), Axis(PITCH, 4), Axis(ROLL, 2))
    terms = separated_terms(model, axes)
    # K₀ (the imposed rows), the Lamé μ and λ; f₀ (0 here) and one per component of g, each a
    # product of a function of pitch and one of roll (g = R_y(roll) R_x(pitch) g₀)
    assert len(terms.operator) == 3 and len(terms.load) == 4
    from dolfinx import fem

    from lungmech import jit
    from lungmech.fem.quantities import assemble_owned

    owned = owned_size(model.space)
    rng = np.random.default_rng(MPI.COMM_WORLD.rank)
    for index in ((0, 5, 3), (7, 12, 0), (3, 0, 7)):
        model.set_parameters({a.parameter.name: float(a.values[i]) for a, i in zip(axes, index)})
        u = np.zeros(owned)
        u[terms.free] = rng.standard_normal(len(terms.free))
        model.state.x.array[:owned] = u
        model.state.x.scatter_forward()
        found = assemble_owned(jit.form(model.residual), fem.Function(model.space).x, owned)[terms.free]
        separated = terms.residual(u, index)[terms.free]
        size = np.sqrt(MPI.COMM_WORLD.allreduce(float(found @ found)))
        assert np.sqrt(MPI.COMM_WORLD.allreduce(float((found - separated) @ (found - separated)))) < 1e-11 * size
    terms.destroy()


def test_models_the_pgd_cannot_separate_are_refused_in_one_line():
    cases = [
        (dict(law=lambda c: NeoHookean.from_young(c["E"], 0.3)), "not affine"),
        (dict(balanced=("x1", "y0", "y1", "z0", "z1")), "depends on the state"),
        (
            dict(constraints=[clamp("x0"), Displacement("x1", 0.01, component="x", ramp=Ramp.constant())]),
            "imposed displacement is not zero",
        ),
    ]
    for keywords, message in cases:
        model = beam([STIFFNESS, PITCH], cells=(3, 2, 2), **keywords)
        with pytest.raises(ParameterError, match=message) as raised:
            separated_terms(model, (Axis(STIFFNESS, 2), Axis(PITCH, 4)))
        assert "\n" not in str(raised.value)
    with pytest.raises(ParameterError, match="one axis per parameter"):
        separated_terms(beam([STIFFNESS, PITCH], cells=(3, 2, 2)), (Axis(STIFFNESS, 2),))


# --- The decomposition ------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("parameters", [(STIFFNESS, PITCH), (STIFFNESS, PITCH, ROLL)], ids=["pitch", "pitch-roll"])
def test_the_pgd_of_a_beam_under_its_turned_weight_is_the_full_model_everywhere(parameters):
    """u(E, θ) = (1/E) Σ gᵢ(θ) uᵢ: separated rank 2 under pitch, 3 under pitch and roll. At ≤ 5
    terms, every one of 50 random points of the box within 1e-4 of the full model in the
    energy norm (no full solve built it)."""
    model = beam(list(parameters))
    axes = tuple(Axis(p, 16 if p is PITCH else 8) for p in parameters)
    terms = separated_terms(model, axes)
    W = inner_product(model, "energy")
    decomposition, rounds = pgd(terms, W, Options(max_terms=5, tolerance=1e-5))
    assert decomposition.size == len(parameters) and decomposition.terms <= 5
    assert not rounds[-1].added  # the greedy stopped on its own: the last term below the tolerance
    potentials = [r.potential for r in rounds]
    assert all(b <= a + 1e-12 * abs(a) for a, b in zip(potentials, potentials[1:]))  # the loss never rises
    assert relative_errors(model, decomposition, Parameters(list(parameters)).sample(50, seed=2)).max() < 1e-4
    W.destroy()
    terms.destroy()


@pytest.mark.slow
def test_the_derivatives_in_mu_are_the_decompositions_own():
    model = beam([STIFFNESS, PITCH], cells=(4, 2, 2))
    axes = (Axis(STIFFNESS, 6), Axis(PITCH, 8))
    terms = separated_terms(model, axes)
    W = inner_product(model, "energy")
    decomposition, _ = pgd(terms, W, Options(max_terms=3))
    point = {"E": 2.5, "pitch": 40.0}
    found = decomposition.factor_derivatives(point)
    for j, (name, h) in enumerate((("E", 1e-6), ("pitch", 1e-5))):
        ahead, behind = dict(point), dict(point)
        ahead[name] += h
        behind[name] -= h
        difference = (decomposition.factors(ahead) - decomposition.factors(behind)) / (2 * h)
        assert np.allclose(found[:, j], difference, rtol=1e-6, atol=1e-8 * np.abs(difference).max())
    with pytest.raises(ParameterError, match="outside the PGD's box"):
        decomposition.factors({"E": 20.0})
    W.destroy()
    terms.destroy()


@pytest.mark.slow
def test_the_indicator_is_the_error_times_the_stiffness_ratio():
    """η = ‖R(u_PGD)‖_{W⁻¹}/‖u_PGD‖_W, W the energy product at E₀ = 3 Pa: with K(μ) = (E/E₀) W on
    the free dofs, K e = R gives η = (E/E₀) ‖e‖_W / ‖u_PGD‖_W, so η over the true relative
    error is E/E₀ (to the PGD's own error in the denominator)."""
    model = beam([STIFFNESS, PITCH], cells=(4, 2, 2))
    terms = separated_terms(model, (Axis(STIFFNESS, 3), Axis(PITCH, 4)))  # coarse: errors to measure
    W = inner_product(model, "energy")
    decomposition, _ = pgd(terms, W, Options(max_terms=1))  # one term of two: a large error
    points = Parameters([STIFFNESS, PITCH]).sample(8, seed=5)
    before = dict(model.parameter_values)
    estimates = indicator(model, decomposition, W, points)
    assert model.parameter_values == before  # left as it was
    errors = relative_errors(model, decomposition, points)
    sizes = [float(norms(decomposition.state(p)[:, None], W, MPI.COMM_WORLD)[0]) for p in points]
    solver = NewtonSolver(model, NewtonOptions(rtol=1e-13, atol=1e-16))
    full = [float(norms(full_solution(model, p, solver)[:, None], W, MPI.COMM_WORLD)[0]) for p in points]
    ratio = np.array([p["E"] / STIFFNESS.default for p in points]) * np.array(full) / np.array(sizes)
    assert np.all(errors > 1e-3)
    assert np.allclose(estimates / errors, ratio, rtol=1e-8)
    low, high = effectivity(estimates, errors)
    assert low == pytest.approx(ratio.min(), rel=1e-8) and high == pytest.approx(ratio.max(), rel=1e-8)
    W.destroy()
    terms.destroy()


@pytest.mark.mpi
def test_a_pgd_on_two_ranks_is_the_serial_one():
    """The same beam on every rank (COMM_SELF) and distributed: the same potentials and, at
    three points, the same energy norm of the state, to 1e-9."""
    found = []
    for comm in (MPI.COMM_SELF, MPI.COMM_WORLD):
        model = beam([STIFFNESS, PITCH], comm=comm, cells=(6, 2, 2))
        terms = separated_terms(model, (Axis(STIFFNESS, 6), Axis(PITCH, 8)))
        W = inner_product(model, "energy")
        decomposition, rounds = pgd(terms, W, Options(max_terms=4, tolerance=1e-8))
        points = Parameters([STIFFNESS, PITCH]).sample(3, seed=1)
        sizes = [float(norms(decomposition.state(p)[:, None], W, comm)[0]) for p in points]
        found.append(np.array([*(r.potential for r in rounds), *sizes]))
        W.destroy()
        terms.destroy()
    assert np.allclose(found[0], found[1], rtol=1e-9, atol=0.0)
