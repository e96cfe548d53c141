"""One problem, one online path: the command line answers what ``solve(μ)`` answers.

An imaged body (a scene with [inverse]) is the loaded state at the start *for every μ*: ``run
--set`` and ``FullOrderModel.solve(μ)`` solve that one problem, and agree. The run records what
the model reports — the loads as applied (a load amplitude set as a parameter included) in
history.csv, summary.json and the P–V curve — for a full, a reduced and a swept model alike; a
static answer (``--at T``, ``solve(μ, times=[T])``) is the path's state at T.
"""

import csv
import json

from mpi4py import MPI

import numpy as np
import pytest

from lungmech.app import plot
from lungmech.app import reduce as reduce_app
from lungmech.app import run as run_app
from lungmech.app import scene as scenes
from lungmech.app.cli import main

PLEURAL = -300.0  # Pa, at the start (ramp 1 → 2)

IMAGED = f"""title = "imaged cube"
[geometry]
builder = "box"
cells = [2, 2, 2]
[material]
law = "lung_skeleton"
alpha = 160.0
gamma = 0.5
c1 = 200.0
c2 = 400.0
[formulation]
type = "poromechanics"
kappa = 1.0e4
phi_s0 = 0.3
[[constraints]]
type = "symmetry"
boundary = "x0"
component = "x"
[[constraints]]
type = "symmetry"
boundary = "y0"
component = "y"
[[constraints]]
type = "symmetry"
boundary = "z0"
component = "z"
[[loads]]
type = "follower_pressure"
boundary = ["x1", "y1", "z1"]
value = {PLEURAL}
name = "pleural"
ramp = {{ times = [0.0, 1.0], values = [1.0, 2.0] }}
[inverse]
tolerance = 1e-10
[stepping]
end = 1.0
times = [0.5]
[output]
fields = false
probes = [[0.9, 0.9, 0.9]]
[parameters.stiffness]
target = "material.c1"
range = [100.0, 400.0]
scale = "log"
[parameters.depth]
target = "loads.pleural.amplitude"
range = [0.5, 2.0]
"""

MU = {"stiffness": 300.0, "depth": 1.5}  # not the defaults (200 Pa, 1)


def _scene(folder, text=IMAGED, name="scene.toml"):
    path = folder / name
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(text)
    MPI.COMM_WORLD.barrier()
    return path


def _sets(mu):
    return [item for name, value in mu.items() for item in ("--set", f"{name}={value}")]


def _history(folder):
    with open(folder / "history.csv") as stream:
        return list(csv.DictReader(stream))


@pytest.fixture(scope="module")
def imaged(tmp_path_factory):
    folder = MPI.COMM_WORLD.bcast(tmp_path_factory.mktemp("imaged"))
    return _scene(folder)


@pytest.fixture
def pressure_volume_data(monkeypatch):
    """What the P–V plot is drawn from, as the plot receives it."""
    drawn = []
    original = plot.pressure_volume
    monkeypatch.setattr(
        run_app, "pressure_volume", lambda p, v, *args, **kw: drawn.append((p, v)) or original(p, v, *args, **kw)
    )
    return drawn


