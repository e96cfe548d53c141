"""A PGD model answers solve(μ) like every model (lungmech.pgd.model): against the scene's full
model at random points of its box, along its load path, with its load factor and its
sensitivities; saved and loaded through the model files, refused on another mesh or
physics; `lungmech pgd build` and `lungmech rom solve --set/--sweep` on it (one online path)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest

from lungmech.app import reduce
from lungmech.app import scene as scenes
from lungmech.app.cli import main
from lungmech.app.pgd import build as build_file
from lungmech.app.recipe import recipe_scene
from lungmech.app.run import build_model, full_order_model
from lungmech.errors import ModelFileError, ParameterError
from lungmech.fem.solver import Stepping
from lungmech.pgd.axes import Axis
from lungmech.pgd.greedy import Options
from lungmech.pgd.model import build
from lungmech.pgd.terms import constants, values
from lungmech.pgd.values import closed_form, joined

# A steel-like beam 2 × 0.5 × 0.5 m clamped at x = 0, under its weight (turned by the pitch, over
# a full turn) and a dead pressure on its free end; E over a factor 10: displacements of mm.
SCENE = """
title = "a linear elastic beam under its own weight and an end pressure"
[geometry]
builder = "box"
cells = [{cells}, 3, 3]
lengths = [2.0, 0.5, 0.5]
[material]
law = "linear"
E = 3e6
nu = 0.3
[[constraints]]
type = "clamp"
boundary = "x0"
[[loads]]
type = "gravity"
name = "gravity"
density = 1000.0
acceleration = [0.0, 0.0, -9.81]
[[loads]]
type = "normal_pressure"
name = "tip"
boundary = "x1"
value = {tip}
[stepping]
end = 1.0
max_step = 0.5
times = [0.5]
[parameters.E]
target = "material.E"
range = [1e6, 1e7]
scale = "log"
[parameters.pitch]
target = "loads.gravity.pitch"
range = [-180.0, 180.0]
[parameters.tip]
target = "loads.tip.value"
range = [-2e3, 2e3]
[output]
probes = [[2.0, 0.25, 0.25], [1.0, 0.5, 0.5]]
"""
# the splines' error, relative, on 32 intervals (the default): in the values 1.8e-6 at these points
# (16: 2.9e-5; 64: 1.3e-7), in their derivatives 7.9e-3 (16: 5.2e-2; 64: 4.4e-4)
CLOSE, SLOPES = 2e-5, 2e-2


def written(folder: Path, cells: int = 8, tip: float = 500.0, name: str = "beam.toml") -> Path:
    path = folder / name
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(SCENE.format(cells=cells, tip=tip))
    MPI.COMM_WORLD.barrier()
    return path


@pytest.fixture(scope="module")
def beam(tmp_path_factory):
    """The scene, its PGD model (built in Python) and its full model."""
    folder = tmp_path_factory.mktemp(f"pgd-model-{MPI.COMM_WORLD.size}")
    folder = Path(MPI.COMM_WORLD.bcast(str(folder)))
    scene = scenes.load(written(folder))
    model, _ = build(build_model(scene), scene.stepping, scene.output.probes)
    return folder, scene, model, full_order_model(scene)


def relative(found: np.ndarray, exact: np.ndarray, denominator: float) -> float:
    return float(np.abs(np.asarray(found) - np.asarray(exact)).max() / denominator)


def test_a_pgd_model_answers_as_the_full_model_at_random_points_of_its_box(beam):
    """At 6 Sobol' points: the volume (over its change), the strain energy, the probes (over
    their motion) and the end pressure as applied, at both output times; and their derivatives
    in μ (over the largest of each), the splines' own."""
    _, scene, pgd, full = beam
    assert pgd.describe()["solver"].startswith("PGD evaluation")
    for point in pgd.parameters.sample(6, seed=4):
        a, b = pgd.solve(point, sensitivities=True), full.solve(point, sensitivities=True)
        assert np.array_equal(a.times, b.times) and list(a.times) == [0.5, 1.0]
        change = np.abs(b.outputs["volume"] - a.start.details["volume"]).max()
        assert relative(a.outputs["volume"], b.outputs["volume"], change) < CLOSE
        assert (
            relative(a.outputs["strain_energy"], b.outputs["strain_energy"], b.outputs["strain_energy"].max()) < CLOSE
        )
        assert relative(a.outputs["probes"], b.outputs["probes"], np.abs(b.outputs["probes"]).max()) < CLOSE
        assert np.allclose(a.outputs["loads/tip"], b.outputs["loads/tip"], rtol=1e-14)
        for name in ("volume", "strain_energy", "probes", "loads/tip"):
            exact = b.sensitivities[name]
            assert relative(a.sensitivities[name], exact, np.abs(exact).max()) < SLOPES, name
        assert a.newton_iterations == 0 and a.start.kind == "rest"


