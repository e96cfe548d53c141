"""The hyper-reduced model online: Newton in q on a reduced mesh of the sampled cells, outputs
from reduced operators (lungmech.rom.reduced_mesh, lungmech.rom.outputs). It never reads or
writes the full state; its volume and probes are the full model's functionals of its state to
round-off, its strain energy within a few τ; imposed displacements that move with time are
covered exactly."""

from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh

from lungmech import rom
from lungmech.errors import ParameterError
from lungmech.fem.constraints import Displacement, clamp
from lungmech.fem.loads import BodyForce, FollowerPressure, Traction
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.parametric import FullOrderModel, Outputs
from lungmech.fem.ramp import Ramp
from lungmech.fem.solver import Stepping
from lungmech.mesh import box, rectangle
from lungmech.parallel.owned import owned_size
from lungmech.rom.basis import origin, reference_state
from lungmech.rom.ecsw import Training
from lungmech.rom.exact import cubic
from lungmech.rom.outputs import imposed_directions
from lungmech.rom.reduced import ReducedModel
from lungmech.rom.reduced_mesh import ReducedMesh

STEPPING = Stepping(max_step=0.25, times=(0.25, 0.5, 0.75))
PROBES = [(3.0, 1.0, 1.0), (1.5, 0.5, 0.5)]
TOLERANCE = 1e-4


def stretched(comm=MPI.COMM_WORLD) -> Model:
    """A block clamped at x = 0 and pulled along x at x = 3 by an imposed displacement that
    grows with time, sheared by its weight and pressed by a follower pressure on its top."""
    return Model(
        box(comm, lengths=(3.0, 1.0, 1.0), cells=(12, 4, 4)),
        NeoHookean.from_young(10.0, 0.3),
        constraints=[clamp("x0"), Displacement("x1", (0.3, 0.0, 0.0), ramp=Ramp((0.0, 1.0), (0.0, 1.0)))],
        loads=[BodyForce((0.0, 0.0, -0.2)), FollowerPressure("z1", 0.2), Traction("y1", (0.0, 0.0, -0.1))],
    )


def hyper_reduced(make=stretched, comm=MPI.COMM_WORLD):
    """The full, Galerkin and hyper-reduced (τ = 1e-4) models of ``make(comm)``, trained on its
    load path (converged states and Newton iterates)."""
    model = make(comm)
    full = FullOrderModel(model, STEPPING, probes=PROBES)
    owned = owned_size(model.space)
    states = []

    def keep(step) -> None:
        states.append((model.state.x.array.copy(), model.time))

    from lungmech.fem.solver import solve

    model.reset()
    solve(model, STEPPING, solver=full.solver, on_step=keep, monitor=lambda step: None)
    basis = rom.pod(
        model,
        np.column_stack([x[:owned] - origin(model, reference_state(model))[:owned] for x, _ in states]),
        inner="energy",
        size=8,
    )
    training = Training(model, basis.vectors)
    with training.watching(full.solver):
        model.reset()
        solve(model, STEPPING, solver=full.solver, monitor=lambda step: None)
    sample = training.sample(TOLERANCE)
    galerkin = ReducedModel(make(comm), basis, STEPPING, probes=PROBES)
    hyper = ReducedModel(make(comm), basis, STEPPING, probes=PROBES, sample=sample)
    return full, galerkin, hyper


@pytest.fixture(scope="module")
def models():
    return hyper_reduced()


def test_the_hyper_reduced_solve_never_touches_the_full_state(models):
    """The model's state is NaN through a whole hyper-reduced solve: every output is finite,
    and the state is still NaN (nothing read it, nothing wrote it)."""
    _, _, hyper = models
    state = hyper.model.state.x.array
    state[:] = np.nan
    solution = hyper.solve()
    assert np.isnan(state).all()
    for name, values in solution.outputs.items():
        assert np.isfinite(values).all(), name
    assert hyper.solver.mesh.cells.size == np.unique(np.concatenate(list(hyper.sample.cells.values()))).size


