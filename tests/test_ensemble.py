"""The ensemble layer (lungmech.parallel.ensemble): the same full solves, run serially and in
groups of ranks, give the same answers (bitwise for groups of one rank, to 1e-9 for a group
of two); a failing task is reported for its point and the others go on."""

from functools import partial
from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest
from trades import written

from lungmech.app import answers
from lungmech.app.answers import Task
from lungmech.app.ladder import Discretisation
from lungmech.errors import ParameterError
from lungmech.parallel.ensemble import Groups, Outcome, Serial, attempt


def tasks(folder) -> list[Task]:
    scene = str(written(folder))
    stiffness = [5.0, 7.5, 12.0, 20.0]
    return [Task(scene, {"stiffness": e}, Discretisation(0, 1), (1.0,)) for e in stiffness] + [
        Task(str(folder / "missing.toml"), {"stiffness": 5.0}, Discretisation(0, 1), (1.0,))
    ]


def halve(task: float, comm: MPI.Comm) -> float:
    if task < 0:
        raise ParameterError(f"no negative task (got {task})")
    if task == 0:
        raise ZeroDivisionError("a bug in the work")
    return comm.allreduce(task, op=MPI.SUM) / comm.size / 2


def test_serial_outcomes_in_order_and_failures_in_one_line():
    lines = []
    found = Serial(MPI.COMM_WORLD).map(halve, [4.0, -1.0, 0.0, 6.0], lines.append)
    assert found[0] == Outcome(2.0) and found[3] == Outcome(3.0)
    assert found[1] == Outcome(None, "no negative task (got -1.0)")
    assert found[2] == Outcome(None, "ZeroDivisionError: a bug in the work")
    if MPI.COMM_WORLD.rank == 0:
        assert len(lines) == 4 and lines[-1].startswith("4/4 solves done, 2 failed")


@pytest.mark.mpi
def test_groups_deal_the_tasks_and_every_rank_gets_every_outcome():
    comm = MPI.COMM_WORLD
    groups = Groups(1, comm)
    lines = []
    found = groups.map(halve, [float(i) for i in range(1, 8)] + [-2.0], lines.append)
    groups.free()
    if comm.rank == 0:  # the progress counts every group's tasks, and the failure
        assert lines[-1].startswith("8/8 solves done, 1 failed")
        assert all(int(line.split("/")[0]) <= 8 for line in lines)
    assert [o.value for o in found[:7]] == [i / 2 for i in range(1, 8)]
    assert found[7].failed == "no negative task (got -2.0)"
    with pytest.raises(ParameterError, match="--group-size"):
        Groups(3, comm)


@pytest.mark.mpi
@pytest.mark.slow
def test_full_solves_in_groups_equal_the_serial_ones(tmp_path):
    """Groups of one rank: bitwise the one-rank answers; one group of two ranks: to 1e-9."""
    comm = MPI.COMM_WORLD
    work = tasks(tmp_path)
    groups = Groups(1, comm)
    dealt = groups.map(partial(answers.solved, cache=str(tmp_path / "groups")), work)
    answers.forget()
    groups.free()
    together = Serial(comm).map(partial(answers.solved, cache=str(tmp_path / "two")), work)
    answers.forget()
    alone = comm.Split(comm.rank)
    one = Serial(alone).map(partial(answers.solved, cache=str(tmp_path / "one")), work) if comm.rank == 0 else None
    answers.forget()
    alone.Free()
    one = comm.bcast(one, root=0)
    for a, b, c in zip(one[:4], dealt[:4], together[:4], strict=True):
        assert a.failed is None and a.value["failed"] is None
        assert a.value["volume"] == b.value["volume"] and a.value["probes"] == b.value["probes"]
        np.testing.assert_allclose(c.value["volume"], a.value["volume"], rtol=1e-9)
    for outcome in (one[4], dealt[4], together[4]):
        assert outcome.value is None and "missing.toml" in outcome.failed


def test_an_interrupt_is_not_a_failed_task():
    def interrupted(task, comm):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        attempt(interrupted, 1, MPI.COMM_WORLD)


def dies(task: tuple[str, bool], comm: MPI.Comm) -> str:
    """Kill this process — the first time (its marker file absent), or ``always``: a lost worker."""
    import os
    import signal

    marker, always = task
    if always or not os.path.exists(marker):
        open(marker, "w").close()
        os.kill(os.getpid(), signal.SIGKILL)
    return f"{comm.size} rank(s), on the second try"


@pytest.mark.serial
@pytest.mark.slow
def test_parsl_workers_answer_as_the_serial_solves_and_a_lost_worker_retries(tmp_path, monkeypatch):
    """Parsl's local pool: 2 workers of 1 rank give the one-rank answers bitwise, 1 worker of
    2 ranks to 1e-9; a task whose process is killed is submitted once more; a task that
    always dies is reported failed, the others go on."""
    from lungmech.parallel.engine import local_pool

    monkeypatch.setenv("PYTHONPATH", str(Path(__file__).parent))  # the workers import this file's functions
    work = tasks(tmp_path)
    serial = Serial(MPI.COMM_SELF).map(partial(answers.solved, cache=str(tmp_path / "serial")), work)
    answers.forget()
    with local_pool(2, 1) as pool:
        assert pool.description == "Parsl, 2 workers of 1 rank"
        dealt = pool.map(partial(answers.solved, cache=str(tmp_path / "pool")), work)
        lost = pool.map(dies, [(str(tmp_path / "once"), False), (str(tmp_path / "always"), True)])
    for a, b in zip(serial[:4], dealt[:4], strict=True):
        assert a.value["volume"] == b.value["volume"] and a.value["probes"] == b.value["probes"]
    assert "missing.toml" in dealt[4].failed
    assert lost[0].value == "1 rank(s), on the second try"
    assert lost[1].value is None and lost[1].failed.startswith("its worker failed 2×")
    with local_pool(1, 2) as pool:
        wide = pool.map(partial(answers.solved, cache=str(tmp_path / "wide")), work[:2])
    for a, b in zip(serial[:2], wide, strict=True):
        np.testing.assert_allclose(b.value["volume"], a.value["volume"], rtol=1e-9)
