"""Where results go and what they say: safe output folders and files, fields every viewer
opens, units and provenance."""

from __future__ import annotations

import csv
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from mpi4py import MPI

import meshio
import numpy as np
import pytest
import pyvista
from fem import TINY_SCENE

from lungmech.app import scene as scenes
from lungmech.app.run import run
from lungmech.errors import OutputError
from lungmech.parallel import destination

pytestmark = pytest.mark.serial  # one process makes the user's files and runs on COMM_SELF
COMM = MPI.COMM_SELF
TINY = {
    "title": "tiny",
    "geometry": {"builder": "box", "cells": [2, 1, 1], "lengths": [2.0, 1.0, 1.0]},
    "material": {"law": "neo_hookean", "E": 1e3, "nu": 0.3},
    "constraints": [{"type": "clamp", "boundary": "x0"}],
    "loads": [{"type": "follower_pressure", "boundary": "x1", "value": 10.0, "name": "push"}],
    "output": {"fields": True, "probes": [[2.0, 1.0, 1.0]]},
}


def write_result(folder: Path, files: dict[str, str]) -> None:
    with destination.output_folder(folder, COMM) as staging:
        for name, text in files.items():
            (staging / name).parent.mkdir(parents=True, exist_ok=True)
            (staging / name).write_text(text)


def staging_marker(pid: int) -> dict:
    return {"written_by": "lungmech", "state": "staging", "host": os.uname().nodename, "pid": pid}


def test_folders_that_only_look_like_leftovers_are_never_touched(tmp_path, monkeypatch):
    """A user's folders named like staging or replaced results, without lungmech's marker, stay."""
    monkeypatch.chdir(tmp_path)
    theirs = [
        ".out.lungmech-staging-1-abcdef",
        ".out.lungmech-staging-notes-v2",
        ".out.lungmech-old-2020-backup",
        ".out.lungmech-old-999999999-abcdef",
    ]
    for name in theirs:
        (tmp_path / name).mkdir()
        (tmp_path / name / "thesis.tex").write_text("years of work")
    write_result(tmp_path / "out", {"a.txt": "1"})
    for name in theirs:
        assert (tmp_path / name / "thesis.tex").read_text() == "years of work"
    empty = tmp_path / ".out.lungmech-staging-999999999-abcdef"  # killed before its marker: empty
    empty.mkdir()
    write_result(tmp_path / "out", {"a.txt": "2"})
    assert not empty.exists()


