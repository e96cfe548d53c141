"""The a priori PGD of a nonlinear model (lungmech.pgd.newton, lungmech.pgd.sampled): Newton
iterations on the parameters' Gauss grid, residual assemblies and no full solve, answer the
poromechanical lung under a follower pressure, that lung balanced under its weight and a
neo-Hookean block at finite strain as their full models do at random points; on a linear model
it is the linear greedy's answer; bad inputs get one line."""

from __future__ import annotations

from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest
from fem import PARAMETRIC_SCENE, write_once
from test_pgd import STIFFNESS, relative_errors
from test_pgd_fitted import LUNG, against_full, written

from lungmech.app import reduce
from lungmech.app import scene as scenes
from lungmech.app.cli import main
from lungmech.app.run import build_model, full_order_model
from lungmech.errors import ParameterError
from lungmech.fem.constraints import clamp
from lungmech.fem.laws import LinearElastic
from lungmech.fem.model import Model
from lungmech.fem.newton import NewtonSolver
from lungmech.fem.parameters import Parameter, Parameters
from lungmech.fem.ramp import Ramp
from lungmech.fem.stepping import Stepping
from lungmech.lung.gravity import Gravity
from lungmech.mesh import box
from lungmech.pgd import Options
from lungmech.pgd.axes import Axis
from lungmech.pgd.model import build as linear_build
from lungmech.pgd.newton import QUADRATURE, Newton, build_nonlinear, quadrature

# The tests' parametric neo-Hookean block (tests/fem.py), pulled at its free end by a follower
# pressure up to 18 % strain, over its stiffness (a factor 4, log) and the pull's amplitude; 135 dofs.
BLOCK = (
    PARAMETRIC_SCENE.replace("cells = [6, 2, 2]", "cells = [4, 2, 2]")
    .replace(
        'type = "traction"\nboundary = "x1"\nvalue = [0.0, 0.0, -10.0]',
        'type = "follower_pressure"\nboundary = "x1"\nvalue = -60.0\n'
        "ramp = { times = [0.0, 1.0], values = [0.0, 1.0] }",
    )
    .replace("range = [0.5, 5.0]", "range = [0.5, 1.5]")
    .replace("fields = false", "fields = false\nprobes = [[2.0, 0.5, 0.5]]")
    + "[stepping]\nend = 1.0\nmax_step = 0.25\ntimes = [0.5]\n"
)


def block(folder: Path) -> Path:
    """The block's scene file in ``folder`` (every rank's)."""
    return write_once(folder / "block.toml", BLOCK)


# The lung phantom's breath (poromechanics, the lung skeleton's law, a follower pleural pressure)
# under its weight, carried by a pleural pressure gradient whose coefficients move with the
# state, over its stiffness and its posture; 1,810 dofs.
BALANCED = (
    LUNG.format(low=0.6)
    .split("[parameters.alpha]")[0]
    .replace("mesh_size = 0.03", "mesh_size = 0.04")
    .replace("over three parameters", "balanced under its weight, over its stiffness and posture")
    + """[[loads]]
type = "gravity"
name = "gravity"
density = 315.0
acceleration = [0.0, 0.0, -9.81]
balanced_on = ["pleura", "diaphragm", "mediastinum"]
ramp = { times = [0.0, 1.0], values = [0.0, 1.0] }
[parameters.c1]
target = "material.c1"
range = [100.0, 400.0]
scale = "log"
[parameters.posture]
target = "loads.gravity.pitch"
range = [-90.0, 0.0]
"""
)


def balanced(folder: Path) -> Path:
    """The balanced lung's scene file in ``folder`` (every rank's)."""
    return write_once(folder / "balanced.toml", BALANCED)


