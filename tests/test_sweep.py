"""rom solve --sweep: many parameter points from a CSV file, each answer with its error
indicator, a bad file refused in one line."""

import csv
import json

from mpi4py import MPI

import numpy as np
import pytest
from fem import PARAMETRIC_SCENE

from lungmech.app import reduce as reduce_app
from lungmech.app import scene as scenes
from lungmech.app.cli import main
from lungmech.app.sweep import sweep

SCENE = PARAMETRIC_SCENE.replace("fields = false", "fields = false\nprobes = [[2.0, 0.5, 0.5]]") + (
    "[stepping]\ntimes = [0.5]\n"
)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A greedy hyper-reduced model of the pulled block (built once), and its folder."""
    folder = MPI.COMM_WORLD.bcast(tmp_path_factory.mktemp("sweep"))
    (folder / "scene.toml").write_text(SCENE) if MPI.COMM_WORLD.rank == 0 else None
    MPI.COMM_WORLD.barrier()
    scene = scenes.load(folder / "scene.toml")
    reduce_app.build(scene, folder / "m.npz", tolerance=1e-3, samples=8, hyper="ecsw", hyper_tolerance=1e-5)
    return folder


def _points(folder, text):
    path = folder / "points.csv"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(text)
    MPI.COMM_WORLD.barrier()
    return path


@pytest.mark.slow
def test_a_sweep_answers_as_the_model_and_the_full_runs(built, capsys):
    """Each row is the reduced model's own answer at its point (to round-off), and the full run
    at that point within the tolerance the model was trained to; the indicator is on every row."""
    points = _points(built, "stiffness [Pa],pull\n600,1\n1800,4.5\n")
    out = built / "swept"
    assert main(["rom", "solve", str(built / "m.npz"), "--sweep", str(points), "-o", str(out), "--set", "pull=2"]) == 0
    assert "2 points in" in capsys.readouterr().out
    rows = list(csv.DictReader((out / "sweep.csv").open()))
    assert [r["point [1]"] for r in rows] == ["0", "0", "1", "1"] and [r["time [s]"] for r in rows] == [
        "0.5",
        "1.0",
    ] * 2
    reduced = reduce_app.load(built / "m.npz")
    for index, point in enumerate([{"stiffness": 600.0, "pull": 1.0}, {"stiffness": 1800.0, "pull": 4.5}]):
        answer = reduced.solve(point)
        mine = [r for r in rows if r["point [1]"] == str(index)]
        assert [float(r["volume [m^3]"]) for r in mine] == pytest.approx(answer.outputs["volume"], rel=1e-12)
        assert float(mine[0]["error_indicator [1]"]) == pytest.approx(answer.indicator, rel=1e-8)
        assert float(mine[0]["probe0_uz [m]"]) == pytest.approx(answer.outputs["probes"][0][0][2], rel=1e-10)
        full = built / f"full{index}"
        sets = [f"stiffness={point['stiffness']}", "--set", f"pull={point['pull']}"]
        assert main(["run", str(built / "scene.toml"), "-o", str(full), "--set", *sets, "-q"]) == 0
        reference = json.loads((full / "summary.json").read_text())
        assert float(mine[-1]["volume [m^3]"]) == pytest.approx(reference["deformed_volume"], rel=1e-4)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["points"] == 2 and 0 < summary["error_indicator_largest"] < 1e-2
    assert summary["parameters"][0] == {"stiffness": 600.0, "pull": 1.0}
    assert (out / "sweep.png").stat().st_size > 0


def test_a_parameter_without_a_column_keeps_the_set_value(built):
    points = _points(built, "stiffness\n700\n")
    summary = sweep(built / "m.npz", points, built / "kept", values={"pull": 3.0})
    assert summary["parameters"] == [{"stiffness": 700.0, "pull": 3.0}]


@pytest.mark.parametrize(
    ("text", "said"),
    [
        ("stiffnes,pull\n600,1\n", "column 'stiffnes' is not a parameter of the model (stiffness, pull)"),
        ("stiffness,pull\n\n600,abc\n", "line 3, column 'pull': 'abc' is not a finite number"),
        ("stiffness,pull\n600,nan\n", "column 'pull': 'nan' is not a finite number"),
        ("stiffness\n6000\n", "line 2: parameter 'stiffness' = 6000 Pa is outside its range [500, 2000] Pa"),
        ("stiffness,pull\n", "holds no points"),
        ("stiffness,pull\n600\n", "line 2: 1 values for 2 columns"),
        ("stiffness,stiffness [Pa]\n600,700\n", "a parameter has two columns"),
        (
            "stiffness [kPa]\n0.7\n",
            "column 'stiffness [kPa]': parameter 'stiffness' is given in [Pa]; write its values in Pa",
        ),
        ("pull [Pa]\n2\n", "parameter 'pull' is given in [1]"),
    ],
)
def test_a_bad_sweep_file_is_refused_in_one_line(built, capsys, text, said):
    points = _points(built, text)
    out = built / "refused"
    assert main(["rom", "solve", str(built / "m.npz"), "--sweep", str(points), "-o", str(out), "-q"]) == 2
    error = capsys.readouterr().err.strip()
    assert said in error and len(error.splitlines()) == 1
    assert not out.exists()


@pytest.mark.parametrize(
    ("extra", "said"),
    [
        (["--scale", "2"], "--sweep takes no --scale"),
        (["SCENE"], "--sweep solves the scene inside the model file"),
        (["-o", "."], "is the current folder"),
    ],
)
def test_a_sweep_refuses_what_it_cannot_do(built, capsys, extra, said, monkeypatch):
    monkeypatch.chdir(built)
    points = _points(built, "stiffness\n700\n")
    extra = [str(built / "scene.toml") if e == "SCENE" else e for e in extra]
    model, rest = (extra[0], extra[1:]) if extra[0].endswith(".toml") else (None, extra)
    args = ["rom", "solve", str(built / "m.npz"), *([model] if model else []), "--sweep", str(points), *rest]
    assert main([*args, *([] if "-o" in rest else ["-o", str(built / "x")]), "-q"]) == 2
    assert said in capsys.readouterr().err


@pytest.mark.mpi
def test_a_sweep_on_all_ranks_answers_as_on_one(built):
    """The file written on N ranks holds the answers of the model on one rank."""
    points = _points(built, "stiffness,pull\n650,4\n1500,0.7\n")
    out = MPI.COMM_WORLD.bcast(built / "parallel")
    sweep(built / "m.npz", points, out)
    alone = reduce_app.load(built / "m.npz", MPI.COMM_SELF)
    rows = list(csv.DictReader((out / "sweep.csv").open()))
    for index, point in enumerate([{"stiffness": 650.0, "pull": 4.0}, {"stiffness": 1500.0, "pull": 0.7}]):
        answer = alone.solve(point)
        mine = [float(r["volume [m^3]"]) for r in rows if r["point [1]"] == str(index)]
        assert np.allclose(mine, answer.outputs["volume"], rtol=1e-10)
        assert float(rows[2 * index]["error_indicator [1]"]) == pytest.approx(answer.indicator, rel=1e-6)


@pytest.mark.slow
def test_a_full_sweep_answers_as_run_does_and_reports_a_failed_point(tmp_path, capsys):
    """run --sweep: each point one full solve of the ensemble, its row the answer `run --set`
    gives there (bit for bit: the same model and solver); a point past the sphere's limit
    pressure fails and is a row that says so, while the others go on; the cache makes a second
    sweep solve nothing."""
    from trades import written

    scene = written(tmp_path, low=0.05, min_step=0.25)
    points = _points(tmp_path, "stiffness [Pa]\n10\n0.05\n17.5\n")
    cache, out = tmp_path / "cache", tmp_path / "swept"
    assert main(["run", str(scene), "--sweep", str(points), "--at", "1", "--cache", str(cache), "-o", str(out)]) == 0
    said = capsys.readouterr().out
    assert "3 points (serial on 1 rank)" in said and "1 failed" in said
    rows = list(csv.DictReader((out / "sweep.csv").open()))
    assert [row["point [1]"] for row in rows] == ["0", "1", "2"] and rows[1]["failed"] and not rows[0]["failed"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["failed"][0]["point"] == 1 and summary["full solves on"] == "serial on 1 rank"
    assert main(["run", str(scene), "--set", "stiffness=17.5", "--at", "1", "-q", "-o", str(tmp_path / "one")]) == 0
    alone = json.loads((tmp_path / "one" / "summary.json").read_text())
    assert float(rows[2]["volume [m^3]"]) == alone["deformed_volume"]
    kept = sorted((cache / "answers").iterdir())
    assert main(["run", str(scene), "--sweep", str(points), "--at", "1", "--cache", str(cache), "-o", str(out)]) == 0
    assert sorted((cache / "answers").iterdir()) == kept
    assert list(csv.DictReader((out / "sweep.csv").open())) == rows


@pytest.mark.serial
def test_a_full_sweep_refuses_options_that_cannot_act(tmp_path, capsys):
    from trades import written

    scene = written(tmp_path)
    points = _points(tmp_path, "stiffness [Pa]\n10\n")
    for extra, said in (
        (["--group-size", "1"], "give --sweep"),
        (["--sweep", str(points), "--workers", "3"], "--engine parsl"),
        (["--sweep", str(points), "--scale", "2"], "--scale"),
    ):
        assert main(["run", str(scene), "-o", str(tmp_path / "out"), *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and said in err[0], err
