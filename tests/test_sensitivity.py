"""Sensitivities dOutputs/dμ against central finite differences of whole solves (full and reduced)."""

from mpi4py import MPI

import dolfinx.jit
import numpy as np
import pytest

from lungmech import rom
from lungmech.errors import ParameterError
from lungmech.fem import FollowerPressure, Model, NeoHookean, Stepping, clamp, sensitivity
from lungmech.fem.constraints import Displacement, symmetry
from lungmech.fem.parameters import HalfSpace, Parameter
from lungmech.fem.parametric import FullOrderModel
from lungmech.lung import AlveolarPressure, Poromechanics, skeleton
from lungmech.mesh import box
from lungmech.parallel.owned import owned_size
from lungmech.rom.basis import origin, reference_state

STEPPING = Stepping(times=(0.5,))  # two output times: 0.5 and 1
RTOL = 1e-6  # the finite differences' truncation (h = 1e-4 of the range) is ~1e-8 here

BLOCK = [
    Parameter("E", "material.E", 10.0, (5.0, 20.0), unit="Pa"),  # Lamé constants from E and ν
    Parameter("nu", "material.nu", 0.3, (0.2, 0.4)),
    Parameter("p", "loads.push.value", 0.5, (0.1, 1.0), unit="Pa"),
    Parameter("a", "constraints.pull.amplitude", 1.0, (0.0, 2.0)),
    Parameter("soft", "material.E", 10.0, (1.0, 20.0), region=HalfSpace((1.0, 0.0, 0.0), "cut", 0.2)),
    Parameter("cut", "interface", 0.5, (0.2, 0.8), unit="m"),
]
BLOCK_MU = {"E": 12.0, "nu": 0.32, "p": 0.6, "a": 0.8, "soft": 6.0, "cut": 0.45}
LUNG = [
    Parameter("kappa", "formulation.kappa", 100.0, (50.0, 200.0), unit="Pa"),
    Parameter("eta", "formulation.pore_barrier", 1.0, (0.5, 2.0), unit="Pa"),
    Parameter("phi", "formulation.phi_s0", 0.5, (0.3, 0.6)),  # a Function of the forms
    Parameter("c1", "material.c1", 0.2, (0.1, 0.4), unit="Pa"),
    Parameter("pf", "loads.air.value", 0.5, (0.1, 1.0), unit="Pa"),
]
LUNG_MU = {"kappa": 120.0, "eta": 1.5, "phi": 0.45, "c1": 0.25, "pf": 0.6}
PROBES = [[1.0, 0.5, 0.5], [1.0, 1.0, 1.0]]


def block(comm=MPI.COMM_SELF, parameters=BLOCK, cells=(3, 2, 2)) -> Model:
    """A neo-Hookean block clamped at x = 0, pushed on x = 1 and pulled sideways there."""
    return Model(
        box(comm, cells=cells),
        lambda c: NeoHookean.from_young(c["E"], c["nu"]),
        constraints=[clamp("x0"), Displacement("x1", 0.05, component="y", name="pull")],
        loads=[FollowerPressure("x1", 0.5, name="push")],
        parameters=parameters,
    )


def lung() -> Model:
    """A poromechanical cube held at x = 0 (inflated unevenly), its porosity barrier active."""
    return Model(
        box(MPI.COMM_SELF, cells=(2, 2, 2)),
        skeleton(0.16, 0.5, 0.2, 0.4),
        formulation=Poromechanics(100.0, 0.5, pore_barrier=1.0, pore_range=(0.5, 1.3)),
        constraints=[clamp("x0"), symmetry("y0", "y"), symmetry("z0", "z")],
        loads=[AlveolarPressure(0.5, name="air")],
        parameters=LUNG,
    )


def outputs(solution) -> dict[str, np.ndarray]:
    """The outputs with sensitivities: all but the formulation's averages."""
    return {name: solution.outputs[name] for name in solution.outputs if not name.startswith("averages/")}


def finite_differences(model: FullOrderModel, mu: dict, name: str) -> dict[str, np.ndarray]:
    """Central differences of every output, h = 1e-4 of the parameter's range."""
    low, high = model.parameters.named(name).range
    h = 1e-4 * (high - low)
    up = outputs(model.solve(mu | {name: mu[name] + h}))
    down = outputs(model.solve(mu | {name: mu[name] - h}))
    return {key: (up[key] - down[key]) / (2 * h) for key in up}


def disagreement(exact: np.ndarray, approximate: np.ndarray) -> float:
    """max |exact − approximate| relative to the larger of the two (0 if both vanish)."""
    scale = max(np.abs(exact).max(), np.abs(approximate).max())
    return float(np.abs(exact - approximate).max() / scale) if scale > 0 else 0.0