@pytest.fixture(scope="module")
def lung(tmp_path_factory):
    """The lung phantom's breath (tests/test_pgd_fitted.py: poromechanics, the lung skeleton's
    law, a follower pleural pressure; α, c1 and the breath's depth) built a priori by the CLI,
    one cubic an axis (its Gauss grid: 64 points), while any Newton solve of the full model would raise; loaded
    from its file."""
    folder = Path(MPI.COMM_WORLD.bcast(str(tmp_path_factory.mktemp("pgd-newton"))))
    scene_file = written(folder)
    out = folder / "lung-newton.npz"

    def no_full_solve(*args, **kwargs):
        raise AssertionError("the a priori PGD solved the full model")

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(NewtonSolver, "solve", no_full_solve)
        assert main(["pgd", "build", str(scene_file), "--intervals", "1", "-o", str(out), "-q"]) == 0
    return reduce.load(out, fields=True), full_order_model(scenes.load(scene_file))


@pytest.mark.slow
def test_the_a_priori_lung_answers_as_its_full_model(lung):
    """At 8 random points of the box and both output times: the state's relative energy-norm
    error ≤ 1e-3 (measured: 4.6e-5), the volume, probe and strain energy within 1e-3 (7.2e-5); the
    answers' indicator (the model's residual at the PGD's answers, the largest at 16 points)
    within a factor 5 of the largest error."""
    pgd, full = lung
    errors, outputs, answers = against_full(pgd, full, 8, seed=7)
    assert max(errors) <= 1e-3, max(errors)
    assert max(outputs) <= 1e-3, max(outputs)
    assert pgd.built["quadrature"] == 64 and len(pgd.built["newton_iterations"]) == 2
    assert max(errors) / 5 <= answers[0].indicator <= 5 * max(errors)


@pytest.mark.slow
def test_a_lung_balanced_under_its_weight(tmp_path):
    """The balanced lung over its stiffness (a factor 4) and posture (−90° to 0°), on its 16
    Gauss points: the Newton–PGD, each iteration taking every point's tangent at its state on
    the modes' span (no tangent held over the box converges here: benchmarks/pgd_tangent.py),
    answers at 6 random points and both output times within 1e-2 of its full model (state in
    the energy norm; volume, probe and strain energy; measured: 1.8e-3 and 4.6e-3), its
    estimate within a factor 5 of its largest error."""
    scene = scenes.load(balanced(tmp_path))
    full = full_order_model(scene)
    pgd, _ = build_nonlinear(full.model, scene.stepping, scene.output.probes, 1, Options(max_terms=20))
    assert pgd.built["method"].endswith("the tangents at their states")
    errors, outputs, answers = against_full(pgd, full, 6, seed=5)
    assert max(errors) <= 1e-2, max(errors)
    assert max(outputs) <= 1e-2, max(outputs)
    assert max(errors) / 5 <= answers[0].indicator <= 5 * max(errors)


def test_on_a_linear_model_newton_is_the_linear_greedy():
    """A linear beam under gravity over its stiffness and a roll of ±30°: the Newton–PGD on the
    axes' Gauss grid solves the linear greedy's own Galerkin problem (the tangent is the
    operator), so it stops after its second iteration and both answer alike at random points
    (to 1e-4 of the state, their greedies' own tolerance), and as the full model does."""
    roll = Parameter("roll", "loads.gravity.roll", 0.0, (-30.0, 30.0))
    parameters = Parameters([STIFFNESS, roll])
    model = Model(
        box(MPI.COMM_WORLD, cells=(8, 3, 3), lengths=(2.0, 0.5, 0.5)),
        lambda c: LinearElastic.from_young(c["E"], 0.3),
        constraints=[clamp("x0")],
        loads=[Gravity(1.0, (0.0, 0.0, -9.81), name="gravity", ramp=Ramp(times=(0.0, 1.0), values=(0.0, 1.0)))],
        parameters=parameters,
    )
    stepping = Stepping(start=0.0, end=1.0, max_step=1.0)
    options = Options(max_terms=8, tolerance=1e-8)
    newton, _ = build_nonlinear(model, stepping, (), 2, options)
    greedy, _ = linear_build(model, stepping, (), 2, options)
    assert newton.built["newton_iterations"] == [2]
    points = parameters.sample(6, seed=41)
    for point in points:
        a, b = newton.solve(point, times=[1.0]), greedy.solve(point, times=[1.0])
        assert np.abs(a.states[0] - b.states[0]).max() <= 1e-4 * np.abs(b.states[0]).max()
    model.set_time(1.0)
    last = newton.decomposition  # one output time: its terms are the answer's
    assert relative_errors(model, last, points).max() <= 2e-3


