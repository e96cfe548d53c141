"""The poromechanical lung model against the cross-code unit cube and the closed form."""

import math

from mpi4py import MPI

import analytic as an
import dolfinx.mesh
import numpy as np
import pytest
from dolfinx import fem

from lungmech import lung
from lungmech.errors import ParameterError
from lungmech.fem.averages import means
from lungmech.fem.constraints import symmetry
from lungmech.fem.model import Model
from lungmech.fem.quantities import deformed_volume
from lungmech.fem.ramp import Ramp
from lungmech.fem.solver import Stepping, solve
from lungmech.lung import AlveolarPressure, Poromechanics, skeleton
from lungmech.lung.inverse import InverseOptions, unloaded_reference
from lungmech.mesh import box, nodes, rectangle
from lungmech.parallel.owned import owned_size

PARAMS = an.LungParams()  # α = 0.16, γ = 0.5, c1 = 0.2, c2 = 0.4, κ = 100, Φs0 = 0.5


def unit_cube(
    pressure: float, ramp: Ramp = Ramp(), comm=MPI.COMM_WORLD, plane: bool = False, cells: int = 2, **formulation
) -> Model:
    """VERIFICATION.md: symmetry on the three faces through the origin, the others free; or the
    unit square in plane strain (``plane``), symmetric on x = 0 and y = 0."""
    geometry = rectangle(comm, cells=(cells, cells)) if plane else box(comm, cells=(cells,) * 3)
    axes = "xy" if plane else "xyz"
    if "imaged_porosity" not in formulation:
        formulation.setdefault("phi_s0", PARAMS.phi_s0)
    return Model(
        geometry,
        skeleton(PARAMS.alpha, PARAMS.gamma, PARAMS.c1, PARAMS.c2),
        formulation=Poromechanics(formulation.pop("kappa", PARAMS.kappa), **formulation),
        constraints=[symmetry(f"{axis}0", axis) for axis in axes],
        loads=[AlveolarPressure(pressure, ramp)],
        plane="strain" if plane else None,
    )


def averages(model: Model) -> dict[str, float]:
    state = {name: mean() for name, (mean, _) in means(model).items()}
    # On the unit cube (volume 1) the mean Green–Lagrange strain is E_ii of the homogeneous state;
    # in plane strain E_zz = 0, so E_xx = E_yy is 3/2 of the mean.
    strain = state.pop("green_lagrange_mean") * (1.5 if model.plane else 1.0)
    return {"J": deformed_volume(model)(), "E": strain, **state}


def test_unit_cube_cross_code_reference():
    model = unit_cube(0.5)
    solve(model, Stepping(initial_step=0.25))
    state = averages(model)
    cross_code = {"J": 1.214217, "E": 0.0690725, "phi_s": 0.498753, "phi_f": 0.715464, "phi_s_current": 0.410761}
    for key, value in cross_code.items():
        assert state[key] == pytest.approx(value, rel=1e-4), key
    exact = an.lung_inflation(0.5, PARAMS)
    for key in cross_code:
        assert state[key] == pytest.approx(exact[key], rel=1e-10), key
    # Free faces: the total stress vanishes; the skeleton carries p_f, the solid bulk −p_f.
    assert state["mean_stress_skeleton"] == pytest.approx(0.5, rel=1e-10)
    assert state["mean_stress_bulk"] == pytest.approx(-0.5, rel=1e-10)
    assert abs(state["mean_stress_total"]) < 1e-10


def test_skeleton_stress_balances_alveolar_pressure_along_a_ramp():
    """σ_skel(J) = p_f at every step of an inspiration–expiration ramp (≥ 5 P–V points)."""
    ramp = Ramp((0.0, 1.0, 2.0), (0.0, 1.0, 0.2))
    model = unit_cube(0.8, ramp)
    volume = deformed_volume(model)
    curve = []
    solve(
        model,
        Stepping(end=2.0, initial_step=0.2, max_step=0.2),
        on_step=lambda s: curve.append((0.8 * ramp(s.time), volume())),
    )
    assert len(curve) >= 10
    for pressure, v in curve:
        assert v == pytest.approx(an.lung_inflation(pressure, PARAMS)["J"], rel=1e-10)


