"""``lungmech trade`` from the command line (lungmech.app.trade_cli): --build makes the Galerkin
and hyper-reduced models by the one reductor into the cache; a loose tolerance chooses a
hyper-reduced model, one that only a finer full model meets chooses that (make test-long); OUT holds the table
(md, csv, json), the Pareto plot and choice.json with the chosen model file, which rom solve
answers with; bad requests are one line; the same table on 1 rank, 2 ranks and 2 groups."""

import csv
import json
from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest
from trades import written

from lungmech.app import reduce
from lungmech.app import scene as scenes
from lungmech.app.answers import answer
from lungmech.app.cli import main
from lungmech.app.ladder import Discretisation
from lungmech.app.run import full_order_model
from lungmech.app.trade import Candidate, trade
from lungmech.parallel.ensemble import Groups
from lungmech.rom import store

# the reference the scene's mesh refined once (h/2): half the time of h/4, whose orders of
# convergence tests/test_field_errors.py and tests/test_trade.py check
BUILD = ["--build", "--taus", "1e-2,1e-4", "--size", "6", "--samples", "4", "--levels", "1"]


def traded(scene: Path, out: Path, cache: Path, tolerance: float, *extra: str) -> tuple[int, dict, list[dict]]:
    code = main(
        ["trade", str(scene), "--tolerance", f"{tolerance:g}", "--points", "1", "--cache", str(cache), "-o", str(out)]
        + ["-q", *extra]
    )
    if code:
        return code, {}, []
    with open(out / "trade.csv") as stream:
        table = list(csv.DictReader(stream))
    return code, json.loads((out / "trade.json").read_text()), table


@pytest.mark.serial
@pytest.mark.slow
def test_a_loose_tolerance_chooses_a_hyper_reduced_model(tmp_path, capsys):
    loosely(tmp_path, capsys)


@pytest.mark.serial
@pytest.mark.long  # (the loose trade again first: 50 s in all) the choice: tests/test_trade_choice.py; solves kept: tests/test_training_paths.py
def test_a_tight_tolerance_chooses_a_full_model_from_the_solves_and_models_kept(tmp_path, capsys):
    scene, cache, loose, errors = loosely(tmp_path, capsys)
    # a tolerance only the finer full models meet: a full model, every solve and model kept
    tight = 0.5 * (errors["full P1 h"] + errors["full P2 h"])
    assert tight < min(errors[name] for name in errors if not name.startswith("full P"))
    code, again, table = traded(scene, tmp_path / "tight", cache, tight, *BUILD)
    assert code == 0, capsys.readouterr().err
    chosen = json.loads((tmp_path / "tight" / "choice.json").read_text())
    assert chosen["model"]["family"] == "full" and chosen["model"]["worst_error"] <= tight
    rows = {row["model"]: row for row in table if row["family"] != "reference"}
    meeting = {
        name: float(row["online [ms]"]) for name, row in rows.items() if float(row["volume error max [-]"]) <= tight
    }
    assert chosen["model"]["name"] == min(meeting, key=meeting.get)  # the fastest of those, as timed in this run
    assert not any(name.startswith("POD") for name in meeting)
    assert not (tmp_path / "tight" / "model.npz").exists()
    assert len(list((cache / "models").iterdir())) == 1  # built once
    assert [m["errors"] for m in again["models"]] == [m["errors"] for m in loose["models"]]
    assert again["full_solves"] == {"solved": 0, "kept": 15}
    out = capsys.readouterr().out
    assert f"* {chosen['model']['name']}" in out and f"choice: {chosen['model']['name']}" in out


