"""Newton: quadratic convergence (exact tangent), cut-back and restore, clear failures."""

from mpi4py import MPI

import numpy as np
import pytest

from lungmech.errors import ParameterError, SolverError
from lungmech.fem.constraints import clamp
from lungmech.fem.loads import BodyForce, FollowerPressure, Traction
from lungmech.fem.materials import NeoHookean, SaintVenantKirchhoff
from lungmech.fem.model import Model
from lungmech.fem.ramp import Ramp
from lungmech.fem.solver import NewtonOptions, NewtonSolver, Stepping, solve
from lungmech.mesh import box


def bent_block(loads_scale: float = 1.0, ramp: Ramp = Ramp()) -> Model:
    """A clamped block under shear traction, gravity and a follower pressure: a non-trivial state."""
    geometry = box(MPI.COMM_WORLD, lengths=(3.0, 1.0, 1.0), cells=(6, 2, 2))
    return Model(
        geometry,
        NeoHookean.from_young(10.0, 0.3),
        degree=2,
        constraints=[clamp("x0")],
        loads=[
            Traction("x1", (0.0, 0.0, -0.5 * loads_scale), ramp=ramp),
            BodyForce((0.0, 0.1 * loads_scale, 0.0), ramp=ramp),
            FollowerPressure("z1", 0.3 * loads_scale, ramp=ramp),
        ],
    )


def test_newton_converges_quadratically():
    """From a converged state, one load increment: r_{k+1} ≲ C r_k² (exact tangent)."""
    model = bent_block(0.1)
    # the exact tangent given: by default a neo-Hookean displacement model moves its bulk stress
    # as the mixed formulation would (tests/test_linearised_pressure.py)
    solver = NewtonSolver(model, NewtonOptions(line_search="none"), jacobian=model.jacobian)
    solve(model, Stepping(end=0.5), solver=solver)
    model.set_time(1.0)
    result = solver.solve()
    converged, residuals = result.converged, result.residuals
    r = np.array(residuals) / residuals[0]
    assert converged and len(r) >= 4, r
    pairs = [(a, b) for a, b in zip(r[:-1], r[1:]) if a < 1e-2 and b > 1e-13]
    assert pairs, r
    for a, b in pairs:
        assert b < 10 * a**2, f"not quadratic: relative residuals {r}"


@pytest.mark.slow
def test_adaptive_stepping_cuts_back_and_recovers():
    """A full step of a large load fails (an element inverts); cutting back gets there."""
    model = bent_block(1.0)
    report = solve(model, Stepping(initial_step=1.0), NewtonOptions(line_search="none"))
    assert report.failures >= 1
    assert report.accepted[-1].time == pytest.approx(1.0)
    # The same end state as a cautious run with small steps.
    cautious = bent_block(1.0)
    solve(cautious, Stepping(initial_step=0.1, growth=1.0))
    assert np.allclose(model.state.x.array, cautious.state.x.array, atol=1e-9)


@pytest.mark.slow
def test_the_automatic_first_step_does_not_start_with_a_failure():
    """The load that fails in one step (above) starts with a step the tangent judged safe."""
    model = bent_block(1.0)
    report = solve(model, Stepping(), NewtonOptions(line_search="none"))
    assert report.failures == 0
    assert 0.01 < report.steps[0].step < 1.0
    assert report.accepted[-1].time == pytest.approx(1.0)


def test_the_automatic_first_step_takes_a_gentle_load_in_one_go():
    model = bent_block(0.01)
    report = solve(model, Stepping())
    assert [s.step for s in report.steps] == [1.0]


@pytest.mark.slow
def test_the_predictor_does_not_extrapolate_across_a_load_reversal():
    """Loading then unloading at equal steps. The first step back starts from the turning point,
    at most one Newton iteration dearer than the last step out (which had a good predictor).
    Extrapolated across the turn, it would start twice as far from its solution (8 iterations
    here, against 5 for the last step out)."""
    model = bent_block(0.5, Ramp((0.0, 1.0, 2.0), (0.0, 1.0, 0.0)))
    report = solve(model, Stepping(end=2.0, initial_step=0.25, growth=1.0))
    iterations = {round(s.time, 6): s.iterations for s in report.accepted}
    assert report.failures == 0
    assert iterations[1.25] <= iterations[1.0] + 1, iterations


def test_failure_is_reported_and_last_state_kept():
    """An impossible load (compression beyond a SVK limit point) stops with a clear error."""
    geometry = box(MPI.COMM_WORLD, cells=(1, 1, 1))
    law = SaintVenantKirchhoff.from_young(1.0, 0.3)
    model = Model(geometry, law, constraints=[clamp("x0")], loads=[Traction("x1", (-5.0, 0.0, 0.0))])
    converged = []
    with pytest.raises(SolverError, match="did not converge") as error:
        solve(model, Stepping(initial_step=0.5, min_step=0.01), on_step=lambda s: converged.append(s.time))
    assert "last converged state" in str(error.value)
    assert np.all(np.isfinite(model.state.x.array))
    assert model.time == pytest.approx(converged[-1] if converged else 0.0)