def test_its_outputs_are_the_full_functionals_of_its_state(models):
    """At every output time: the volume (a cubic in q and the imposed displacement's factor) and
    the probes (linear) equal the full model's of the reconstructed state x₀ + V q to round-off;
    the strain energy, an ECSW functional, is within 5 τ of it."""
    _, _, hyper = models
    solution = hyper.solve()
    outputs = Outputs(hyper.model, PROBES)
    for index in range(len(solution.times)):
        hyper.reconstruct(solution, index)
        exact = outputs()
        assert solution.outputs["volume"][index] == pytest.approx(exact["volume"], rel=1e-12)
        assert (
            np.abs(solution.outputs["probes"][index] - exact["probes"]).max() <= 1e-12 * np.abs(exact["probes"]).max()
        )
        assert solution.outputs["strain_energy"][index] == pytest.approx(exact["strain_energy"], rel=5 * TOLERANCE)


def test_it_tracks_the_galerkin_and_full_models(models):
    """Outputs within a few τ of the Galerkin model's on the training path; the Galerkin model
    within its own (basis) error of the full one."""
    full, galerkin, hyper = models
    f, g, h = full.solve(), galerkin.solve(), hyper.solve()
    for name in ("volume", "strain_energy", "probes"):
        scale = np.abs(f.outputs[name]).max()
        assert np.abs(h.outputs[name] - g.outputs[name]).max() <= 10 * TOLERANCE * scale, name
        assert np.abs(g.outputs[name] - f.outputs[name]).max() <= 1e-6 * scale, name
    assert np.linalg.norm(h.states[-1] - g.states[-1]) <= 10 * TOLERANCE * np.linalg.norm(g.states[-1])


def test_the_reduced_mesh_holds_the_sampled_cells_and_their_dofs():
    """On P2: every sub dof sits where its full dof does; a residual integrated over the cells
    is the same on the reduced mesh as on the full one, dof by dof (cell and facet integrals)."""
    model = Model(
        box(MPI.COMM_SELF, lengths=(3.0, 1.0, 1.0), cells=(6, 2, 2)),
        NeoHookean.from_young(10.0, 0.3),
        degree=2,
        constraints=[clamp("x0")],
        loads=[FollowerPressure("z1", 0.3)],
    )
    model.state.interpolate(lambda x: 0.05 * np.array([x[1] * x[2], x[0] ** 2 / 9, np.sin(x[0])]))
    cells = np.array([0, 5, 17, 40, 71], dtype=np.int32)
    reduced = ReducedMesh(model, cells)
    full_coordinates = model.space.tabulate_dof_coordinates()
    blocks = reduced.parent_dofs[::3] // 3
    assert np.abs(reduced.space.tabulate_dof_coordinates() - full_coordinates[blocks]).max() < 1e-14
    mesh = model.geometry.mesh
    tags = dmesh.meshtags(mesh, 3, cells, np.ones(len(cells), dtype=np.int32))
    facets = model.geometry.facet_tags
    mesh.topology.create_connectivity(3, 2)
    ours = np.unique(np.concatenate([mesh.topology.connectivity(3, 2).links(c) for c in cells]))
    keep = np.isin(facets.indices, ours)
    on_cells = dmesh.meshtags(mesh, 2, facets.indices[keep], facets.values[keep])
    integrals = [
        i.reconstruct(subdomain_id=1, subdomain_data=tags)
        if i.integral_type() == "cell"
        else i.reconstruct(subdomain_data=on_cells)
        for i in model.residual.integrals()
    ]
    residual = ufl.Form(integrals)
    whole = fem.assemble_vector(fem.form(residual)).array
    reduced.state.x.array[:] = reduced.restrict(model.state.x.array)
    sub = fem.assemble_vector(reduced.form(residual)).array
    assert np.abs(sub - whole[reduced.parent_dofs]).max() <= 1e-13 * np.abs(whole).max()
    assert np.abs(np.delete(whole, reduced.parent_dofs)).max() == 0.0  # nothing outside the cells