@pytest.mark.parametrize(
    ("intervals", "points", "measured"),
    [(2, QUADRATURE, "1.2e-4"), (4, 64, "2.2e-5")],
    ids=["the Gauss grid (64 points)", "64 Sobol' points (the grid has 256)"],
)
def test_a_block_at_finite_strain(tmp_path, intervals, points, measured):
    """The neo-Hookean block: at 6 random points and both output times within 1e-3 of its full
    model (state in the energy norm, volume, probe and strain energy; measured: ``measured``),
    on the axes' Gauss grid or on Sobol' points where the grid is larger than the quadrature
    asked; the derivatives in μ are the splines' own (against central differences of the PGD,
    1e-5)."""
    scene = scenes.load(block(tmp_path))
    full = full_order_model(scene)
    newton = Newton(quadrature=points)
    pgd, _ = build_nonlinear(full.model, scene.stepping, scene.output.probes, intervals, Options(max_terms=12), newton)
    assert pgd.built["quadrature"] == min(points, (4 * intervals) ** 2)
    errors, outputs, _ = against_full(pgd, full, 6, seed=3)
    assert max(errors) <= 1e-3, max(errors)
    assert max(outputs) <= 1e-3, max(outputs)
    point = {"stiffness": 800.0, "pull": 1.2}
    found = pgd.solve(point, sensitivities=True).sensitivities["probes"][-1]
    for j, name in enumerate(pgd.parameters.names):
        h = 1e-4 * point[name]
        ahead = pgd.solve(point | {name: point[name] + h}).outputs["probes"][-1]
        behind = pgd.solve(point | {name: point[name] - h}).outputs["probes"][-1]
        assert np.allclose(found[..., j], (ahead - behind) / (2 * h), rtol=1e-5, atol=1e-12)


def test_the_quadrature_is_the_axes_gauss_grid_or_sobol_points(tmp_path):
    """The box's quadrature: the tensor product of the axes' Gauss rules (weights summing to 1,
    exact for a product of degree-7 polynomials on each axis), or the model's own Sobol' points
    with equal weights where that grid has more points than asked — refused in one line where
    they are too few to determine an axis's splines."""
    model = build_model(scenes.load(block(tmp_path)))
    axes = [Axis(parameter, 2) for parameter in model.parameters]
    grid = quadrature(model, axes, Newton())
    assert grid.units.shape == (64, 2) and grid.weights.sum() == pytest.approx(1.0, rel=1e-14)
    assert grid.weights @ (grid.units[:, 0] ** 7 * grid.units[:, 1] ** 4) == pytest.approx(1 / 40, rel=1e-13)
    sobol = quadrature(model, axes, Newton(quadrature=32, seed=5))
    expected = [model.parameters.to_unit(p) for p in model.parameters.sample(32, seed=5)]
    assert np.allclose(sobol.units, expected) and np.all(sobol.weights == 1 / 32)
    fine = [Axis(parameter, 8) for parameter in model.parameters]  # 11 splines an axis
    with pytest.raises(ParameterError, match="8 Sobol' points do not determine the 11 splines of axis 'stiffness'"):
        quadrature(model, fine, Newton(quadrature=8))


def test_bad_inputs_of_a_nonlinear_pgd_get_one_line(tmp_path, capsys):
    """Iterations that do not converge, their step halved down to 1/16 of the path (from the
    first output time, 0.5 s), and a quadrature of too few points, are refused in one line; the
    model file is not written."""
    scene = scenes.load(block(tmp_path))
    full = full_order_model(scene)
    with pytest.raises(
        ParameterError,
        match=r"did not converge at t = 0.0625 s in 1 iterations .*, its step from t = 0 s halved to 0.0625 of the path",
    ):
        build_nonlinear(full.model, scene.stepping, (), 1, Options(max_terms=4), Newton(iterations=1))
    out = tmp_path / "block.npz"
    assert main(["pgd", "build", str(block(tmp_path)), "--quadrature", "4", "-o", str(out)]) != 0
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "quadrature" in error[0] and not out.exists()