def loosely(tmp_path: Path, capsys) -> tuple[Path, Path, dict, dict[str, float]]:
    """The trade at a loose tolerance (5e-2) with --build, checked: a hyper-reduced model
    chosen, the cheapest that meets it; its scene, cache, trade.json and each model's error."""
    scene, cache = written(tmp_path), tmp_path / "cache"
    code, loose, table = traded(scene, tmp_path / "loose", cache, 5e-2, *BUILD)
    assert code == 0, capsys.readouterr().err
    assert loose["reference"] == "full P1 h/2" and len(loose["points"]) == 3
    assert [p["kind"] for p in loose["points"]].count("corner") == 2
    assert loose["failure_bound_95"] == pytest.approx(1 - 0.05 ** (1 / 3))
    assert loose["convergence"] == {}  # (no full P1 model between h and the reference: no order observed)
    assert loose["full_solves"] == {"solved": 15, "kept": 0}  # a new cache: 5 full models (2h too) × 3 points
    by_name = {row["model"]: row for row in table}
    assert {"POD Galerkin", "POD ECSW τ=0.01", "POD ECSW τ=0.0001", "full P1 h", "full P2 h", "full P2–P1 h"} <= set(
        by_name
    )
    errors = {name: float(row["volume error max [-]"]) for name, row in by_name.items() if row["family"] != "reference"}
    for name, error in errors.items():  # measured against an independent finer reference: never zero
        assert 0 < error < 0.2 and float(by_name[name]["online [ms]"]) > 0 and by_name[name]["failed points"] == "0"
    meeting = [name for name, error in errors.items() if error <= 5e-2]
    online = {name: float(by_name[name]["online [ms]"]) for name in meeting}
    chosen = json.loads((tmp_path / "loose" / "choice.json").read_text())
    assert chosen["model"]["name"] == min(online, key=online.get)  # the cheapest that meets it
    assert chosen["model"]["family"] == "ecsw"
    # a reduced model of the scene's mesh answers that mesh's problem: its error against the
    # finer reference is the full model's on that mesh, to its own reduction error
    assert errors["POD Galerkin"] == pytest.approx(errors["full P1 h"], rel=0.05)
    assert errors["full P2 h"] < errors["full P1 h"]
    reduced_against(loose, by_name, tmp_path / "loose" / "model.npz", scene)
    # the built models record their cost, and no test point is one they were trained on
    galerkin = by_name["POD Galerkin"]
    assert float(galerkin["offline [s]"]) > 0 and int(galerkin["full solves"]) == 4
    assert int(by_name["POD ECSW τ=0.01"]["full solves"]) == 8  # and ECSW's own training pass
    metadata, _ = store.read_on_root(tmp_path / "loose" / "model.npz", MPI.COMM_SELF, arrays=False)
    trained = [point["stiffness"] for point in metadata["extra"]["reduced"]["training"]]
    tested = [point["values"]["stiffness"] for point in loose["points"]]
    assert len(trained) == 4 and not set(trained) & set(tested)
    assert (tmp_path / "loose" / "model.npz").read_bytes() == Path(chosen["model"]["built_from"]).read_bytes()
    for name in ("trade.md", "trade.png"):
        assert (tmp_path / "loose" / name).stat().st_size > 0
    assert "| **POD ECSW" in (tmp_path / "loose" / "trade.md").read_text()
    # the chosen model file answers rom solve, as measured
    solved = tmp_path / "solved"
    point = loose["points"][0]["values"]
    assert (
        main(
            ["rom", "solve", str(tmp_path / "loose" / "model.npz"), "--at", "1", "-q", "-o", str(solved)]
            + [f"--set=stiffness={point['stiffness']!r}"]
        )
        == 0
    )
    return scene, cache, loose, errors


def reduced_against(found: dict, by_name: dict, chosen: Path, scene: Path) -> None:
    """The reduced models' error of reduction: against the full model on the scene's mesh, the
    same as solving the chosen model file and that full model here, one by one, gives; at each
    point within the triangle its error and that full model's against the finer reference make
    (their denominators, the two volume changes, within 10 %)."""
    assert found["reduced_against"] == "full P1 h"
    rows = {row["model"]: row for row in found["models"]}
    mesh = np.array(rows["full P1 h"]["errors"]["volume"])
    for name, row in by_name.items():
        reduction = row["reduction error max [-]"]
        assert (reduction == "") == (row["family"] in ("full", "reference")), name
        if reduction:
            alone, total = (np.array(rows[name][key]["volume"]) for key in ("reduction_errors", "errors"))
            assert float(reduction) == pytest.approx(alone.max()) and (alone > 0).all()
            assert (alone <= 1.1 * (total + mesh)).all() and (alone >= np.abs(total - mesh) / 1.1).all()
    chosen_name = json.loads((chosen.parent / "choice.json").read_text())["model"]["name"]
    measured = rows[chosen_name]["reduction_errors"]["volume"]
    full = full_order_model(scenes.load(scene), MPI.COMM_SELF, start="inverse_motion")
    reduced = reduce.load(chosen, MPI.COMM_SELF)
    times = found["output_times_s"]
    for point, error in zip(found["points"], measured, strict=True):
        mine, theirs = answer(reduced, point["values"], times), answer(full, point["values"], times)
        change = abs(theirs["volume"][-1] - theirs["start_volume"])
        assert error == pytest.approx(abs(mine["volume"][-1] - theirs["volume"][-1]) / change, rel=1e-6, abs=1e-12)


