"""Gravity on the lung held at its hilum, with and without the balancing pleural pressure.

Independent reference: the reaction at the hilum, read from the residual at its nodes. Held
by the hilum alone, the lung hangs there (reaction = −weight); with the balancing pressure
the hilum carries nothing, in force and in moment.
"""

from mpi4py import MPI

import numpy as np
import pytest
from dolfinx import fem, la
from fem import MESHES

from lungmech.errors import ParameterError
from lungmech.fem.constraints import clamp
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.quantities import reaction
from lungmech.fem.solver import NewtonSolver, solve
from lungmech.fem.state_dependent import StateDependent
from lungmech.lung.gravity import Gravity
from lungmech.mesh import from_file

DENSITY, G = 300.0, np.array([0.0, 0.0, -9.81])
SURROUNDING = ("pleura", "diaphragm", "mediastinum")


@pytest.fixture(scope="module")
def lung():
    return from_file(MESHES / "lung_phantom_right.msh", MPI.COMM_WORLD)


def _hilum_reaction(lung, gravity):
    model = Model(lung, NeoHookean.from_young(1e4, 0.3), loads=[gravity], constraints=[clamp("hilum")])
    report = solve(model)
    return model, report, reaction(model, "hilum")()


@pytest.mark.slow
def test_without_balance_the_hilum_carries_the_weight(lung):
    weight = DENSITY * lung.volume() * G
    _, _, held = _hilum_reaction(lung, Gravity(DENSITY, G))
    assert held.force == pytest.approx(-weight, abs=1e-9 * np.linalg.norm(weight))


def test_balancing_pressure_leaves_the_hilum_unloaded(lung):
    weight = np.linalg.norm(DENSITY * lung.volume() * G)
    model, report, held = _hilum_reaction(lung, Gravity(DENSITY, G, balanced_on=SURROUNDING))
    assert np.linalg.norm(held.force) < 1e-9 * weight
    assert np.linalg.norm(held.moment) < 1e-9 * weight * lung.size
    sag = model.displacement().x.array.reshape(-1, 3)[:, 2]
    assert sag.min() < -1e-4  # the lung does deform under its weight and the pressure gradient
    assert report.newton_iterations < 80  # linear convergence of the lagged coefficients, bounded


def test_a_surface_that_cannot_balance_the_weight_is_an_error(lung):
    # The mediastinal face is flat: its pressure pushes along x only, never against a weight along z.
    with pytest.raises(ParameterError, match="no pressure on mediastinum can balance"):
        _hilum_reaction(lung, Gravity(DENSITY, G, balanced_on=("mediastinum",)))


@pytest.mark.serial  # finite differences of this rank's rows
def test_the_newton_tangent_is_the_derivative_of_the_balanced_residual(lung):
    """The low-rank tangent U Vᵀ d against central differences of R(u, Θ(u)) − R(u, θ frozen):
    the change of the residual through the coefficients alone. Newton's operator applies K + U Vᵀ."""
    model, _, _ = _hilum_reaction(lung, Gravity(DENSITY, G, balanced_on=SURROUNDING))
    coupled = StateDependent(model)
    form, vector = fem.form(model.residual), fem.Function(model.space).x
    rng = np.random.default_rng(1)
    free = np.ones(model.state.x.array.size, dtype=bool)
    for bc in model.bcs:
        free[bc.dof_indices()[0]] = False  # imposed dofs stay put
    x = model.state.x.array + 1e-3 * rng.standard_normal(free.size) * free
    d = rng.standard_normal(free.size) * free

    def residual(at: np.ndarray, update: bool) -> np.ndarray:
        model.state.x.array[:] = at
        if update:
            coupled.update()
        vector.array[:] = 0.0
        fem.assemble_vector(vector.array, form)
        vector.scatter_reverse(la.InsertMode.add)
        return vector.array[: coupled.owned].copy()

    residual(x, update=True)
    U, V = coupled.low_rank()
    h = 1e-6
    frozen = residual(x + h * d, False) - residual(x - h * d, False)  # θ = Θ(x)
    through_coefficients = (residual(x + h * d, True) - residual(x - h * d, True) - frozen) / (2 * h)
    expected = U @ (V.T @ d[: coupled.owned])
    rows = free[: coupled.owned]  # the imposed rows are the constraint's (U vanishes there)
    assert np.linalg.norm(expected) > 0 and not expected[~rows].any()
    assert np.linalg.norm((through_coefficients - expected)[rows]) < 1e-6 * np.linalg.norm(expected)

    # Newton's operator is K + U Vᵀ at the iterate
    solver = NewtonSolver(model)
    snes, problem = solver.problem.solver, solver.problem
    operator, K, _ = snes.getJacobian()
    at, direction = problem.x.duplicate(), problem.x.duplicate()
    at.array[:], direction.array[:] = x[: coupled.owned], d[: coupled.owned]
    snes.computeFunction(at, problem.b)
    snes.computeJacobian(at, operator, K)
    applied, frozen = at.duplicate(), at.duplicate()
    operator.mult(direction, applied)
    K.mult(direction, frozen)
    assert np.linalg.norm(applied.array - frozen.array - expected) < 1e-10 * np.linalg.norm(expected)


