"""Numerical stability at the extremes: stiffness from 1 Pa to 1 GPa under pleural suction from
3 Pa to 30 kPa, on the bundled lung phantom (3.7k cells).

Every case either converges, to the small-strain closed form where strains are small (a body
held at one small patch under a uniform pressure: ΔV/V = |p|/K, K = E/(3(1 − 2ν))), or stops
at a named physical limit: an inverted cell, a loss of stability, or the minimum step. No case
fails because a residual tolerance sits below round-off (as an absolute 1e-12 did at 1 GPa).
"""

from __future__ import annotations

import re

from mpi4py import MPI

import pytest

from lungmech import meshes
from lungmech.errors import SolverError
from lungmech.fem import limits
from lungmech.fem.constraints import Displacement, clamp
from lungmech.fem.loads import FollowerPressure
from lungmech.fem.materials import NeoHookean, SaintVenantKirchhoff
from lungmech.fem.model import Model
from lungmech.fem.quantities import deformed_volume
from lungmech.fem.solver import NewtonOptions, NewtonSolver, Stepping, solve
from lungmech.mesh import box, from_file

pytestmark = pytest.mark.slow
NU = 0.3
STEPPING, NEWTON = Stepping(initial_step=0.25, min_step=1e-3), NewtonOptions(max_iterations=15)
LIMITS = ("an element inverted", "loss of stability", "the minimum step")
SURFACE = ("pleura", "diaphragm", "mediastinum")


@pytest.fixture(scope="module")
def lung():
    return from_file(meshes.reference("lung_phantom_right"), MPI.COMM_WORLD)


def breathe(geometry, law, pressure: float):
    model = Model(geometry, law, constraints=[clamp("hilum")], loads=[FollowerPressure(SURFACE, pressure)])
    return model, solve(model, STEPPING, NEWTON, monitor=lambda step: None)


@pytest.mark.parametrize("E", [1.0, 1e3, 1e6, 1e9])
@pytest.mark.parametrize("pressure", [-3.0, -300.0, -3e4])
def test_stiffness_times_load(lung, E, pressure):
    strain = abs(pressure) / E
    try:
        model, report = breathe(lung, NeoHookean.from_young(E, NU), pressure)
    except SolverError as error:
        assert strain >= 1.0, f"p/E = {strain:g} should converge: {error}"  # suction ≥ E: beyond the limit point
        assert any(limit in str(error) for limit in LIMITS), str(error)
        assert re.match(r"the load path stopped at t = \S+ s: ", str(error))
        return
    assert strain < 1.0
    growth = deformed_volume(model)() / lung.volume() - 1
    if strain <= 1e-3:
        bulk = E / (3 * (1 - 2 * NU))
        assert growth == pytest.approx(strain * E / bulk, rel=0.01)
    assert report.failures == 0 or strain > 1e-3


def test_a_softening_law_stops_at_its_limit_point(lung):
    """Saint Venant–Kirchhoff softens in compression: a squeezed lung reaches a limit point."""
    with pytest.raises(SolverError, match="loss of stability: the body's response to the load is running away"):
        breathe(lung, SaintVenantKirchhoff.from_young(1e3, NU), 300.0)


def slender_bar() -> Model:
    """A 1 × 0.2 × 0.2 m bar, clamped at both ends, its end x = 1 pushed 1.5 m towards the other
    (t = 1). On this mesh its straight path bifurcates (Euler buckling) near t = 0.175."""
    geometry = box(MPI.COMM_SELF, (1.0, 0.2, 0.2), (6, 2, 2))
    return Model(
        geometry, NeoHookean.from_young(10.0, NU), constraints=[clamp("x0"), Displacement("x1", (-1.5, 0.0, 0.0))]
    )


@pytest.mark.parametrize(
    "t, diagnosis",
    [
        (0.10, "^$"),  # half-way to the bifurcation: nothing to report
        (0.17, "kept [0-9.]+ % of its smallest eigenvalue at rest .buckling, or a bifurcation"),
        (0.18, "an eigenvalue of the wrong sign .buckling, or a bifurcation"),
    ],
)
def test_a_bifurcation_is_diagnosed_from_the_tangent(t, diagnosis):
    """The straight path of a compressed bar, just before and just past its first bifurcation:
    the tangent's eigenvalue nearest 0 has lost most of its value at rest, then changed sign."""
    model = slender_bar()
    solver = NewtonSolver(model)
    rest = model.state.x.array.copy()
    solve(model, Stepping(end=t, max_step=0.01), solver=solver, monitor=lambda step: None)
    assert re.search(diagnosis, limits.diagnose(model, solver, model.set_time, t, (rest, 0.0), 1.0))


def test_a_slender_bar_crushed_stops_at_a_named_limit():
    """Far past its bifurcations (the symmetric mesh keeps it straight, unstable), crushed to a
    few % of its volume: the path stops, and says where and why."""
    with pytest.raises(SolverError) as error:
        solve(slender_bar(), STEPPING, NEWTON, monitor=lambda step: None)
    assert any(limit in str(error.value) for limit in LIMITS), str(error.value)
    assert re.match(r"the load path stopped at t = \S+ s: ", str(error.value))


def test_a_block_driven_through_itself_inverts():
    """Imposing a displacement longer than a stubby block: its cells must turn inside out."""
    geometry = box(MPI.COMM_SELF, (1.0, 1.0, 1.0), (2, 2, 2))
    model = Model(
        geometry, NeoHookean.from_young(10.0, NU), constraints=[clamp("x0"), Displacement("x1", (-1.5, 0.0, 0.0))]
    )
    with pytest.raises(SolverError, match="an element inverted: J = det F reached"):
        solve(model, STEPPING, NEWTON, monitor=lambda step: None)