@pytest.mark.serial
def test_bad_trade_requests_are_one_line(tmp_path, capsys):
    scene = written(tmp_path)
    cache = str(tmp_path / "cache")
    cases = [
        (["--tolerance", "0"], "tolerance"),
        (["--tolerance", "nan"], "tolerance"),
        (["--tolerance", "1e-2", "--quantity", "speed"], "--quantity"),
        (["--tolerance", "1e-2", "--points", "0"], "--points"),
        (["--tolerance", "1e-2", "--queries", "0"], "--queries"),
        (["--tolerance", "1e-2", "--samples", "4"], "--build"),
        (["--tolerance", "1e-2", "--build", "--taus", "1e-3,1e-3"], "twice"),
        (["--tolerance", "1e-2", "--build", "--taus", "2"], "--taus"),
        (["--tolerance", "1e-2", "--build", "--sizes", "4,4"], "the basis sizes are given twice"),
        (["--tolerance", "1e-2", "--sizes", "4"], "give --build"),
        (["--tolerance", "1e-2", "--models", str(tmp_path / "missing.npz")], "missing.npz"),
        (["--tolerance", "1e-2", "--models", str(scene)], "sphere.toml"),
        (["--tolerance", "1e-2", "-o", "."], "current folder"),
        (["--tolerance", "1e-2", "--levels", "0"], "--levels"),
        (["--tolerance", "1e-2", "--engine", "parsl", "--group-size", "1"], "--engine"),
        (["--tolerance", "1e-2", "--workers", "3"], "--engine parsl"),
        (["--tolerance", "1e-2", "--engine", "parsl", "--workers", "64"], "cores"),
        (["--tolerance", "1e-2", "--group-size", "0"], "--group-size"),
    ]
    for arguments, named in cases:
        code = main(["trade", str(scene), "--cache", cache, "-o", str(tmp_path / "out"), *arguments])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and named in err[0], (arguments, err)
        assert not (tmp_path / "out").exists()


@pytest.mark.mpi
@pytest.mark.slow
def test_the_same_table_on_one_rank_two_ranks_and_two_groups(tmp_path):
    """The full solves on two ranks, in two groups of one rank, and on one rank (rank 0's own
    trade); each candidate measured on the trade's ranks: the same answers — bitwise between
    the groups and one rank, to the solvers' tolerances on two ranks —, and the same
    energy-norm errors (their fields carried and measured on the trade's ranks: to round-off
    between the groups and one rank)."""
    comm = MPI.COMM_WORLD
    scene = written(tmp_path)
    full = [Candidate.full(Discretisation(0, 1))]
    energy = {"quantity": "energy", "count": 1, "levels": 1, "full": full}
    both = trade(scene, 0.5, cache=tmp_path / "two", comm=comm, **energy)
    groups = Groups(1, comm)
    dealt = trade(scene, 0.5, cache=tmp_path / "groups", comm=comm, ensemble=groups, **energy)
    groups.free()
    alone = comm.Split(comm.rank)
    one = trade(scene, 0.5, cache=tmp_path / "one", comm=alone, **energy) if comm.rank == 0 else None
    alone.Free()
    one = comm.bcast(one, root=0)
    assert both.results["full P1 h"]["ranks"] == comm.size and one.results["full P1 h"]["ranks"] == 1
    assert dealt.ensemble == "2 groups of 1 rank" and one.ensemble == "serial on 1 rank"
    for name in ("full P1 h/2", "full P1 h"):
        for a, b, c in zip(one.results[name]["answers"], dealt.results[name]["answers"], both.results[name]["answers"]):
            assert a["volume"] == b["volume"] and a["probes"] == b["probes"]
            np.testing.assert_allclose(c["volume"], a["volume"], rtol=1e-8)
    np.testing.assert_array_equal(dealt.errors["full P1 h"]["volume"], one.errors["full P1 h"]["volume"])
    np.testing.assert_allclose(both.errors["full P1 h"]["volume"], one.errors["full P1 h"]["volume"], rtol=1e-5)
    np.testing.assert_allclose(dealt.errors["full P1 h"]["energy"], one.errors["full P1 h"]["energy"], rtol=1e-9)
    np.testing.assert_allclose(both.errors["full P1 h"]["energy"], one.errors["full P1 h"]["energy"], rtol=1e-5)
    assert one.choice.chosen.name == dealt.choice.chosen.name == both.choice.chosen.name