def test_balanced_gravity_converges_quadratically_in_one_newton_solve(lung):
    _, report, _ = _hilum_reaction(lung, Gravity(DENSITY, G, balanced_on=SURROUNDING))
    residuals = report.steps[0].residuals
    assert report.steps[0].iterations <= 6
    # r_{k+1} / r_k² stays bounded while r falls by orders of magnitude: quadratic, not linear
    rates = [np.log(r2 / r1) / np.log(r1 / r0) for r0, r1, r2 in zip(residuals, residuals[1:], residuals[2:])]
    assert max(rates) > 1.7, residuals


def test_another_mesh_of_the_same_kind_reuses_the_compiled_forms():
    """The balancing pressure's forms hold no number of the mesh (its length L is a Constant):
    a larger lung (another patient) has the same UFL signatures, the key of the FFCx cache."""
    from lungmech.mesh.nodes import move

    def signatures(scale: float) -> set[str]:
        geometry = from_file(MESHES / "lung_phantom_right.msh", MPI.COMM_WORLD)
        move(geometry.mesh, (scale - 1.0) * geometry.mesh.geometry.x[:, :3])
        model = Model(
            geometry,
            NeoHookean.from_young(1e4, 0.3),
            loads=[Gravity(DENSITY, G, balanced_on=SURROUNDING)],
            constraints=[clamp("hilum")],
        )
        assert geometry.size == pytest.approx(scale * lung_size)
        return {model.residual.signature(), model.jacobian.signature()}

    lung_size = from_file(MESHES / "lung_phantom_right.msh", MPI.COMM_WORLD).size
    assert signatures(1.0) == signatures(1.3)


@pytest.mark.parametrize("rank", [6, 4])
def test_the_least_correction_is_the_smallest_pressure_that_balances(rank):
    """The balance's KKT solve (by LU, or by the pseudo-inverse where it is singular) against
    an independent least-norm solution: c = argmin cᵀNc over A c = t, b free. With A of full
    rank it balances exactly; with A of rank 4 (a boundary that cannot carry every moment) its
    force and moment are the closest A can give, as the least-squares balance."""
    from scipy.optimize import minimize

    from lungmech.lung.gravity import _NORM, _least_correction

    rng = np.random.default_rng(rank)
    A = rng.standard_normal((6, 9)) * np.array([1e2, 1e2, 1e2, 1e3, 1e3, 1e3])[:, None]  # m² and m³ rows
    if rank < 6:
        A[rank:] = 0.0
    target = A @ rng.standard_normal(9) if rank < 6 else rng.standard_normal(6) * 50
    c, multipliers, inverse = _least_correction(A, target)
    assert np.all(np.isfinite(c)) and inverse.shape == (15, 15) and multipliers.shape == (6,)
    np.testing.assert_allclose(A @ c, target, rtol=1e-9, atol=1e-9 * np.abs(target).max())
    constraint = {"type": "eq", "fun": lambda x: (A @ x - target)[:rank] / np.abs(target).max()}
    reference = minimize(lambda x: x @ _NORM @ x, c + 0.1, constraints=[constraint], method="SLSQP", tol=1e-14).x
    assert c @ _NORM @ c <= reference @ _NORM @ reference * (1 + 1e-6) + 1e-12