def test_each_answer_carries_the_indicator_at_its_point(beam):
    """η(μ) of an answer, from the residual's Gram matrix (no assembly), is the full residual's
    dual norm at the PGD's state (lungmech.pgd.indicator) at 5 Sobol' points: to round-off on a
    PGD of 2 terms (η about 4e-3 and more), within 2e-9 on the converged one (η about 2e-7: the
    Gram form's cancellation and its floor, measured 7.5e-10); the same at any output time and
    load factor, with or without the fem model set (the residual scales with the state); a
    model file keeps it."""
    from lungmech.pgd.indicator import indicator
    from lungmech.rom.basis import inner_product

    folder, scene, pgd, _ = beam
    points = pgd.parameters.sample(5, seed=6)
    coarse, _ = build(build_model(scene), scene.stepping, options=Options(max_terms=2))
    for model, rtol, atol in ((coarse, 1e-9, 0.0), (pgd, 0.0, 2e-9)):
        W = inner_product(model.model, "energy")
        try:
            model.model.set_time(scene.stepping.end)
            exact = indicator(model.model, model.decomposition, W, points)
        finally:
            W.destroy()
        found = np.array([model.solve(point).indicator for point in points])
        assert np.allclose(found, exact, rtol=rtol, atol=atol) and np.all(found > 0), (found, exact)
        assert len(set(found.round(12))) == len(found)  # one per point, not one for all
        assert model.solve(points[0], times=[0.5], scale=0.3).indicator == pytest.approx(found[0], rel=1e-12)
        set_model = model.solve(points[0], scale=0.3, sensitivities=True).indicator  # the values read at s = 0.3
        assert set_model == pytest.approx(found[0], rel=1e-9, abs=atol)
    path = folder / "indicated.npz"
    build_file(scene, path, modes=6)
    loaded = reduce.load(path, fields=True)
    assert loaded.online.residual.shape == pgd.online.residual.shape
    found = np.array([loaded.solve(point).indicator for point in points])
    assert np.allclose(found, exact, rtol=0.0, atol=2e-9), (found, exact)


def test_its_path_and_load_factor_are_the_linear_models(beam):
    """Any time of the path and a load factor: the full model's answer there (linear, from rest,
    one ramp); several factors for the loads are refused in one line."""
    _, _, pgd, full = beam
    point = {"E": 2e6, "pitch": 75.0, "tip": -800.0}
    a = pgd.solve(point, times=[0.3], scale=0.5)
    b = full.solve(point, times=[0.3], scale=0.5)
    assert relative(a.outputs["probes"], b.outputs["probes"], np.abs(b.outputs["probes"]).max()) < CLOSE
    assert a.outputs["loads/tip"][0] == pytest.approx(0.3 * 0.5 * -800.0)
    pgd.fields(a.states[-1], 0.3)  # the field of that answer: the fem model at its parameters and loads
    assert pgd.model.parameter_values == pgd.parameters.values(point)
    assert pgd.model.scalar_loads()["tip"] == pytest.approx(0.3 * 0.5 * -800.0)
    with pytest.raises(ParameterError, match="one finite load factor for every load"):
        pgd.solve(point, scale=[1.0, 2.0])
    with pytest.raises(ParameterError, match=r"'E' = 2e\+07 Pa is outside its range"):
        pgd.solve({"E": 2e7})
    steps = []
    pgd.solve(point, on_step=steps.append)
    assert [s.phase for s in steps] == ["start", "path", "path"] and steps[0].state().sum() == 0.0


