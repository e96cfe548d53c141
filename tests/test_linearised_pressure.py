"""Newton's tangent with a linearised bulk stress (lungmech.fem.linearised_pressure): exact at an
equilibrium, not elsewhere; the same solution as the exact tangent; the mixed formulation's
iteration counts on a nearly incompressible body where the exact tangent needs several times as
many; only where a law has a bulk term to linearise."""

from mpi4py import MPI

import numpy as np
import pytest
from dolfinx.fem.petsc import assemble_matrix

from lungmech.fem.constraints import clamp
from lungmech.fem.linearised_pressure import LinearisedPressure
from lungmech.fem.loads import Traction
from lungmech.fem.materials import MooneyRivlin, NeoHookean, SaintVenantKirchhoff
from lungmech.fem.model import Model
from lungmech.fem.quantities import Probe
from lungmech.fem.solver import NewtonSolver, Stepping, solve
from lungmech.lung import Poromechanics, skeleton
from lungmech.mesh import box, cook_membrane
from lungmech.parallel.owned import owned_size

NU = 0.4999  # κ/μ = 5000


def cook(cells: int, law=None, plane: str = "strain", comm=MPI.COMM_WORLD) -> Model:
    """Cook's membrane (VERIFICATION.md), P2, sheared by 100 N/m."""
    return Model(
        cook_membrane(comm, cells=(cells, cells)),
        law or NeoHookean.from_young(240.565, NU),
        degree=2,
        plane=plane,
        constraints=[clamp("clamped")],
        loads=[Traction("loaded", (0.0, 100.0 / 16.0))],
    )


def corner(model: Model) -> float:
    return float(Probe(model.geometry.mesh, [[48.0, 60.0]])(model.displacement())[0, 1])


def tangents(solver: NewtonSolver) -> tuple[float, float]:
    """‖K_Newton − K_exact‖ / ‖K_exact‖ (Frobenius) at the model's state."""
    model = solver.model
    newton = assemble_matrix(solver.problem.J, bcs=model.bcs)
    exact = assemble_matrix(solver.jacobian_form, bcs=model.bcs)
    newton.assemble(), exact.assemble()
    scale = exact.norm()
    newton.axpy(-1.0, exact)
    return newton.norm() / scale


def test_the_newton_tangent_is_exact_at_an_equilibrium_only():
    model = cook(4)
    solver = NewtonSolver(model)
    solve(model, Stepping(end=0.5), solver=solver, monitor=lambda step: None)
    pressure = solver._pressure
    pressure.at_equilibrium()
    assert tangents(solver) < 1e-13
    # a state off the equilibrium (its J off by 1 %) with the bulk stress of the equilibrium:
    # κ g(J) moved, s did not, and κ = 5000 μ makes the difference show
    model.state.x.array[:] *= 1.2
    model.state.x.scatter_forward()
    assert tangents(solver) > 1e-3
    pressure.at_equilibrium()
    assert tangents(solver) < 1e-13


def test_a_step_moves_the_bulk_stress_by_its_linearisation():
    """s ← κ [g(J) + g'(J) DJ[Δu]]: for the neo-Hookean law g = ln J, checked against
    κ ln J(u + ε Δu) to first order in ε."""
    model = cook(2)
    solver = NewtonSolver(model)
    pressure = solver._pressure
    rng = np.random.default_rng(1)
    start = 1e-2 * rng.standard_normal(model.state.x.array.size)
    step = 1e-2 * rng.standard_normal(start.size)
    owned = owned_size(model.space)
    values = []
    for epsilon in (0.0, 1e-4):
        model.state.x.array[:] = start + epsilon * step
        model.state.x.scatter_forward()
        pressure.at_equilibrium()
        values.append(pressure.stress.x.array.copy())
    pressure.advance(start[:owned], 1e-4 * step[:owned])
    linearised = pressure.stress.x.array
    change = values[1] - values[0]
    assert np.abs(linearised - values[1]).max() < 1e-3 * np.abs(change).max()  # O(ε²) off
    assert np.abs(linearised - values[0]).max() > 0.5 * np.abs(change).max()  # and it moved


@pytest.mark.parametrize("cells", [4, 16])
def test_nearly_incompressible_cook_converges_as_the_mixed_formulation(cells):
    """The same corner displacement as Newton with the exact tangent, in the mixed formulation's
    iterations (11–12 on these meshes) where the exact tangent needs twice as many or more."""
    model = cook(cells)
    report = solve(model, monitor=lambda step: None)
    exact = cook(cells)
    exact_report = solve(exact, solver=NewtonSolver(exact, jacobian=exact.jacobian), monitor=lambda step: None)
    assert corner(model) == pytest.approx(corner(exact), rel=1e-9)
    assert report.failures == 0
    assert report.newton_iterations <= 16
    assert exact_report.newton_iterations >= 2 * report.newton_iterations - 4


def test_convergence_is_superlinear():
    """Newton on the pair (u, s) is exact, so the residual falls faster than linearly to the end."""
    model = cook(8)
    solver = NewtonSolver(model)
    solve(model, Stepping(end=0.25), solver=solver, monitor=lambda step: None)
    model.set_time(0.3)
    result = solver.solve()
    r = np.array(result.residuals) / max(result.residuals)
    assert result.converged
    r = r[np.argmax(r) :]  # from the largest residual on (a Newton path may climb first)
    tail = [(a, b) for a, b in zip(r[:-1], r[1:]) if a < 0.1]
    assert tail, r
    for a, b in tail:
        assert np.log(b) / np.log(a) > 1.5, f"not superlinear: relative residuals {r}"


@pytest.mark.slow
def test_plane_stress_and_mooney_rivlin_take_it_too():
    law = MooneyRivlin.from_young(240.565, NU)
    for plane in ("strain", "stress"):
        model = cook(4, law, plane)
        assert LinearisedPressure.of(model) is not None
        report = solve(model, monitor=lambda step: None)
        exact = cook(4, law, plane)
        solve(exact, solver=NewtonSolver(exact, jacobian=exact.jacobian), monitor=lambda step: None)
        assert corner(model) == pytest.approx(corner(exact), rel=1e-9)
        assert report.failures == 0


def test_only_where_a_law_has_a_bulk_term():
    geometry = box(MPI.COMM_WORLD, (1.0, 1.0, 1.0), (1, 1, 1))
    assert LinearisedPressure.of(Model(geometry, SaintVenantKirchhoff.from_young(1.0, 0.3))) is None  # no split
    assert LinearisedPressure.of(Model(geometry, NeoHookean.from_young(1.0, 0.3), degree=2, mixed=True)) is None
    assert LinearisedPressure.of(Model(geometry, NeoHookean.incompressible(1.0), degree=2, mixed=True)) is None
    lung = Model(geometry, skeleton(0.16, 0.5, 0.2, 0.4), formulation=Poromechanics(kappa=100.0, phi_s0=0.3))
    assert LinearisedPressure.of(lung) is None  # its own fields and energy
    assert LinearisedPressure.of(Model(geometry, NeoHookean.from_young(1.0, 0.3))) is not None
    # Newton with a given tangent (an incremental potential, say) keeps it
    model = Model(geometry, NeoHookean.from_young(1.0, 0.3))
    assert NewtonSolver(model, jacobian=model.jacobian)._pressure is None
