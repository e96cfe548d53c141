"""Loads users expect: a total force, tractions and pressures given as formulas of position and
time, and a dead normal pressure — each against an equivalent load or a closed form."""

import re

from mpi4py import MPI

import numpy as np
import pytest

from lungmech.errors import ParameterError
from lungmech.fem.constraints import clamp, symmetry
from lungmech.fem.loads import FollowerPressure, Force, NormalPressure, Traction
from lungmech.fem.materials import LinearElastic, NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.quantities import Probe, reaction
from lungmech.fem.ramp import Ramp
from lungmech.fem.solver import Stepping, solve
from lungmech.mesh import box, cook_membrane, quarter_annulus

QUIET = {"monitor": lambda step: None}


def _block(load, law=None) -> Model:
    geometry = box(MPI.COMM_WORLD, lengths=(2.0, 1.0, 0.5), cells=(4, 2, 2))
    return Model(geometry, law or NeoHookean.from_young(50.0, 0.3), degree=2, constraints=[clamp("x0")], loads=[load])


@pytest.mark.slow
def test_a_total_force_is_its_traction_over_the_area_and_the_support_carries_it():
    """1.5 N on the 1 m × 0.5 m end face = 3 Pa of traction; the clamp's reaction is −1.5 N."""
    force = Force("x1", (0.3, -1.5, 0.0))
    by_force, by_traction = _block(force), _block(Traction("x1", (0.6, -3.0, 0.0)))
    for model in (by_force, by_traction):
        solve(model, Stepping(), **QUIET)
    assert np.allclose(by_force.state.x.array, by_traction.state.x.array, rtol=0, atol=1e-12)
    support = reaction(by_force, "x0")()
    assert support.force == pytest.approx([-0.3, 1.5, 0.0], abs=1e-9)