@pytest.mark.serial  # finite differences of this rank's rows
def test_residual_is_the_derivative_of_the_total_energy():
    """Central finite differences of Π along random directions equal the assembled residual."""
    model = unit_cube(0.5)
    solve(model, Stepping(end=0.5, initial_step=0.25))  # a non-trivial state, not an equilibrium of t = 1
    model.set_time(1.0)
    energy = fem.form(model.potential)
    residual = fem.form(model.residual)
    state = model.state.x.array
    base = state.copy()
    rng = np.random.default_rng(1)
    r = fem.assemble_vector(residual).array
    for _ in range(3):
        direction = rng.standard_normal(base.shape)
        h = 1e-6
        values = []
        for sign in (1, -1):
            state[:] = base + sign * h * direction
            values.append(fem.assemble_scalar(energy))
        state[:] = base
        n = owned_size(model.space)
        assert (values[0] - values[1]) / (2 * h) == pytest.approx(r[:n] @ direction[:n], rel=1e-6)


@pytest.mark.parametrize(("pressure", "bounds"), [(0.5, (0.5, 1.2)), (-0.3, (0.9, math.inf))])
def test_porosity_barrier_matches_the_closed_form(pressure, bounds):
    """Overdistension (inflated past r = 1.2) and collapse (deflated below r = 0.9) are resisted."""
    model = unit_cube(pressure, pore_barrier=0.1, pore_range=bounds)
    solve(model, Stepping(initial_step=0.25))
    state = averages(model)
    exact = an.lung_inflation_with_pore_barrier(pressure, PARAMS, 0.1, *bounds)
    free = an.lung_inflation(pressure, PARAMS)
    assert abs(exact["J"] - free["J"]) > 1e-3  # the barrier is active
    for key in ("J", "phi_s", "phi_f"):
        assert state[key] == pytest.approx(exact[key], rel=1e-9), key


def test_skeleton_scaled_by_the_solid_fraction():
    """W = Φs0 W_skel: the cube inflates like one whose α, c1, c2 are multiplied by Φs0."""
    model = unit_cube(0.2, scaling="skeleton")
    solve(model, Stepping(initial_step=0.25))
    scaled = an.LungParams(alpha=0.5 * PARAMS.alpha, c1=0.5 * PARAMS.c1, c2=0.5 * PARAMS.c2)
    assert averages(model)["J"] == pytest.approx(an.lung_inflation(0.2, scaled)["J"], rel=1e-10)


KEYS = ("J", "E", "phi_s", "phi_f", "phi_s_current")


@pytest.mark.parametrize("plane", [False, True], ids=["3-D", "plane strain"])
@pytest.mark.parametrize("scaling", ["none", "linear"])
def test_lung_cube_matches_its_closed_form(plane, scaling):
    """Free inflation, in 3-D and in plane strain (J = λ², λ3 = 1), with the skeleton, bulk and
    pore energies all scaled by Φs0 ("linear", as Patte et al. and dolfin_mech) or none:
    s_skel σ_skel(J) = p_f in the free directions, Φs = 1/(1/Φs0 + p_f/(s_bulk κ))."""
    model = unit_cube(0.4, plane=plane, scaling=scaling, phi_s0=0.3)
    solve(model, Stepping(), monitor=lambda step: None)
    state = averages(model)
    exact = an.lung_inflation(0.4, an.LungParams(phi_s0=0.3), scaling, plane)
    for key in KEYS:
        assert state[key] == pytest.approx(exact[key], rel=1e-9), key
    if scaling == "linear":  # Φs0 = 0.3 softens every energy: the lung inflates further
        assert exact["J"] > 1.05 * an.lung_inflation(0.4, an.LungParams(phi_s0=0.3), "none", plane)["J"]


@pytest.mark.parametrize(
    ("plane", "bounds", "exponent", "scaling"),
    [
        (False, (1.0, 1.0), 2.0, "linear"),  # dolfin_mech's barrier, n = p = q = 1, on Patte's scaling
        (True, (0.8, 1.1), 3.0, "none"),  # another exponent, in plane strain
    ],
)
def test_porosity_barrier_forms_match_the_closed_form(plane, bounds, exponent, scaling):
    model = unit_cube(0.5, plane=plane, scaling=scaling, pore_barrier=0.1, pore_range=bounds, pore_exponent=exponent)
    solve(model, Stepping(), monitor=lambda step: None)
    state = averages(model)
    exact = an.lung_inflation_with_pore_barrier(0.5, PARAMS, 0.1, *bounds, exponent, scaling, plane)
    free = an.lung_inflation(0.5, PARAMS, scaling, plane)
    assert abs(exact["J"] - free["J"]) > 1e-3  # the barrier is active
    for key in ("J", "phi_s", "phi_f"):
        assert state[key] == pytest.approx(exact[key], rel=1e-9), key


