"""Signals and MPI failures, from outside: the command line as a user runs it.

Ctrl-C (SIGINT) and SIGTERM stop a run with one line and exit 130 / 143; the staging folder is
removed and the earlier result is intact. A run killed outright (SIGKILL) leaves its staging
folder, which the next run into the same place removes. Under ``mpiexec -n 2``, a failure on
one rank ends the run on all of them: no rank waits forever (each run here has a timeout).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fem import TINY_SCENE

pytestmark = pytest.mark.slow
BIN = Path(sys.executable).parent
MPIEXEC = str(BIN / "mpiexec") if (BIN / "mpiexec").exists() else "mpiexec"
QUICK = TINY_SCENE.replace('"tiny"', '"quick"')
# About a second per step and a hundred steps: long enough to be interrupted mid-solve.
SLOW = QUICK.replace("cells = [2, 1, 1]", "cells = [12, 6, 6]").replace(
    "[output]", "[formulation]\ndegree = 2\n[stepping]\ninitial_step = 0.01\nmax_step = 0.01\n[output]"
)
ENV = {**os.environ, "PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": "1"}


def lungmech(*args: str, ranks: int = 1, cwd: Path) -> list[str]:
    command = [str(BIN / "lungmech"), *args]
    return [MPIEXEC, "-n", str(ranks), *command] if ranks > 1 else command


@pytest.fixture
def earlier(tmp_path) -> Path:
    """A finished result in out/, and the slow scene."""
    (tmp_path / "quick.toml").write_text(QUICK)
    (tmp_path / "slow.toml").write_text(SLOW)
    done = subprocess.run(
        lungmech("run", "quick.toml", "-o", "out", "-q", cwd=tmp_path),
        cwd=tmp_path,
        env=ENV,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    return tmp_path


def _contents(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir()}


def _solving(workspace: Path, ranks: int = 1) -> tuple[subprocess.Popen, str]:
    """The slow run started into out/, returned once it has done its first step (whatever the
    machine's speed: mid-solve, its staging folder made), with what it printed so far."""
    process = subprocess.Popen(
        lungmech("run", "slow.toml", "-o", "out", ranks=ranks, cwd=workspace),
        cwd=workspace,
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    said = []
    for line in process.stdout:  # one plain line per step: the output is not a terminal
        said.append(line)
        if line.startswith("loading: step 1 "):
            return process, "".join(said)
    process.wait(timeout=60)
    raise AssertionError(f"the slow run ended before it could be interrupted: {''.join(said)} {process.stderr.read()}")


def _interrupt(workspace: Path, sig: int, ranks: int = 1) -> subprocess.CompletedProcess:
    process, said = _solving(workspace, ranks)
    return _signalled(process, sig, timeout=120, said=said)


def _signalled(process: subprocess.Popen, sig: int, timeout: float, said: str = "") -> subprocess.CompletedProcess:
    """Send ``sig`` to ``process`` and wait for it to end (within ``timeout`` s, else fail);
    ``said``: what it printed before."""
    process.send_signal(sig)
    try:
        out, err = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        raise AssertionError("the interrupted run did not stop") from None
    return subprocess.CompletedProcess(process.args, process.returncode, said + out, err)


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_stops_the_run_and_keeps_the_earlier_result(earlier, sig, code):
    before = _contents(earlier / "out")
    result = _interrupt(earlier, sig)
    assert result.returncode == code, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert lines == [
        f"lungmech: interrupted by {signal.Signals(sig).name}; nothing was written and earlier results are unchanged"
    ], result.stderr
    assert _contents(earlier / "out") == before
    assert sorted(p.name for p in earlier.iterdir()) == ["out", "quick.toml", "slow.toml"]  # no staging left


def test_a_killed_run_leaves_staging_that_the_next_run_removes(earlier):
    process, _ = _solving(earlier)
    process.kill()
    process.communicate(timeout=60)
    left = [p for p in earlier.iterdir() if ".lungmech-staging-" in p.name]
    assert len(left) == 1
    done = subprocess.run(
        lungmech("run", "quick.toml", "-o", "out", "-q", cwd=earlier),
        cwd=earlier,
        env=ENV,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0 and "removed" in done.stdout + done.stderr
    assert sorted(p.name for p in earlier.iterdir()) == ["out", "quick.toml", "slow.toml"]


def test_mpi_a_signal_stops_every_rank(earlier):
    before = _contents(earlier / "out")
    result = _interrupt(earlier, signal.SIGTERM, ranks=2)
    assert result.returncode == 143, result.stderr
    assert "lungmech: interrupted by SIGTERM" in result.stderr and "Traceback" not in result.stderr
    assert _contents(earlier / "out") == before
    assert sorted(p.name for p in earlier.iterdir()) == ["out", "quick.toml", "slow.toml"]


@pytest.mark.parametrize(
    "args, message",
    [
        (["run", "quick.toml", "-o", "notes.txt"], "exists and is not a folder"),
        (["run", "quick.toml", "-o", "."], "is the current folder"),
        (["run", "quick.toml", "-o", "notes.txt/out"], "cannot write into"),
        (["run", "bad.toml", "-o", "x"], "loads[0]: value must be 2 or 3 numbers"),
        (["rom", "solve", "quick.toml", "-o", "x"], "is not a lungmech reduced model"),
    ],
)
def test_mpi_a_failure_ends_every_rank_with_one_line(tmp_path, args, message):
    (tmp_path / "quick.toml").write_text(QUICK)
    (tmp_path / "bad.toml").write_text(QUICK.replace("value = [0.0, 0.0, -10.0]", 'value = "abc"'))
    (tmp_path / "notes.txt").write_text("mine")
    result = subprocess.run(
        lungmech(*args, ranks=2, cwd=tmp_path), cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=240
    )
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2 and len(lines) == 1 and message in lines[0], result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml", "notes.txt", "quick.toml"]
    assert (tmp_path / "notes.txt").read_text() == "mine"


PAUSE = "LUNGMECH_TEST_PAUSE_BEFORE_SWAP"


def _interrupt_before_the_swap(workspace: Path, sig: int, ranks: int) -> tuple[subprocess.CompletedProcess, float]:
    """Run the quick scene into out/, paused between the solve and the swap; send ``sig`` there
    (to mpiexec, which forwards it to every rank). The result, and the seconds it took to end."""
    process = subprocess.Popen(
        lungmech("run", "quick.toml", "-o", "out", "-q", ranks=ranks, cwd=workspace),
        cwd=workspace,
        env={**ENV, PAUSE: "0.5"},  # the signal is sent as soon as the pause is announced
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    said = []
    for line in process.stdout:  # the hook says when it pauses
        said.append(line)
        if "test pause before the swap" in line:
            break
    else:
        process.wait(timeout=60)
        raise AssertionError(f"the run never paused before its swap: {''.join(said)} {process.stderr.read()}")
    sent = time.perf_counter()
    result = _signalled(process, sig, timeout=30, said="".join(said))
    return result, time.perf_counter() - sent


@pytest.mark.parametrize(
    "sig, code, ranks, attempts",
    [
        # each signal and each rank count in the default suite, 3 times each; every pairing
        # 10 times (a minute each) with make test-long
        (signal.SIGTERM, 143, 1, 3),
        (signal.SIGINT, 130, 2, 3),
        *[
            pytest.param(sig, code, ranks, 10, marks=pytest.mark.long)
            for sig, code in ((signal.SIGINT, 130), (signal.SIGTERM, 143))
            for ranks in (1, 2)
        ],
    ],
)
def test_a_signal_between_the_solve_and_the_swap_ends_every_run_alike(earlier, sig, code, ranks, attempts):
    """``attempts`` times: one lungmech line, exit 130/143 within 10 s, the earlier result
    byte-identical, no staging folder left (serial and on two ranks; the launcher's own lines
    aside). Each run has a copy of the workspace; they go one after another (together they would
    only slow the rest of the suite: each is CPU-bound)."""
    import shutil

    before = _contents(earlier / "out")
    expected = (
        f"lungmech: interrupted by {signal.Signals(sig).name}; nothing was written and earlier results are unchanged"
    )
    spaces = []
    for attempt in range(attempts):
        spaces.append(earlier.parent / f"{earlier.name}-{attempt}")
        shutil.copytree(earlier, spaces[-1])
    results = [_interrupt_before_the_swap(space, sig, ranks) for space in spaces]
    for attempt, (space, (result, seconds)) in enumerate(zip(spaces, results)):
        ours = [line for line in result.stderr.splitlines() if line.startswith("lungmech")]
        assert result.returncode == code and ours == [expected], (attempt, result.returncode, result.stderr)
        assert "Traceback" not in result.stderr and "SEGV" not in result.stderr, result.stderr
        assert seconds < 10, (attempt, seconds)
        assert _contents(space / "out") == before
        assert sorted(p.name for p in space.iterdir()) == ["out", "quick.toml", "slow.toml"], attempt


def test_sigterm_is_handled_after_gmsh_has_read_the_mesh(tmp_path):
    """The bundled scene's mesh is read by gmsh, which resets the handlers to the default action
    (the run died of SIGTERM without a word, its staging left; without lungmech putting its own
    back, this test sees exit -15): the run ends with its one line and 143. The signal comes at
    the solve's first progress line, after the mesh was read, whatever the machine's speed."""
    process = subprocess.Popen(
        lungmech("run", "-o", "out", cwd=tmp_path),
        cwd=tmp_path,
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    said = []
    for line in process.stdout:  # one plain line per step: the output is not a terminal
        said.append(line)
        if line.startswith(("unloading", "breathing")):
            break
    else:
        raise AssertionError(f"the bundled scene ended before it could be interrupted: {''.join(said)}")
    result = _signalled(process, signal.SIGTERM, timeout=60, said="".join(said))
    assert result.returncode == 143, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert lines == ["lungmech: interrupted by SIGTERM; nothing was written and earlier results are unchanged"]
    assert list(tmp_path.iterdir()) == []