def test_a_model_it_cannot_answer_is_refused_in_one_line_before_any_work(beam, tmp_path):
    """Loads not at rest at the path's start, no parameter, no interval."""
    _, scene, _, _ = beam
    model = build_model(scene)
    with pytest.raises(ParameterError, match="ramp is 0.5, not 0, at the path's start"):
        build(model, Stepping(start=0.5, end=1.0))
    with pytest.raises(ParameterError, match="intervals"):
        build(model, scene.stepping, intervals=0)
    bare = tmp_path / "bare.toml"  # (one folder for every rank: rank 0 writes)
    if MPI.COMM_WORLD.rank == 0:
        bare.write_text(SCENE.format(cells=4, tip=1.0).split("[parameters.E]")[0])
    MPI.COMM_WORLD.barrier()
    plain = scenes.load(bare)
    with pytest.raises(ParameterError, match="no parameters to separate"):
        build(build_model(plain), plain.stepping)


def test_a_pgd_file_is_built_and_solved_through_the_cli_like_the_full_model(beam, tmp_path, capsys):
    """`pgd build` writes a model file; `rom solve --set` answers as `run --set` does (the
    summary's volume, energy and probes), and `rom solve --sweep` at each row; a second build
    of the file replaces it, another file is not replaced."""
    folder, scene, _, _ = beam
    tmp = Path(MPI.COMM_WORLD.bcast(str(tmp_path)))
    model = tmp / "pgd.npz"
    assert main(["pgd", "build", str(scene.source), "-o", str(model), "--modes", "6"]) == 0
    assert "separated terms on" in capsys.readouterr().out
    given = ["--set", "E=4e6", "--set", "pitch=-120", "--set", "tip=300"]
    assert main(["rom", "solve", str(model), *given, "-o", str(tmp / "pgd-run")]) == 0
    assert main(["run", str(scene.source), *given, "-o", str(tmp / "full-run")]) == 0
    a, b = (json.loads((tmp / name / "summary.json").read_text()) for name in ("pgd-run", "full-run"))
    motion = np.abs(b["probes"]["displacement"]).max()
    assert relative(a["probes"]["displacement"], b["probes"]["displacement"], motion) < CLOSE
    assert abs(a["deformed_volume"] - b["deformed_volume"]) < CLOSE * abs(b["deformed_volume"] - b["start_volume"])
    assert a["strain_energy"] == pytest.approx(b["strain_energy"], rel=CLOSE)
    assert 0 < a["error_indicator"] < 1e-3 and b["error_indicator"] is None  # the PGD's estimate of itself
    points = tmp / "points.csv"
    if MPI.COMM_WORLD.rank == 0:
        points.write_text("E,pitch,tip\n4e6,-120,300\n1e6,180,-2000\n")
    MPI.COMM_WORLD.barrier()
    assert main(["rom", "solve", str(model), "--sweep", str(points), "-o", str(tmp / "sweep")]) == 0
    rows = list(csv.DictReader((tmp / "sweep" / "sweep.csv").read_text().splitlines()))
    assert [(row["point [1]"], row["time [s]"]) for row in rows] == [(p, t) for p in "01" for t in ("0.5", "1.0")]
    assert float(rows[1]["volume [m^3]"]) == a["deformed_volume"]  # the same solve(μ)
    assert main(["pgd", "build", str(scene.source), "-o", str(model), "--modes", "6"]) == 0  # its own file
    assert main(["pgd", "build", str(scene.source), "-o", str(scene.source)]) == 2
    assert "saved as .npz" in capsys.readouterr().err


def test_a_pgd_file_is_refused_on_another_mesh_or_physics(beam, tmp_path):
    folder, scene, pgd, _ = beam
    tmp = Path(MPI.COMM_WORLD.bcast(str(tmp_path)))
    path = tmp / "beam.npz"
    build_file(scene, path, modes=4)
    loaded = reduce.load(path)
    point = {"E": 5e6, "pitch": 10.0, "tip": 0.0}
    assert np.allclose(loaded.solve(point).outputs["probes"], pgd.solve(point).outputs["probes"], rtol=1e-12, atol=0)
    finer = scenes.load(written(tmp, cells=10, name="finer.toml"))
    with pytest.raises(ModelFileError, match=r"other physics than this scene's: geometry.cells: \[8.0, 3.0, 3.0\]"):
        reduce.reduced_order(path)(finer, MPI.COMM_WORLD)
    with pytest.raises(ModelFileError, match="is an a priori PGD; a patient's model is fitted to its own breaths"):
        with recipe_scene(path, None):
            pass
    with pytest.raises(ModelFileError, match="another mesh"):  # (given as its own scene: the mesh is checked)
        reduce.reduced_order(path, inside=True)(finer, MPI.COMM_WORLD)
    other = scenes.load(written(tmp, tip=900.0, name="other.toml"))
    with pytest.raises(ModelFileError, match="other physics"):
        reduce.reduced_order(path)(other, MPI.COMM_WORLD)