def test_bulk_modulus_and_barrier_as_fields():
    """κ(x) per cell: Φs = 1/(1/Φs0 + p_f/κ) in every cell, whatever the (inhomogeneous)
    deformation; a barrier field that is 0 everywhere changes nothing."""
    model = unit_cube(
        0.3, kappa=lambda x: 50.0 + 100.0 * x[0], pore_barrier=lambda x: 0.0 * x[0], pore_range=(0.99, 1.01)
    )
    solve(model, Stepping(), monitor=lambda step: None)
    kappa = model.formulation.kappa.x.array
    phi_s = model.state.sub(1).collapse().x.array
    assert np.ptp(kappa) > 50.0
    assert phi_s == pytest.approx(1 / (1 / PARAMS.phi_s0 + 0.3 / kappa), rel=1e-10)
    assert averages(model)["J"] == pytest.approx(an.lung_inflation(0.3, PARAMS)["J"], rel=1e-9)


def _imaged_porosity(x):
    return 0.6 + 0.2 * x[0] * x[1] + 0.05 * x[2]


@pytest.mark.parametrize("scaling", ["none", "linear"])
def test_inverse_problem_with_the_imaged_porosity_round_trips(scaling):
    """What CT gives: the loaded geometry and its porosity (here heterogeneous). The inverse
    problem finds the unloaded reference and Φs0 together; the direct problem from them gives
    back the imaged nodes and every cell's porosity."""
    imaged = unit_cube(0.5, cells=3, scaling=scaling, imaged_porosity=_imaged_porosity)
    nodes_imaged = imaged.geometry.mesh.geometry.x.copy()
    report = unloaded_reference(imaged, time=1.0, options=InverseOptions(tolerance=1e-11))
    assert report.iterations <= 15, report.mismatch
    assert report.porosity[-1] <= 1e-11

    direct = unit_cube(0.5, cells=3, scaling=scaling, phi_s0=0.5)
    direct.geometry.mesh.geometry.x[:] = imaged.geometry.mesh.geometry.x
    direct.formulation.phi_s0.x.array[:] = imaged.formulation.phi_s0.x.array
    direct.reset()
    solve(direct, Stepping(), monitor=lambda step: None)
    moved = direct.geometry.mesh.geometry.x + np.pad(
        nodes.sampler(direct.geometry.mesh)(direct.displacement()), ((0, 0), (0, 0))
    )
    assert np.abs(moved - nodes_imaged).max() <= 1e-8
    object.__setattr__(direct.formulation, "imaged_porosity", imaged.formulation.imaged_porosity)
    assert lung.poromechanics.ImagedPorosity(direct).mismatch() <= 1e-8


def test_inverse_problem_with_the_imaged_porosity_matches_the_closed_form():
    """A homogeneous lung imaged at p_f with porosity φ̂: its reference is the cube shrunk by
    J^(1/3), with σ_skel(J) = p_f, and Φs0 = 1/(1/Φs − p_f/κ), Φs = (1 − φ̂) J."""
    model = unit_cube(0.5, imaged_porosity=0.7)
    report = unloaded_reference(model, time=1.0, options=InverseOptions(tolerance=1e-12))
    J = an.lung_inflation(0.5, PARAMS)["J"]
    phi_s0 = 1 / (1 / ((1 - 0.7) * J) - 0.5 / PARAMS.kappa)
    assert model.geometry.volume() == pytest.approx(1 / J, rel=1e-10)
    assert model.formulation.phi_s0.x.array == pytest.approx(phi_s0, rel=1e-10)
    assert report.iterations <= 8


def _solid_fraction(x):
    return 0.35 + 0.3 * x[0] * x[1]