def test_the_volume_is_an_exact_cubic_of_the_coordinates():
    """∫ det F dX at x = r + Z z: the cubic from k + 2 assemblies against the assembled volume at
    random z (not the one it checks itself); in 2-D (plane strain) a quadratic, C₃ = 0; and a
    functional of higher degree (∫ J² dX, a sextic) is refused."""
    rng = np.random.default_rng(5)
    for model in (
        Model(box(MPI.COMM_WORLD, cells=(3, 3, 3)), NeoHookean.from_young(1.0, 0.3)),
        Model(rectangle(MPI.COMM_WORLD, cells=(4, 4)), NeoHookean.from_young(1.0, 0.3), plane="strain"),
    ):
        owned = owned_size(model.space)
        start = reference_state(model)
        Z = np.random.default_rng(MPI.COMM_WORLD.rank).uniform(
            -0.05, 0.05, (owned, 4)
        )  # rng draws the same z everywhere
        volume = ufl.det(model.F) * model.dx
        polynomial = cubic(model, volume, start, Z)
        compiled = fem.form(volume)
        for _ in range(3):
            z = rng.uniform(-2.0, 2.0, 4)
            model.state.x.array[:] = start
            model.state.x.array[:owned] += Z @ z
            model.state.x.scatter_forward()
            exact = MPI.COMM_WORLD.allreduce(fem.assemble_scalar(compiled), op=MPI.SUM)
            assert polynomial(z) == pytest.approx(exact, rel=1e-12)
            step = 1e-6 * rng.standard_normal(4)
            assert polynomial(z + step) - polynomial(z - step) == pytest.approx(
                2 * polynomial.gradient(z) @ step, rel=1e-6
            )
        if model.plane is not None:
            assert np.abs(polynomial.c3).max() <= 1e-12 * np.abs(polynomial.c2).max()
        with pytest.raises(ParameterError, match="not a cubic polynomial"):
            cubic(model, ufl.det(model.F) ** 2 * model.dx, start, Z)


def test_imposed_displacements_are_affine_in_their_factors():
    """origin(x₀) = r + D a(t) at every time, with a clamp and a moving boundary sharing the
    edge dofs (the later condition wins there, in both); the clamp gets no direction."""
    model = stretched()
    reference = reference_state(model)
    r, D, kept = imposed_directions(model, reference)
    assert list(kept) == [1]
    for t in (0.0, 0.3, 1.0):
        model.set_time(t)
        assert np.abs(origin(model, reference) - (r + D @ model.imposed_amplitudes()[kept])).max() == 0.0


@pytest.mark.slow
def test_hyper_reduced_sensitivities_are_those_of_its_own_answer():
    assert_sensitivities_of_own_answer(MPI.COMM_SELF)


def assert_sensitivities_of_own_answer(comm) -> None:
    """d(outputs)/dμ of the hyper-reduced model (its sampled residual, tangent and energy, the
    cubic volume, the linear probes) against central differences of its own solves: for the
    Young's modulus and Poisson's ratio (law constants), a follower pressure (a load value), an
    imposed displacement's amplitude (dx₀/dμ), a region's stiffness and an interface's position
    (Functions of the forms)."""
    from test_sensitivity import BLOCK, BLOCK_MU, PROBES, RTOL, block, disagreement, finite_differences

    def parametric_block(parameters) -> Model:  # test_sensitivity's block, on a finer mesh
        return block(comm, parameters, cells=(6, 3, 3))

    from lungmech.fem.solver import NewtonSolver

    stepping = Stepping(times=(0.5,))
    model = parametric_block(parameters=BLOCK)
    reference = reference_state(model)
    owned = owned_size(model.space)
    solver = NewtonSolver(model)
    full = FullOrderModel(model, stepping, solver=solver)
    points = model.parameters.sample(8, seed=1)
    snapshots = [(state - origin(model, reference)[:owned]) for mu in points for state in full.solve(mu).states]
    basis = rom.pod(model, np.column_stack(snapshots), inner="energy", size=8)
    training = Training(model, basis.vectors)
    with training.watching(solver):
        for mu in points:
            full.solve(mu)
    sample = training.sample(1e-3)
    cells = model.geometry.mesh.topology.index_map(3).size_global
    assert sample.count(MPI.COMM_WORLD)["internal"] < cells / 4  # a sample, not every cell
    hyper = ReducedModel(parametric_block(parameters=BLOCK), basis, stepping, probes=PROBES, sample=sample)
    solution = hyper.solve(BLOCK_MU, sensitivities=True)
    for i, name in enumerate(hyper.parameters.names):
        differences = finite_differences(hyper, BLOCK_MU, name)
        for key in ("volume", "strain_energy", "probes"):
            assert disagreement(solution.sensitivities[key][..., i], differences[key]) < RTOL, (name, key)