def test_run_set_and_the_full_order_model_solve_the_same_imaged_problem(imaged, tmp_path):
    """run --set and FullOrderModel.solve(μ) agree, and at every μ the start is the image: its
    deformed volume is the mesh's (1 m³), whatever the stiffness or the pressure."""
    out = tmp_path / "run"
    assert main(["run", str(imaged), "-o", str(out), "-q", *_sets(MU)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["start"]["kind"] == "imaged" and summary["parameters"] == MU
    full = run_app.full_order_model(scenes.load(imaged))
    answer = full.solve(MU)
    assert summary["outputs"]["time"] == pytest.approx([0.5, 1.0], abs=1e-12)
    assert summary["outputs"]["volume"] == pytest.approx(answer.outputs["volume"], rel=1e-10)
    assert np.array(summary["outputs"]["probes"]) == pytest.approx(answer.outputs["probes"], rel=1e-8, abs=1e-12)
    for mu in (MU, {"stiffness": 120.0, "depth": 0.6}, full.parameters.defaults):
        solution = full.solve(mu, times=[0.0])
        assert solution.start.details["volume"] == pytest.approx(1.0, abs=1e-8)  # the image, m³
        assert solution.outputs["volume"][0] == pytest.approx(1.0, abs=1e-8)
    again = full.solve(MU)  # after other μ: the answer is a function of μ alone
    assert again.outputs["volume"] == pytest.approx(answer.outputs["volume"], rel=1e-12)
    deeper = full.solve(MU | {"depth": 2.0})
    assert deeper.outputs["volume"][-1] > answer.outputs["volume"][-1]  # a larger pull inflates more


def test_a_load_parameter_is_recorded_as_applied(imaged, tmp_path, pressure_volume_data):
    """--set depth=1.5 scales the pleural pressure: history.csv, summary.json and the P–V curve
    all carry −300 Pa × 1.5 × ramp(t), not the scene's −300 Pa × ramp(t)."""
    out = tmp_path / "run"
    assert main(["run", str(imaged), "-o", str(out), "-q", *_sets(MU)]) == 0
    rows = _history(out)
    times = np.array([float(r["time [s]"]) for r in rows])
    applied = PLEURAL * MU["depth"] * (1.0 + times)
    assert np.array([float(r["pleural [Pa]"]) for r in rows]) == pytest.approx(applied, rel=1e-12)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["outputs"]["loads/pleural"] == pytest.approx(PLEURAL * MU["depth"] * np.array([1.5, 2.0]))
    if MPI.COMM_WORLD.rank == 0:
        pressures, volumes = pressure_volume_data[-1]
        assert pressures == pytest.approx(-applied, rel=1e-12)  # P_L = p_alv − p_pl = −p_pl
        assert volumes == pytest.approx([float(r["volume [m^3]"]) for r in rows], rel=1e-12)


def test_a_static_answer_is_the_path_at_that_time(imaged, tmp_path):
    """--at T and solve(μ, times=[T]): the equilibrium at T, the same as the whole path's at T."""
    full = run_app.full_order_model(scenes.load(imaged))
    whole = full.solve(MU)
    at = full.solve(MU, times=[0.5])
    assert at.times.tolist() == [0.5]
    assert at.outputs["volume"][0] == pytest.approx(whole.outputs["volume"][0], rel=1e-10)
    out = tmp_path / "at"
    assert main(["run", str(imaged), "-o", str(out), "-q", "--at", "0.5", *_sets(MU)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["outputs"]["time"] == [0.5]
    assert summary["outputs"]["volume"] == pytest.approx(at.outputs["volume"], rel=1e-10)
    assert max(float(r["time [s]"]) for r in _history(out)) == pytest.approx(0.5)


def test_times_outside_the_path_are_refused(imaged, tmp_path, capsys):
    assert main(["run", str(imaged), "-o", str(tmp_path / "x"), "-q", "--at", "3"]) == 2
    said = capsys.readouterr().err
    assert said.count("\n") == 1 and "--at 3 s lies outside the scene's load path [0, 1] s" in said
    full = run_app.full_order_model(scenes.load(imaged))
    with pytest.raises(Exception, match=r"time -1 s lies outside the model's load path \[0, 1\] s"):
        full.solve(times=[-1.0])
    with pytest.raises(Exception, match="sensitivities of an imaged body"):
        full.solve(sensitivities=True)


PRESSED = (
    IMAGED.replace("[inverse]\ntolerance = 1e-10\n", "")
    .replace(
        'law = "lung_skeleton"\nalpha = 160.0\ngamma = 0.5\nc1 = 200.0\nc2 = 400.0',
        'law = "neo_hookean"\nE = 1.0e3\nnu = 0.3',
    )
    .replace('type = "poromechanics"\nkappa = 1.0e4\nphi_s0 = 0.3\n', 'type = "displacement"\n')
    .replace('target = "material.c1"\nrange = [100.0, 400.0]', 'target = "material.E"\nrange = [500.0, 2000.0]')
    .replace(f"value = {PLEURAL}", "value = -30.0")
)


@pytest.mark.slow
def test_rom_solve_and_sweep_answer_the_same_rows(tmp_path, pressure_volume_data):
    """A reduced model's rom solve and --sweep at one μ give the same numbers at the output
    times; both carry the pressure as applied (amplitude 1.5)."""
    scene = _scene(tmp_path, PRESSED)
    model = tmp_path / "m.npz"
    assert main(["rom", "build", str(scene), "-o", str(model), "--samples", "4", "--size", "6", "-q"]) == 0
    mu = {"stiffness": 900.0, "depth": 1.5}
    out = tmp_path / "solve"
    assert main(["rom", "solve", str(model), "-o", str(out), "-q", "--fields", *_sets(mu)]) == 0  # and its P–V plot
    summary = json.loads((out / "summary.json").read_text())
    rows = _history(out)
    at_outputs = [r for r in rows if float(r["time [s]"]) in (0.5, 1.0)]
    points = _scene(tmp_path, "stiffness [Pa],depth\n900,1.5\n", "points.csv")
    swept = tmp_path / "swept"
    assert main(["rom", "solve", str(model), "--sweep", str(points), "-o", str(swept), "-q"]) == 0
    with open(swept / "sweep.csv") as stream:
        table = list(csv.DictReader(stream))
    for name in ("volume [m^3]", "strain_energy [J]", "pleural [Pa]", "probe0_uz [m]"):
        mine = [float(r[name]) for r in at_outputs]
        assert mine == pytest.approx([float(r[name]) for r in table], rel=1e-12), name
    assert summary["outputs"]["loads/pleural"] == pytest.approx([-30.0 * 1.5 * 1.5, -30.0 * 1.5 * 2.0])
    times = np.array([float(r["time [s]"]) for r in rows])
    assert [float(r["pleural [Pa]"]) for r in rows] == pytest.approx(-30.0 * 1.5 * (1 + times), rel=1e-12)
    if MPI.COMM_WORLD.rank == 0:
        assert pressure_volume_data[-1][0] == pytest.approx(-30.0 * 1.5 * (1 + times), rel=1e-12)  # not a lung: p


@pytest.fixture(scope="module")
def imaged_model(imaged, tmp_path_factory):
    """The imaged cube's hyper-reduced model, trained at 8 points of its box."""
    folder = MPI.COMM_WORLD.bcast(tmp_path_factory.mktemp("imaged_model"))
    path = folder / "m.npz"
    built = ["rom", "build", str(imaged), "-o", str(path), "--samples", "8", "--size", "10", "-q"]
    assert main([*built, "--hyper", "ecsw", "--ecsw-tolerance", "1e-6"]) == 0
    return path


def test_a_reduced_model_of_an_imaged_scene_starts_on_the_image(imaged_model, tmp_path, capsys):
    """A reduced model of an [inverse] scene solves the imaged problem at every μ: at a point
    it was not trained on, it finds its reference there and starts on the image, and says so."""
    capsys.readouterr()
    out = tmp_path / "solve"
    assert main(["rom", "solve", str(imaged_model), "-o", str(out), *_sets({"stiffness": 110.0})]) == 0
    said = capsys.readouterr().out
    line = next(line for line in said.splitlines() if "start:" in line)
    assert "(its unloaded reference from the reduced inverse motion at μ); volume 1000 L, the image's" in line
    summary = json.loads((out / "summary.json").read_text())
    start = summary["start"]
    assert start["kind"] == "imaged" and start["imaged_volume"] == pytest.approx(1.0)
    assert abs(start["from_image"]) <= 1e-12
    assert summary["reference_volume"] == start["reference_volume"] < 0.99  # its reference, not the image
    assert not (out / "reference.vtu").exists()  # a body of sampled cells: no field, no mesh


@pytest.mark.slow
def test_rom_solve_and_run_answer_the_same_imaged_problem(imaged, imaged_model, tmp_path):
    """``rom solve --set`` (the hyper-reduced model on its sampled cells) and ``run --set`` (the
    full model, its mesh moved to the reference by the fixed point) agree at points of the box
    the model was not trained on: on the command line at two, through the same ``solve(μ)`` at
    ten more, corners among them. Their reference volumes to 1e-5, the volumes along the path to
    1e-4 of its volume change, the probe to 1e-5 of the cube's size."""
    full = run_app.full_order_model(scenes.load(imaged))
    reduced = reduce_app.load(imaged_model)  # as rom solve loads it: on its body alone
    box = full.parameters

    def agree(a, b):
        reference = a.start.details["reference_volume"]
        assert b.start.details["reference_volume"] == pytest.approx(reference, rel=1e-5)
        change = np.ptp(np.concatenate([[reference], a.outputs["volume"]]))
        assert np.abs(b.outputs["volume"] - a.outputs["volume"]).max() <= 1e-4 * change
        assert np.abs(b.outputs["probes"] - a.outputs["probes"]).max() <= 1e-5

    for i, mu in enumerate(box.sample(2, seed=21)):
        mu = {name: round(value, 6) for name, value in mu.items()}
        run, solved = tmp_path / f"run{i}", tmp_path / f"solve{i}"
        assert main(["run", str(imaged), "-o", str(run), "-q", *_sets(mu)]) == 0
        assert main(["rom", "solve", str(imaged_model), "-o", str(solved), "-q", *_sets(mu)]) == 0
        a, b = (json.loads((folder / "summary.json").read_text()) for folder in (run, solved))
        assert a["start"]["reference_volume"] == pytest.approx(b["start"]["reference_volume"], rel=1e-5)
        change = abs(a["outputs"]["volume"][-1] - a["start"]["reference_volume"])
        assert np.abs(np.subtract(a["outputs"]["volume"], b["outputs"]["volume"])).max() <= 1e-4 * change
    corners = [box.from_unit(np.array(corner, dtype=float)) for corner in ((0, 0), (0, 1), (1, 0), (1, 1))]
    for mu in [*box.sample(6, seed=22), *corners]:
        agree(full.solve(mu), reduced.solve(mu))