def test_a_folder_of_lungmech_is_replaced_and_only_then(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "out"
    write_result(out, {"a.txt": "1", "sub/b.txt": "2"})
    marker = json.loads((out / destination.MARKER).read_text())
    assert marker["state"] == "complete" and set(marker["files"]) == {"a.txt", "sub/b.txt"}
    write_result(out, {"c.txt": "3"})  # lungmech's own, unchanged: replaced
    assert sorted(p.name for p in out.iterdir()) == [destination.MARKER, "c.txt"]
    (out / "note.txt").write_text("mine")
    with pytest.raises(OutputError, match="holds 'note.txt', which lungmech did not write"):
        write_result(out, {"d.txt": "4"})
    (out / "note.txt").unlink()
    (out / "c.txt").write_text("edited")
    with pytest.raises(OutputError, match="was changed after lungmech wrote it"):
        write_result(out, {"d.txt": "4"})
    assert (out / "c.txt").read_text() == "edited"
    empty = tmp_path / "empty"
    empty.mkdir()
    write_result(empty, {"e.txt": "5"})  # an empty folder may be used
    assert (empty / "e.txt").is_file()


def test_where_a_folder_may_not_go(tmp_path, monkeypatch):
    (tmp_path / "work" / "inputs").mkdir(parents=True)
    scene = tmp_path / "work" / "inputs" / "scene.toml"
    scene.write_text("x")
    monkeypatch.chdir(tmp_path / "work")
    for target, message in [
        (".", "is the current folder"),
        (tmp_path, "holds the current folder"),
        ("inputs", "holds the input"),
        ("inputs/scene.toml", "is the input"),
    ]:
        with pytest.raises(OutputError, match=message):
            with destination.output_folder(target, COMM, inputs=[scene]):
                pass
    assert scene.read_text() == "x"


def test_a_failed_job_leaves_the_old_result_and_no_staging(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "out"
    write_result(out, {"a.txt": "old"})
    for error in (ValueError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(error)):
            with destination.output_folder(out, COMM) as staging:
                (staging / "a.txt").write_text("new")
                raise error
        assert (out / "a.txt").read_text() == "old"
        assert [p.name for p in tmp_path.iterdir()] == ["out"]


def _until_exec(pid: int, marker: bytes) -> None:
    """Wait until process ``pid`` has exec'd its own command (containing ``marker``): a forked
    child shows its parent's command line, then briefly none, before that."""
    command = Path(f"/proc/{pid}/cmdline")
    for _ in range(500):
        if not command.exists() or marker in command.read_bytes():
            return
        time.sleep(0.01)


def test_stale_staging_of_a_killed_run_is_removed_and_a_live_one_respected(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "out"
    dead = tmp_path / ".out.lungmech-staging-999999999-abc123"  # no such process
    dead.mkdir()
    (dead / "half.vtu").write_text("x")
    (dead / destination.MARKER).write_text(json.dumps(staging_marker(999999999)))
    write_result(out, {"a.txt": "1"})
    assert not dead.exists() and (out / "a.txt").is_file()
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])  # a live Python run
    _until_exec(other.pid, b"import time")
    try:
        alive = tmp_path / f".out.lungmech-staging-{other.pid}-abc123"
        alive.mkdir()
        (alive / destination.MARKER).write_text(json.dumps(staging_marker(other.pid)))
        with pytest.raises(OutputError, match=f"another lungmech run \\(process {other.pid}\\) is writing"):
            write_result(out, {"b.txt": "2"})
    finally:
        other.kill()
        other.wait()
    assert (out / "a.txt").is_file()
    stranger = subprocess.Popen(["sleep", "60"])  # a live process that is not Python: a reused pid
    _until_exec(stranger.pid, b"sleep")
    try:
        (alive / destination.MARKER).write_text(json.dumps(staging_marker(stranger.pid)))
        write_result(out, {"b.txt": "2"})
    finally:
        stranger.kill()
        stranger.wait()
    assert not alive.exists() and (out / "b.txt").is_file()


def test_staging_from_another_host_is_reported_not_removed(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    foreign = tmp_path / ".out.lungmech-staging-123-abc123"
    foreign.mkdir()
    (foreign / destination.MARKER).write_text(json.dumps(staging_marker(123) | {"host": "elsewhere.example"}))
    with pytest.raises(
        OutputError, match="was left by a lungmech run on host elsewhere.example; remove it if that run"
    ):
        write_result(tmp_path / "out", {"a.txt": "1"})
    assert foreign.is_dir()


def test_an_interrupted_swap_is_finished(tmp_path, monkeypatch):
    """A crash between moving the old result away and moving the new one in: the next run
    restores the old one first."""
    monkeypatch.chdir(tmp_path)
    write_result(tmp_path / "out", {"a.txt": "old"})
    (tmp_path / "out").rename(tmp_path / ".out.lungmech-old-999999999-abc123")
    write_result(tmp_path / "elsewhere", {"x": "1"})  # another target: untouched
    assert not (tmp_path / "out").exists()
    with destination.output_folder(tmp_path / "out", COMM) as staging:
        assert (tmp_path / "out" / "a.txt").read_text() == "old"  # restored before the work
        (staging / "a.txt").write_text("new")
    assert (tmp_path / "out" / "a.txt").read_text() == "new"


def test_a_folder_changed_during_the_run_keeps_both(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "out"
    with pytest.raises(OutputError, match="this run's results are in"):
        with destination.output_folder(out, COMM) as staging:
            (staging / "a.txt").write_text("new")
            out.mkdir()
            (out / "theirs.txt").write_text("appeared meanwhile")
    assert (out / "theirs.txt").is_file()
    kept = [p for p in tmp_path.iterdir() if p.name.startswith("out-")]
    assert len(kept) == 1 and (kept[0] / "a.txt").read_text() == "new"


def test_single_files_replace_only_lungmech_files(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ours = lambda path: path.read_text().startswith("lungmech")  # noqa: E731
    target = tmp_path / "model.npz"
    with destination.output_file(target, COMM, ours=ours) as path:
        assert path.parent != tmp_path and path.name == "model.npz"  # written elsewhere first
        path.write_text("lungmech 1")
    with destination.output_file(target, COMM, ours=ours) as path:
        path.write_text("lungmech 2")
    assert target.read_text() == "lungmech 2"
    target.write_text("the user's")
    with pytest.raises(OutputError, match="was not written by lungmech"):
        with destination.output_file(target, COMM, ours=ours) as path:
            path.write_text("lungmech 3")
    assert target.read_text() == "the user's"
    with pytest.raises(OutputError, match="is the input"):
        with destination.output_file(tmp_path / "in.npz", COMM, inputs=[tmp_path / "in.npz"]):
            pass
    assert [p.name for p in tmp_path.iterdir()] == ["model.npz"]


def test_fields_open_in_pyvista_and_meshio_and_units_everywhere(tmp_path):
    scene = scenes.parse(TINY)
    summary = run(scene, tmp_path / "out", COMM)
    out = tmp_path / "out"
    # the .pvd time series: every step, the displacement at the nodes and J in the cells
    reader = pyvista.PVDReader(str(out / "fields.pvd"))
    assert len(reader.time_values) == summary["steps"] + 1
    reader.set_active_time_value(reader.time_values[-1])
    grid = reader.read()[0]
    mesh = meshio.read(out / f"fields_{summary['steps']:06d}.vtu")
    assert grid.n_cells == mesh.cells[0].data.shape[0] == summary["cells"]
    assert np.allclose(grid.point_data["displacement"], mesh.point_data["displacement"])
    tip = np.argmin(np.linalg.norm(mesh.points - [2.0, 1.0, 1.0], axis=1))  # a node: the probe
    assert np.allclose(mesh.point_data["displacement"][tip], summary["probes"]["displacement"][0], atol=1e-12)
    assert mesh.cell_data["J"][0].min() > 0
    # units: every CSV column, every summary number
    with open(out / "history.csv") as stream:
        header = next(csv.reader(stream))
    assert header[:3] == ["time [s]", "volume [m^3]", "strain_energy [J]"] and "push [Pa]" in header
    assert all(h.endswith("]") for h in header)
    units = summary["units"]
    for key in ("start_volume", "deformed_volume", "largest_volume.volume", "strain_energy", "probes.displacement"):
        assert key in units
    provenance = summary["provenance"]
    assert provenance["mpi_ranks"] == 1 and provenance["lungmech"] and len(provenance["scene_sha256"]) == 64
    assert (out / "pressure_volume.png").stat().st_size > 10_000 and (out / "deformed.png").stat().st_size > 10_000


@pytest.mark.slow
def test_mixed_and_quadratic_fields_are_written(tmp_path):
    table = {
        **TINY,
        "material": {"law": "neo_hookean", "E": 1e3, "nu": 0.45},
        "formulation": {"type": "mixed", "degree": 2},
    }
    summary = run(scenes.parse(table), tmp_path / "out", COMM)
    mesh = meshio.read(tmp_path / "out" / f"fields_{summary['steps']:06d}.vtu")
    assert mesh.cells[0].type == "tetra10" and "pressure" in mesh.point_data
    grid = pyvista.read(tmp_path / "out" / f"fields_{summary['steps']:06d}.vtu")
    assert grid.n_cells == summary["cells"]


def test_provenance_hashes_the_scene_file(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text(
        'title = "x"\n[geometry]\nbuilder = "box"\ncells = [1, 1, 1]\n[material]\nlaw = "linear"\n'
        'E = 1.0\nnu = 0.3\n[[constraints]]\ntype = "clamp"\nboundary = "x0"\n[output]\nfields = false\n'
    )
    summary = run(scenes.load(path), tmp_path / "out", COMM)
    assert summary["provenance"]["scene_sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()


class _Terminal:
    def __init__(self, tty: bool):
        self.text, self.tty = "", tty

    def write(self, text: str) -> None:
        self.text += text

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return self.tty


@pytest.mark.parametrize("tty", [True, False])
def test_progress_is_a_live_bar_on_a_terminal_and_lines_in_logs(tty, monkeypatch):
    import logging

    from lungmech.app.console import Progress

    monkeypatch.delenv("CI", raising=False)
    monkeypatch.setenv("TERM", "xterm")
    logging.getLogger("lungmech").setLevel(logging.INFO)
    stream = _Terminal(tty)
    progress = Progress("breathing", COMM, stream)
    progress.update(0.25, "step 1")
    progress.note("step cut back")
    progress.update(1.0, "step 2")
    progress.close("2 steps")
    if tty:
        assert "\r\033[K" in stream.text and "[######" in stream.text and " 25%" in stream.text
        assert stream.text.count("\n") == 3  # the note, the bar left in place, the closing line
    else:
        assert stream.text.splitlines()[:3] == ["breathing: step 1", "breathing: step cut back", "breathing: step 2"]
        assert "\r" not in stream.text and "#" not in stream.text
    assert stream.text.rstrip().endswith("s)")


def test_a_mount_point_can_be_the_output_folder(tmp_path, monkeypatch):
    """A folder that cannot be renamed (a mount point, as with docker -v host:/out) is filled in
    place, and replaced in place on a rerun."""
    import subprocess

    monkeypatch.chdir(tmp_path)
    mount = tmp_path / "mnt"
    mount.mkdir()
    if (
        os.geteuid() != 0
        or subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)], capture_output=True
        ).returncode
        != 0
    ):
        pytest.skip("mounting a tmpfs needs root")
    try:
        write_result(mount, {"a.txt": "1"})
        write_result(mount, {"b.txt": "2"})
        assert sorted(p.name for p in mount.iterdir()) == [destination.MARKER, "b.txt"]
        assert sorted(p.name for p in tmp_path.iterdir()) == ["mnt"]
    finally:
        subprocess.run(["umount", "-l", str(mount)])


def test_a_failed_job_removes_the_folders_it_made(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError):
        with destination.output_folder(tmp_path / "new1" / "new2" / "out", COMM):
            raise ValueError("failed")
    assert list(tmp_path.iterdir()) == []


def test_a_metaimage_moves_with_its_data(tmp_path, monkeypatch):
    from lungmech.app.cli import main
    from lungmech.registration import image

    monkeypatch.chdir(tmp_path)
    for name in ("p.mhd", "q.nhdr"):
        assert main(["phantom", "-o", name, "--spacing", "8"]) == 0
        assert image.read(name).volume > 0
        assert main(["phantom", "-o", name, "--spacing", "8"]) == 0  # its own, unchanged: replaced
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.mhd", "p.zraw", "q.nhdr", "q.raw.gz"]


def test_a_picture_that_cannot_be_drawn_is_a_warning(tmp_path, monkeypatch, capsys):
    """No off-screen rendering here, say: the run keeps its results, says what is missing, exits 0."""
    from lungmech.app import plot
    from lungmech.app.cli import main

    def broken(*args, **kwargs):
        raise RuntimeError("cannot open an off-screen window")

    monkeypatch.setattr(plot, "_draw", broken)
    (tmp_path / "scene.toml").write_text(TINY_SCENE)
    assert main(["run", str(tmp_path / "scene.toml"), "-o", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "lungmech: warning: deformed.png was not drawn (cannot open an off-screen window)" in out
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [destination.MARKER, "history.csv", "summary.json"]