def compared(full: FullOrderModel, mu: dict) -> dict:
    """The sensitivities at mu and the finite differences of every parameter."""
    solution = full.solve(mu, sensitivities=True)
    assert solution.parameter_names == full.parameters.names
    differences = {name: finite_differences(full, mu, name) for name in full.parameters.names}
    return {"solution": solution, "differences": differences}


@pytest.fixture(scope="module")
def blocks():
    return compared(FullOrderModel(block(), STEPPING, probes=PROBES), BLOCK_MU)


@pytest.fixture(scope="module")
def lungs():
    return compared(FullOrderModel(lung(), STEPPING, probes=[[1.0, 1.0, 1.0]]), LUNG_MU)


def check(case: dict, name: str) -> None:
    solution, differences = case["solution"], case["differences"][name]
    i = solution.parameter_names.index(name)
    assert set(solution.sensitivities) == set(differences)
    for key, exact in solution.sensitivities.items():
        assert exact.shape == (*solution.outputs[key].shape, len(solution.parameter_names)), key
        assert disagreement(exact[..., i], differences[key]) < RTOL, (name, key)


@pytest.mark.parametrize("name", [p.name for p in BLOCK])
def test_block_sensitivities_are_the_finite_differences(blocks, name):
    """Derived law constants (E, ν → Lamé), a follower pressure, an imposed displacement's
    amplitude, a region's value and the position of its interface."""
    check(blocks, name)


@pytest.mark.parametrize("name", [p.name for p in LUNG])
def test_poromechanics_sensitivities_are_the_finite_differences(lungs, name):
    """Formulation constants (κ, the porosity barrier η), the reference solid fraction (a field),
    a skeleton constant and the alveolar pressure."""
    check(lungs, name)


@pytest.mark.parametrize("case", ["blocks", "lungs"])
def test_a_wrong_derivative_fails(case, request):
    """Every parameter's sensitivities disagree with every other parameter's finite differences."""
    compared = request.getfixturevalue(case)
    solution = compared["solution"]
    for i, name in enumerate(solution.parameter_names):
        for other, differences in compared["differences"].items():
            if other != name:
                worst = max(disagreement(solution.sensitivities[k][..., i], differences[k]) for k in differences)
                assert worst > 1e-2, (name, other)


def test_the_loads_derivatives_are_exact_and_the_model_is_left_as_it_was(blocks):
    solution = blocks["solution"]
    push = solution.sensitivities["loads/push"]
    assert push[:, solution.parameter_names.index("p")] == pytest.approx([0.5, 1.0], rel=1e-10)  # ramp(t)
    assert np.count_nonzero(np.delete(push, solution.parameter_names.index("p"), axis=1)) == 0
    model = block()
    model.set_parameters(BLOCK_MU)
    FullOrderModel(model, STEPPING).solve(BLOCK_MU)
    model.set_time(0.7)
    before = model.state.x.array.copy(), dict(model.parameter_values), model.scalar_loads()
    imposed = model._imposed[1].target.x.array.copy()
    sensitivity.value_derivatives(model)
    assert np.array_equal(model.state.x.array, before[0])
    assert model.parameter_values == before[1] and model.scalar_loads() == before[2] and model.time == 0.7
    assert np.array_equal(model._imposed[1].target.x.array, imposed)


def test_another_mu_compiles_nothing(blocks, monkeypatch):
    full = FullOrderModel(block(), STEPPING, probes=PROBES)
    full.solve(BLOCK_MU, sensitivities=True)
    calls = []
    original = dolfinx.jit.ffcx_jit
    monkeypatch.setattr(dolfinx.jit, "ffcx_jit", lambda *a, **k: calls.append(1) or original(*a, **k))
    full.solve(BLOCK_MU | {"E": 8.0, "cut": 0.6}, sensitivities=True)
    assert calls == []