@pytest.mark.slow
def test_iterative_solver_matches_direct():
    direct, iterative = bent_block(), bent_block()
    solve(direct)
    solve(iterative, options=NewtonOptions(linear_solver="iterative"))
    assert np.allclose(
        iterative.state.x.array, direct.state.x.array, rtol=0, atol=1e-8 * np.abs(direct.state.x.array).max()
    )


@pytest.mark.slow
@pytest.mark.parametrize("law", ["nearly incompressible", "incompressible"])
def test_the_iterative_solver_splits_the_mixed_formulation(law):
    """Taylor–Hood (u, p): Schur split, AMG on u, the pressure mass matrix weighted by
    1/μ₀ + 1/κ for S. The direct solver's state, and Krylov iterations that barely grow with the
    mesh where the pressure block is preconditioned well (an exact u block: the same count on
    two meshes)."""
    from lungmech.mesh import cook_membrane

    def cook(cells: int, linear_solver: str, petsc_options=None) -> tuple[Model, int]:
        material = (
            NeoHookean.incompressible(80.0) if law == "incompressible" else NeoHookean.from_young(240.565, 0.4999)
        )
        model = Model(
            cook_membrane(MPI.COMM_WORLD, cells=(cells, cells)),
            material,
            degree=2,
            mixed=True,
            plane="strain",
            constraints=[clamp("clamped")],
            loads=[Traction("loaded", (0.0, 100.0 / 16.0))],
        )
        options = NewtonOptions(linear_solver=linear_solver, petsc_options=petsc_options or {})
        solver = NewtonSolver(model, options)
        ksp, krylov = solver.problem.solver.getKSP(), []
        solver.problem.solver.setMonitor(lambda snes, it, norm: krylov.append(ksp.getIterationNumber()))
        report = solve(model, Stepping(), solver=solver, monitor=lambda step: None)
        assert report.failures == 0
        return model, sum(krylov) / report.newton_iterations

    direct, _ = cook(8, "direct")
    iterative, _ = cook(8, "iterative")
    scale = np.abs(direct.state.x.array).max()
    assert np.allclose(iterative.state.x.array, direct.state.x.array, rtol=0, atol=1e-8 * scale)
    exact_u = {"fieldsplit_u_pc_type": "lu", "fieldsplit_u_pc_factor_mat_solver_type": "mumps"}
    coarse, fine = cook(4, "iterative", exact_u)[1], cook(16, "iterative", exact_u)[1]
    assert fine < 1.5 * coarse + 5, (coarse, fine)


def test_the_iterative_solver_refuses_plane_stress_above_p1():
    from lungmech.mesh import rectangle

    model = Model(rectangle(MPI.COMM_WORLD, cells=(1, 1)), NeoHookean(1.0, 1.0), degree=2, plane="stress")
    with pytest.raises(ParameterError, match="no preconditioner for the fields u, thickness_stretch yet"):
        NewtonSolver(model, NewtonOptions(linear_solver="iterative"))


@pytest.mark.slow
def test_the_iterative_solver_condenses_the_lung_s_solid_fraction():
    """The lung cube (u, Φs) with the Schur split: the same state as the direct solver, and each
    linear solve only as exact as Newton needs (few Krylov iterations)."""
    from test_lung import averages, unit_cube

    direct, iterative = unit_cube(0.5, cells=4, scaling="linear"), unit_cube(0.5, cells=4, scaling="linear")
    solve(direct, Stepping(), monitor=lambda step: None)
    solver = NewtonSolver(iterative, NewtonOptions(linear_solver="iterative"))
    report = solve(iterative, Stepping(), solver=solver, monitor=lambda step: None)
    assert report.failures == 0
    assert averages(iterative)["J"] == pytest.approx(averages(direct)["J"], rel=1e-9)
    assert solver.problem.solver.getKSP().getPC().getType() == "fieldsplit"
    assert np.allclose(iterative.state.x.array, direct.state.x.array, rtol=0, atol=1e-8)


def test_bad_solver_options():
    with pytest.raises(ParameterError, match="linear_solver"):
        NewtonOptions(linear_solver="magic")
    with pytest.raises(ParameterError, match="min_step"):
        Stepping(initial_step=1e-9)


def test_petsc_options_of_the_user_only_are_checked():
    """Choosing another SNES type leaves lungmech's line-search default unused: not an error."""
    from lungmech.fem.solver import NewtonOptions, NewtonSolver

    geometry = box(MPI.COMM_WORLD, cells=(1, 1, 1))
    model = Model(geometry, SaintVenantKirchhoff.from_young(1.0, 0.3), constraints=[clamp("x0")])
    NewtonSolver(model, NewtonOptions(petsc_options={"snes_type": "newtontr"}))
    NewtonSolver(model, NewtonOptions(petsc_options={"snes_type": "ksponly", "ksp_view": False}))