def test_heterogeneous_reference_fraction_from_a_function_and_from_a_file(tmp_path):
    """Φs solves ∂W_bulk/∂Φs = −p_f in every cell: Φs = 1/(1/Φs0 + p_f/κ), whatever the deformation."""
    model = unit_cube(0.3, phi_s0=_solid_fraction)
    solve(model, Stepping(initial_step=0.5))
    phi_s0 = model.formulation.phi_s0.x.array
    phi_s = model.state.sub(1).collapse().x.array
    assert np.ptp(phi_s0) > 0.1
    assert phi_s == pytest.approx(1 / (1 / phi_s0 + 0.3 / PARAMS.kappa), rel=1e-10)

    # The same field from a file, one value per cell in the mesh's input order.
    mesh = model.geometry.mesh
    midpoints = dolfinx.mesh.compute_midpoints(
        mesh, 3, np.arange(mesh.topology.index_map(3).size_local, dtype=np.int32)
    )
    values = np.zeros(mesh.topology.index_map(3).size_global)
    values[mesh.topology.original_cell_index[: len(midpoints)]] = _solid_fraction(midpoints.T)
    mesh.comm.Allreduce(MPI.IN_PLACE, values, op=MPI.SUM)  # every rank's cells, written once
    if mesh.comm.rank == 0:
        np.save(tmp_path / "phi_s0.npy", values)
    mesh.comm.Barrier()
    from_file = lung.reference_fraction(str(tmp_path / "phi_s0.npy"), mesh)
    assert from_file.x.array == pytest.approx(phi_s0, rel=1e-14)


def test_bad_reference_fractions(tmp_path):
    mesh = box(MPI.COMM_SELF, cells=(1, 1, 1)).mesh
    with pytest.raises(ParameterError, match=r"phi_s0 must lie in \(0, 1\) \(got values in \[0.75, 1.25\]\)"):
        lung.reference_fraction(lambda x: 0.5 + x[0], mesh)
    if MPI.COMM_WORLD.rank == 0:
        np.save(tmp_path / "short.npy", np.full(3, 0.5))
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(ParameterError, match="has 3 values; the mesh has 6 cells"):
        lung.reference_fraction(str(tmp_path / "short.npy"), mesh)
    with pytest.raises(ParameterError, match="not found"):
        lung.reference_fraction(str(tmp_path / "missing.npy"), mesh)
    with pytest.raises(ParameterError, match="pore_range"):
        Poromechanics(1.0, 0.5, pore_range=(1.2, 2.0))


def test_bad_lung_parameters():
    with pytest.raises(ParameterError, match="kappa"):
        Poromechanics(0.0, 0.5)
    with pytest.raises(ParameterError, match="phi_s0"):
        Poromechanics(100.0, 1.5)


def test_lung_scene_reproduces_the_closed_form(tmp_path):
    from lungmech.app import scene as scenes
    from lungmech.app.run import run

    scene = scenes.parse(
        {
            "geometry": {"builder": "box", "cells": [1, 1, 1]},
            "material": {"law": "lung_skeleton", "alpha": 0.16, "gamma": 0.5, "c1": 0.2, "c2": 0.4},
            "formulation": {"type": "poromechanics", "kappa": 100.0, "phi_s0": 0.5},
            "constraints": [
                {"type": "symmetry", "boundary": b, "component": c} for b, c in (("x0", "x"), ("y0", "y"), ("z0", "z"))
            ],
            "loads": [{"type": "alveolar_pressure", "value": 0.5}],
            "output": {"fields": False},
        }
    )
    summary = run(scene, tmp_path / "out")
    assert summary["deformed_volume"] == pytest.approx(an.lung_inflation(0.5, PARAMS)["J"], rel=1e-10)
    assert summary["formulation"] == "Poromechanics"
    assert (tmp_path / "out" / "pressure_volume.png").stat().st_size > 0
    last = (tmp_path / "out" / "history.csv").read_text().splitlines()
    header, row = last[0].split(","), dict(zip(last[0].split(","), last[-1].split(",")))
    assert "phi_s [1]" in header and float(row["phi_s [1]"]) == pytest.approx(
        an.lung_inflation(0.5, PARAMS)["phi_s"], rel=1e-10
    )


def test_lung_scene_errors():
    from lungmech.app import scene as scenes
    from lungmech.errors import SceneError

    base = {
        "geometry": {"builder": "box"},
        "material": {"law": "lung_skeleton", "alpha": 0.16, "gamma": 0.5, "c1": 0.2, "c2": 0.4},
    }
    with pytest.raises(SceneError, match="formulation.type: unknown type 'poro'"):
        scenes.parse({**base, "formulation": {"type": "poro"}})
    with pytest.raises(SceneError, match="formulation: poromechanics needs exactly one of phi_s0"):
        scenes.parse({**base, "formulation": {"type": "poromechanics", "kappa": 1.0}})
    with pytest.raises(SceneError, match="phi_s0"):
        scenes.parse({**base, "formulation": {"type": "poromechanics", "kappa": 1.0, "phi_s0": 2.0}})
    with pytest.raises(SceneError, match=r"material \(law 'lung_skeleton'\): missing key"):
        scenes.parse({**base, "material": {"law": "lung_skeleton", "alpha": 0.16}})