@pytest.mark.mpi
def test_a_build_on_every_rank_equals_the_serial_one(beam):
    """The scene's PGD model distributed and on each rank alone (COMM_SELF): the same outputs
    and derivatives at random points, to 1e-9; the indicator (about 2e-7 here, near its
    round-off floor) to 2e-9."""
    _, scene, pgd, _ = beam
    alone, _ = build(build_model(scene, MPI.COMM_SELF), scene.stepping, scene.output.probes)
    assert alone.decomposition.terms == pgd.decomposition.terms
    for point in pgd.parameters.sample(4, seed=9):
        a, b = pgd.solve(point, sensitivities=True), alone.solve(point, sensitivities=True)
        assert a.indicator == pytest.approx(b.indicator, rel=0.0, abs=2e-9) and a.indicator > 0
        for name in ("volume", "strain_energy", "probes"):
            assert relative(a.outputs[name], b.outputs[name], np.abs(b.outputs[name]).max()) < 1e-9, name
            exact = b.sensitivities[name]
            assert relative(a.sensitivities[name], exact, np.abs(exact).max()) < 1e-9, name


def test_the_values_in_closed_form_are_the_models_and_refused_where_none_holds(beam):
    """The moduli (linear in E) and the end pressure (its value) in closed form equal the model's
    own at random points, so an answer need not set the fem model (the same answer as with its
    sensitivities, which does); gravity turned by the pitch has one, by pitch and roll one with
    a term in their products (cos p sin r), a Lamé constant of the Poisson ratio none. Forms
    joined into one give each one's values, stacked."""
    _, scene, pgd, _ = beam
    assert pgd._closed is not None
    for point in pgd.parameters.sample(5, seed=31):
        quick, set_model = pgd.solve(point), pgd.solve(point, sensitivities=True)
        for name in ("strain_energy", "loads/tip", "volume"):
            assert np.allclose(quick.outputs[name], set_model.outputs[name], rtol=1e-12, atol=0), name
    for model, pairs in ((build_model(scene), 0), (with_parameter(scene, "roll", "loads.gravity.roll", [-30, 30]), 1)):
        model.set_time(1.0)  # the loads at the path's end (0 at its start)
        weight = [c for c in constants(model) if np.size(c.value) == 3]  # ρg, turned by the posture
        axes = tuple(Axis(p, 8) for p in model.parameters)
        read = lambda: np.concatenate([np.ravel(c.value) for c in weight])  # noqa: B023, E731
        form = closed_form(model, axes, read)
        assert form is not None and len(form.pairs) == pairs  # the pitch alone: cos and sin; with the roll, products
        stiffness = lambda: np.array([model.parameter_values["E"]])  # noqa: B023, E731  (no pair: zeros in the joined one's)
        moduli, nothing = (closed_form(model, axes, r) for r in (stiffness, lambda: np.zeros(0)))
        assert moduli is not None and nothing is not None and not moduli.pairs
        together, ends = joined([moduli, nothing, form])
        assert ends == [len(moduli.base), len(moduli.base), len(moduli.base) + len(form.base)]
        for point in model.parameters.sample(6, seed=5):
            model.set_parameters(point)
            assert np.allclose(form(point), read(), rtol=0.0, atol=1e-12 * np.abs(read()).max())
            assert np.allclose(together(point), np.concatenate([moduli(point), form(point)]), rtol=1e-14, atol=0)
    model = with_parameter(scene, "nu", "material.nu", [0.1, 0.45])
    axes = tuple(Axis(p, 8) for p in model.parameters)
    assert closed_form(model, axes, lambda: values(model)) is None  # λ = Eν/((1+ν)(1−2ν))


def with_parameter(scene, name, target, box):
    """The scene's model with one more parameter (the roll: gravity turned by pitch and roll)."""
    table = dict(scene.table) | {
        "parameters": dict(scene.table["parameters"]) | {name: {"target": target, "range": box}}
    }
    return build_model(scenes.parse(table, folder=Path(scene.source).parent))