@pytest.mark.slow
def test_auto_takes_the_iterative_solver_for_large_problems_where_one_fits(monkeypatch):
    """Above ITERATIVE_FROM_DOFS unknowns "auto" is iterative, unless no preconditioner fits
    the formulation (plane stress above P1): then it stays direct."""
    import lungmech.fem.newton as solver_module
    from lungmech.mesh import rectangle

    monkeypatch.setattr(solver_module, "ITERATIVE_FROM_DOFS", 10)
    assert NewtonSolver(bent_block()).linear_solver == "iterative"
    plate = Model(rectangle(MPI.COMM_WORLD, cells=(2, 2)), NeoHookean(1.0, 1.0), degree=2, plane="stress")
    assert NewtonSolver(plate).linear_solver == "direct"
    monkeypatch.setattr(solver_module, "ITERATIVE_FROM_DOFS", 10**9)
    assert NewtonSolver(bent_block()).linear_solver == "direct"


def test_mumps_estimates_its_memory_before_it_factorises():
    """The analysis alone (INFOG(16)): an estimate that grows with the mesh and bounds, within a
    small factor, the memory the factorisation then takes (INFOG(21), measured by MUMPS)."""
    from dolfinx.fem.petsc import assemble_matrix

    from lungmech.fem.linear import factorisation_memory, factorised

    estimates, used = [], []
    for cells in (2, 4):
        geometry = box(MPI.COMM_WORLD, lengths=(3.0, 1.0, 1.0), cells=(6 * cells, 2 * cells, 2 * cells))
        model = Model(geometry, NeoHookean.from_young(10.0, 0.3), constraints=[clamp("x0")])
        K = assemble_matrix(NewtonSolver(model).jacobian_form, bcs=model.bcs)
        K.assemble()
        estimates.append(factorisation_memory(K))
        ksp = factorised(K)
        ksp.setUp()
        used.append(ksp.getPC().getFactorMatrix().getMumpsInfog(21) * 1e6 / 2**20)  # MB to MiB
        ksp.destroy(), K.destroy()
    assert estimates[1] > 2 * estimates[0]
    for estimate, measured in zip(estimates, used):
        assert measured <= estimate <= 3 * measured, (estimates, used)


@pytest.mark.slow
def test_auto_takes_the_iterative_solver_where_a_factorisation_would_not_fit(monkeypatch, caplog):
    """Below ITERATIVE_FROM_DOFS, "auto" compares MUMPS's estimate with the memory a rank may
    count on: direct on this machine, iterative on one with 1 MiB to spare (and says why)."""
    import lungmech.fem.newton as solver_module

    monkeypatch.setattr(solver_module, "MEMORY_CHECK_FROM_DOFS", 10)
    assert NewtonSolver(bent_block()).linear_solver == "direct"
    monkeypatch.setattr(solver_module.linear, "available_memory", lambda comm: 1.0)
    with caplog.at_level("INFO", logger="lungmech"):
        assert NewtonSolver(bent_block()).linear_solver == "iterative"
    assert any("MiB per rank of the 1 MiB available" in r.message for r in caplog.records)
    monkeypatch.setattr(solver_module, "MEMORY_CHECK_FROM_DOFS", 10**9)  # too small to ask
    assert NewtonSolver(bent_block()).linear_solver == "direct"


@pytest.mark.slow
def test_auto_leaves_a_factorisation_that_runs_out_of_memory(caplog):
    """MUMPS capped at 1 MB (ICNTL(23)) fails in its first factorisation: "auto" says so once,
    goes on with the iterative solver and reaches the direct solver's answer; "direct" fails."""
    from test_lung import averages, unit_cube

    capped = {"mat_mumps_icntl_23": 1}
    model, reference = unit_cube(0.5, cells=4), unit_cube(0.5, cells=4)
    solver = NewtonSolver(model, NewtonOptions(petsc_options=capped))
    with caplog.at_level("WARNING", logger="lungmech"):
        solve(model, Stepping(), solver=solver, monitor=lambda step: None)
    assert solver.linear_solver == "iterative"
    assert sum("ran out of memory" in r.message for r in caplog.records) == 1
    solve(reference, Stepping(), monitor=lambda step: None)
    assert averages(model)["J"] == pytest.approx(averages(reference)["J"], rel=1e-9)
    with pytest.raises(SolverError):
        solve(
            unit_cube(0.5, cells=4),
            Stepping(min_step=0.1),
            NewtonOptions(linear_solver="direct", petsc_options=capped),
            monitor=lambda step: None,
        )