def test_reduced_sensitivities_are_those_of_the_reduced_model():
    """dq/dμ of a POD-Galerkin model: the finite differences of its own solves, not the full model's."""
    parameters = BLOCK[:4]
    model = block(parameters=parameters)
    full = FullOrderModel(model, Stepping())
    reference = reference_state(model)
    snapshots = []
    for mu in model.parameters.sample(8, seed=1):
        state = full.solve(mu).states[-1]
        snapshots.append(state - origin(model, reference)[: len(state)])
    basis = rom.pod(model, np.column_stack(snapshots), inner="l2", size=5)
    solver = rom.ReducedSolver(model, basis)
    reduced = FullOrderModel(model, Stepping(), solver=solver, probes=PROBES)
    mu = {name: BLOCK_MU[name] for name in model.parameters.names}
    reduced.solve(mu)
    values = sensitivity.value_derivatives(model)
    dq = sensitivity.reduced_state_derivatives(model, basis.vectors, solver.jacobian_form, values)
    assert dq.shape == (basis.size, len(parameters))
    dx = basis.vectors @ dq + values.imposed[: basis.vectors.shape[0]]
    derivatives = sensitivity.output_derivatives(model, reduced.outputs, solver, dx, values)
    direct = sensitivity.output_derivatives(model, reduced.outputs, solver)  # the full model's K at this state
    for i, name in enumerate(model.parameters.names):
        differences = finite_differences(reduced, mu, name)
        for key in ("volume", "strain_energy", "probes"):
            assert disagreement(derivatives[key][..., i], differences[key][-1]) < RTOL, (name, key)
        # the full model's derivative at the same state is another one: the basis is not complete
        assert disagreement(direct["probes"][..., i], differences["probes"][-1]) > 1e-3, name


def test_a_complete_basis_gives_the_direct_sensitivities():
    model = block(parameters=BLOCK[:4])
    solver = FullOrderModel(model, Stepping()).solver
    FullOrderModel(model, Stepping(), solver=solver).solve({"a": 0.8})
    owned = owned_size(model.space)
    free = np.setdiff1d(np.arange(owned), model.constrained_dofs())
    V = np.eye(owned)[:, free]
    values = sensitivity.value_derivatives(model)
    direct = sensitivity.state_derivatives(model, solver.jacobian_form, values)
    reduced = V @ sensitivity.reduced_state_derivatives(model, V, solver.jacobian_form, values)
    reduced += values.imposed[:owned]
    assert np.allclose(reduced, direct, rtol=1e-10, atol=1e-12 * np.abs(direct).max())


def test_loads_set_by_hand_are_refused():
    model = block()
    model.set_time(1.0)
    model._load_values[0].value = 0.3  # not what set_time sets
    with pytest.raises(ParameterError, match="not set by Model.set_time"):
        sensitivity.value_derivatives(model)


def test_load_derivatives_follow_the_load_factor():
    """A load path scaled by f (and taken about a reference time) scales the loads' derivatives
    alike: ∂p/∂μ at factor 0.5 about t₀ = 0.5 is half its change since t₀ (the ramp is t)."""
    model = block()
    model.set_time(1.0)
    whole = sensitivity.value_derivatives(model).loads["push"]
    model.set_time(1.0, load_factor=0.5, about=0.5)
    scaled = sensitivity.value_derivatives(model).loads["push"]
    np.testing.assert_allclose(scaled, (0.5 + 0.5 * (1.0 - 0.5)) * whole, rtol=1e-10, atol=1e-15)
    assert model.scalar_loads()["push"] == pytest.approx(0.75 * BLOCK[2].default)  # left as it was


@pytest.mark.mpi
def test_sensitivities_same_on_all_ranks_as_on_one():
    def sensitivities(comm) -> dict[str, np.ndarray]:
        full = FullOrderModel(block(comm), STEPPING, probes=PROBES)
        return full.solve(BLOCK_MU, sensitivities=True).sensitivities

    parallel, serial = sensitivities(MPI.COMM_WORLD), sensitivities(MPI.COMM_SELF)
    assert set(parallel) == set(serial)
    for key in serial:
        assert np.allclose(parallel[key], serial[key], rtol=1e-9, atol=1e-10 * np.abs(serial[key]).max()), key


@pytest.mark.parametrize("E, nu", [(12.0, 0.32), (5.0, 0.4), (20.0, 0.2)])
def test_derived_constants_differentiate_to_the_closed_form_also_at_the_ends_of_the_range(E, nu):
    """μ = E/2(1+ν), λ = Eν/((1+ν)(1−2ν)): linear in E (exact), not in ν (second order), and
    one-sided differences at the ends of the ranges stay inside them."""
    model = block(parameters=BLOCK[:2])
    model.set_parameters(E=E, nu=nu)
    derivatives = sensitivity.value_derivatives(model).constants
    mu, lam = derivatives[model.material.mu], derivatives[model.material.lmbda]
    assert mu == pytest.approx([1 / (2 * (1 + nu)), -E / (2 * (1 + nu) ** 2)], rel=1e-9)
    closed = [nu / ((1 + nu) * (1 - 2 * nu)), E * (1 + 2 * nu**2) / ((1 + nu) ** 2 * (1 - 2 * nu) ** 2)]
    assert lam == pytest.approx(closed, rel=1e-8)