def test_each_solve_starts_afresh_at_its_own_loads(models):
    """A second solve takes the same path as the first: the automatic first step measures F at
    the start's loads, not at the loads the last solve ended with."""
    _, _, hyper = models
    first, second = hyper.solve(), hyper.solve()
    assert first.newton_iterations == second.newton_iterations
    for name in first.outputs:
        assert np.abs(first.outputs[name] - second.outputs[name]).max() <= 1e-12 * np.abs(first.outputs[name]).max()


def test_a_failed_path_leaves_a_consistent_model(models):
    """Up to t = 0.5 s, then Newton allowed one iteration and steps no shorter than 0.5 s: the
    path fails with one clear error, and the model holds x₀ + V q of its last equilibrium at
    t = 0.5 s, its moved boundary included, and so does the solver."""
    from lungmech.errors import SolverError
    from lungmech.fem.solver import NewtonOptions, solve
    from lungmech.rom.hyper_reduced import HyperReducedSolver

    _, _, hyper = models
    model = stretched()
    solver = HyperReducedSolver(model, hyper.basis, hyper.sample)
    solve(model, Stepping(end=0.5, max_step=0.25), solver=solver, monitor=lambda step: None)
    equilibrium = solver.state.copy()
    solver.options = NewtonOptions(max_iterations=1)
    with pytest.raises(SolverError, match="the load path stopped at t = 0.5 s"):
        solve(model, Stepping(start=0.5, initial_step=0.5, min_step=0.5), solver=solver, monitor=lambda step: None)
    assert model.time == 0.5 and np.array_equal(solver.state, equilibrium) and np.abs(equilibrium).max() > 0
    owned = hyper.basis.vectors.shape[0]  # the basis has this rank's owned rows
    expected = origin(model, reference_state(model))[:owned] + hyper.basis.vectors @ equilibrium
    assert np.abs(model.state.x.array[:owned] - expected).max() <= 1e-14


def test_a_full_order_model_refuses_a_solver_of_reduced_coordinates(models):
    from lungmech.rom.hyper_reduced import HyperReducedSolver

    _, _, hyper = models
    model = stretched()
    with pytest.raises(ParameterError, match="iterates on reduced coordinates"):
        FullOrderModel(model, STEPPING, solver=HyperReducedSolver(model, hyper.basis, hyper.sample))


def test_outside_a_solve_it_evaluates_at_the_current_loads(models):
    """F (for the automatic first step) and the sampled functionals are evaluated at the loads
    of the moment, not at those of the last solve: back at t = 0 after a path that ended with
    the boundary moved, q = 0 is the start state on the reduced mesh, dof by dof."""
    _, _, hyper = models
    hyper.solve()
    model, solver = hyper.model, hyper.solver
    at_end = solver.mesh.state.x.array.copy()
    model.set_time(0.0)
    solver.set_state(np.zeros(hyper.basis.size))
    start = solver.mesh.restrict(origin(model, reference_state(model)))
    assert np.abs(at_end - start).max() > 0.1  # the reduced mesh holds moved boundary dofs
    solver.deformation_gradient()
    assert np.abs(solver.mesh.state.x.array - start).max() == 0.0
    model.set_time(1.0)
    solver.functionals(np.zeros(hyper.basis.size))
    assert np.abs(solver.mesh.state.x.array - solver.mesh.restrict(origin(model, reference_state(model)))).max() == 0.0