def test_a_total_force_in_2d_is_per_metre_of_thickness():
    """Cook's 100 N/m on the 16 m edge is its classical 6.25 Pa traction."""
    models = [
        Model(
            cook_membrane(MPI.COMM_WORLD, cells=(4, 4)),
            LinearElastic.from_young(1.0, 1 / 3),
            plane="stress",
            constraints=[clamp("clamped")],
            loads=[load],
        )
        for load in (Force("loaded", (0.0, 1.0)), Traction("loaded", (0.0, 1.0 / 16.0)))
    ]
    for model in models:
        solve(model, Stepping(), **QUIET)
    assert np.allclose(models[0].state.x.array, models[1].state.x.array, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_a_traction_formula_of_time_follows_the_time():
    """ "t" with a constant ramp is the default ramp 0 → 1 times 1: the same state at every step."""
    formula = _block(Traction("x1", (0.0, "-2 * t", 0.0), ramp=Ramp.constant()))
    numbers = _block(Traction("x1", (0.0, -2.0, 0.0)))
    states = []
    for model in (formula, numbers):
        path = []
        solve(
            model,
            Stepping(initial_step=0.25, growth=1.0),
            on_step=lambda s, m=model: path.append(m.state.x.array.copy()),
            **QUIET,
        )
        states.append(path)
    assert len(states[0]) == 4
    for a, b in zip(*states):
        assert np.allclose(a, b, rtol=0, atol=1e-12)


def test_a_traction_formula_of_position_has_its_force_and_moment():
    """t_x = σ0 (1 − 2y) on the end face y ∈ [0, 1], z ∈ [0, 0.5]: no net force, a bending moment
    M_z = −∫ y t_x dA = σ0 W H²/6 (H = 1, W = 0.5), which the clamp carries back."""
    sigma0 = 1e-4  # small: the moment arm barely moves
    model = _block(Traction("x1", (f"{sigma0} * (1 - 2 * y)", 0.0, 0.0)), LinearElastic.from_young(50.0, 0.3))
    solve(model, Stepping(), **QUIET)
    support = reaction(model, "x0")()
    assert np.abs(support.force).max() <= 1e-12
    assert support.moment[2] == pytest.approx(-sigma0 * 0.5 / 6.0, rel=1e-3)
    # bending: the top of the end face pulled back, the bottom pushed out
    ux = Probe(model.geometry.mesh, [[2.0, 0.0, 0.25], [2.0, 1.0, 0.25]])(model.displacement())[:, 0]
    assert ux[0] > 0 > ux[1]


def test_a_dead_normal_pressure_is_a_traction_along_the_reference_normal():
    by_pressure, by_traction = _block(NormalPressure("x1", 2.0)), _block(Traction("x1", (-2.0, 0.0, 0.0)))
    for model in (by_pressure, by_traction):
        solve(model, Stepping(), **QUIET)
    assert np.allclose(by_pressure.state.x.array, by_traction.state.x.array, rtol=0, atol=1e-12)


@pytest.mark.parametrize("pressure", [NormalPressure, FollowerPressure])
def test_a_pressure_in_a_thick_cylinder_matches_lame(pressure):
    """Small strain (p/E = 1e-4): dead and follower pressures both give Lamé's
    u(a) = p a (1 + ν)/E ((1 − 2ν) a² + b²)/(b² − a²), and differ at finite strain."""
    E, nu, a, b = 1.0e3, 0.3, 1.0, 2.0

    def inner_displacement(p: float) -> float:
        geometry = quarter_annulus(MPI.COMM_WORLD, a, b, cells=(8, 32))
        model = Model(
            geometry,
            NeoHookean.from_young(E, nu),
            degree=2,
            plane="strain",
            constraints=[symmetry("x0", "x"), symmetry("y0", "y")],
            loads=[pressure("inner", p)],
        )
        solve(model, Stepping(), **QUIET)
        return Probe(geometry.mesh, [[a, 0.0]])(model.displacement())[0, 0]

    p = 0.1
    expected = p * a * (1 + nu) / E * ((1 - 2 * nu) * a**2 + b**2) / (b**2 - a**2)
    assert inner_displacement(p) == pytest.approx(expected, rel=5e-3)


def test_dead_and_follower_pressures_differ_at_finite_strain():
    """Inflating a quarter annulus by 30 %: the follower pressure pushes on the grown, turned
    surface, the dead one on the reference normal; the follower inflates it more."""

    def inflate(pressure) -> float:
        geometry = quarter_annulus(MPI.COMM_WORLD, 1.0, 2.0, cells=(4, 16))
        model = Model(
            geometry,
            NeoHookean.from_young(1.0, 0.3),
            degree=2,
            plane="strain",
            constraints=[symmetry("x0", "x"), symmetry("y0", "y")],
            loads=[pressure("inner", 0.15)],
        )
        solve(model, Stepping(), **QUIET)
        return Probe(geometry.mesh, [[1.0, 0.0]])(model.displacement())[0, 0]

    dead, follower = inflate(NormalPressure), inflate(FollowerPressure)
    assert follower > dead > 0.1


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: Traction("x1", (0.0, "x +", 0.0)), "value[1]: 'x +' is not a formula"),
        (lambda: Traction("x1", (0.0, "open('f')", 0.0)), "is not a formula of x, y, z, t"),
        (lambda: NormalPressure("x1", "w * 2"), "unknown name 'w'"),
        (lambda: Force("x1", (0.0, "t", 0.0)), "value[1] must be a number"),
        (lambda: _block(Traction("x1", ("z", 0.0, 0.0))).geometry, None),
    ],
)
def test_bad_formulas_are_clear_errors(make, message):
    if message is None:
        make()  # z is known in 3-D
        return
    with pytest.raises(ParameterError, match=re.escape(message)):
        make()


def test_z_in_a_plane_body_is_refused():
    with pytest.raises(ParameterError, match="unknown name 'z'"):
        Model(
            cook_membrane(MPI.COMM_WORLD, cells=(2, 2)),
            LinearElastic.from_young(1.0, 0.3),
            plane="strain",
            constraints=[clamp("clamped")],
            loads=[Traction("loaded", ("z", 0.0))],
        )