def weighed_lung(comm=MPI.COMM_WORLD) -> Model:
    """The right-lung phantom held at its hilum, under its weight balanced by a pleural pressure
    gradient (whose coefficients are whole-body integrals of the state) and a pleural pressure."""
    from fem import MESHES

    from lungmech.lung.gravity import Gravity
    from lungmech.mesh import from_file

    surrounding = ("pleura", "diaphragm", "mediastinum")
    return Model(
        from_file(MESHES / "lung_phantom_right.msh", comm),
        NeoHookean.from_young(1e4, 0.3),
        constraints=[clamp("hilum")],
        loads=[Gravity(300.0, (0.0, 0.0, -9.81), balanced_on=surrounding), FollowerPressure(surrounding, -500.0)],
    )


def assert_balanced_gravity_reduces(comm) -> ReducedModel:
    """Balanced gravity, hyper-reduced: its moments exactly (affine in q), the pressure's
    response over its own ECSW sample. The hyper-reduced model tracks the Galerkin one within a
    few τ; its tangent, with the rank-12 term of the sampled coefficients, is the derivative of
    its residual; and the hilum of its reconstructed state carries the Galerkin state's load to a few τ of
    the weight."""
    from lungmech.fem.quantities import reaction
    from lungmech.fem.solver import NewtonSolver

    probes = [(0.05, 0.0, 0.16)]
    model = weighed_lung(comm)
    solver = NewtonSolver(model)
    full = FullOrderModel(model, STEPPING, solver=solver, probes=probes)
    basis = rom.pod(model, np.array(full.solve().states).T, inner="energy", size=8)
    training = Training(model, basis.vectors)
    with training.watching(solver):
        full.solve()
    sample = training.sample(TOLERANCE)
    assert 0 < sample.count(comm)["load0_response"] < 100
    galerkin = ReducedModel(weighed_lung(comm), basis, STEPPING, probes=probes)
    hyper = ReducedModel(weighed_lung(comm), basis, STEPPING, probes=probes, sample=sample)
    g, h = galerkin.solve(), hyper.solve()
    # the tangent is the derivative of the sampled residual, θ = Θ(q) included (central differences)
    solver = hyper.solver
    q = solver.state.copy()
    solver.reduced_residual(q)
    tangent = solver.reduced_jacobian()
    step = 1e-6 * np.linalg.norm(q)
    columns = [
        (solver.reduced_residual(q + step * e) - solver.reduced_residual(q - step * e)) / (2 * step)
        for e in np.eye(q.size)
    ]
    assert np.linalg.norm(np.column_stack(columns) - tangent) <= 1e-6 * np.linalg.norm(tangent)
    for name in ("volume", "strain_energy", "probes"):
        assert np.abs(h.outputs[name] - g.outputs[name]).max() <= 10 * TOLERANCE * np.abs(g.outputs[name]).max(), name
    held = []  # the hilum carries the pleural pressure's resultant over its gap, not the weight
    for reduced, solution in ((galerkin, g), (hyper, h)):
        reduced.reconstruct(solution, len(solution.times) - 1)
        held.append(reaction(reduced.model, "hilum")().force)
    weight = 300.0 * hyper.model.geometry.volume() * 9.81
    assert np.linalg.norm(held[1] - held[0]) <= 10 * TOLERANCE * weight
    return hyper


@pytest.mark.slow
def test_balanced_gravity_reduces():
    """And what it cannot do is said before any work: a sample without the pressure's response
    (trained on another model). (Its sensitivities: tests/test_imaged_sensitivity.py.)"""
    from lungmech.rom.ecsw import Sample
    from lungmech.rom.hyper_reduced import HyperReducedSolver

    hyper = assert_balanced_gravity_reduces(MPI.COMM_WORLD)
    partial = Sample(
        {k: v for k, v in hyper.sample.cells.items() if k != "load0_response"},
        {k: v for k, v in hyper.sample.weights.items() if k != "load0_response"},
        TOLERANCE,
    )
    with pytest.raises(ParameterError, match="no cells for load0_response"):
        HyperReducedSolver(weighed_lung(), hyper.basis, partial)
