"""A reduction's full training solves on an ensemble, kept in the cache: a path brought back from
the cache is the path solved in place; a greedy run through an ensemble, resumed after an
interrupt, or in batches trains as it should; an imaged body's paths (both its unknowns) too;
bad requests are refused in one line."""

from dataclasses import replace
from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest
from fem import BOX, PARAMETRIC_SCENE, pushed_block, write_once
from test_one_path import IMAGED

from lungmech.app import reduce, training_paths
from lungmech.app import scene as scenes
from lungmech.app.cli import main
from lungmech.errors import Interrupted, ParameterError
from lungmech.fem.parameters import Parameters
from lungmech.fem.start import one_state
from lungmech.parallel.ensemble import Groups, Serial
from lungmech.parallel.layout import layout
from lungmech.rom import store
from lungmech.rom.greedy import greedy
from lungmech.rom.load_paths import canonical, placed, solve_path
from lungmech.rom.reductor import TrainingSet


def test_a_path_from_canonical_arrays_is_the_path_solved_here():
    """Snapshots, states at the output times and Newton iterates go to canonical arrays and back
    to the very same numbers (1 rank or several: the layout is partition-independent)."""
    full = pushed_block(MPI.COMM_WORLD)
    start = one_state(full.start, full.model)
    path = solve_path(full, {"E": 15.0, "p": 1.5}, start, iterates=True)
    full.reset()
    where = layout(full.model.space)
    back = placed(canonical(path, where), where, iterates=True)
    assert np.array_equal(back.snapshots, path.snapshots) and back.snapshots.shape[1] >= 2
    assert np.array_equal(back.solution.states, path.solution.states)
    assert np.array_equal(back.solution.outputs["volume"], path.solution.outputs["volume"])
    assert back.solution.parameters == path.solution.parameters
    assert len(back.iterates) == len(path.iterates) > back.snapshots.shape[1]
    for (x, t, mu), (y, s, nu) in zip(back.iterates, path.iterates, strict=True):
        assert np.array_equal(x, y) and t == s and mu == nu
    with pytest.raises(ParameterError, match="without its Newton iterates"):
        placed(canonical(solve_path(full, {}, start), where), where, iterates=True)


def test_a_batch_greedy_adds_its_largest_indicators_each_round():
    """batch = 3: every round but the last solves the 3 candidates of largest indicator; the
    model still meets the tolerance; the batch is checked."""
    full = pushed_block()
    candidates = Parameters(BOX).sample(16, seed=1)
    trained = greedy(full, candidates, 1e-3, batch=3)
    assert trained.met
    sizes = [r.size for r in trained.rounds[:-1]]
    assert len(trained.training) == 1 + len(sizes) and all(sizes.count(size) == 3 for size in set(sizes[:-3]))
    for left in trained.rounds[:-1]:  # a batch's points: the largest indicators of its round
        assert left.indicator >= trained.rounds[-1].indicator
    with pytest.raises(ParameterError, match="greedy batch"):
        greedy(full, candidates, 1e-3, batch=0)
    with pytest.raises(ParameterError, match="give a tolerance"):
        TrainingSet(candidates, batch=2)


class _Stopping(Serial):
    """A serial ensemble interrupted (as by Ctrl-C) after ``after`` tasks."""

    def __init__(self, after: int) -> None:
        super().__init__(MPI.COMM_WORLD)
        self.after = after

    def map(self, work, tasks, progress=None):
        if self.after < len(tasks):
            super().map(work, tasks[: self.after])
            raise Interrupted(2)
        self.after -= len(tasks)
        return super().map(work, tasks, progress)


def _basis(path: Path) -> np.ndarray:
    return store.read(path)[1]["vectors"]


def test_an_interrupted_build_resumes_from_the_paths_it_solved(tmp_path):
    """A greedy build stopped after its first full solve leaves no model file; run again, it finds them
    in the cache, solves the rest, and writes the model an uninterrupted build writes, to the
    last bit. Built once more, it solves nothing."""
    scene = scenes.load(write_once(tmp_path / "scene.toml", PARAMETRIC_SCENE))
    cache, model = tmp_path / "cache", tmp_path / "m.npz"
    common = {"tolerance": 1e-3, "samples": 8, "cache": cache}
    with pytest.raises(Interrupted):
        reduce.build(scene, model, ensemble=_Stopping(1), **common)
    assert not model.exists()
    resumed = reduce.build(scene, model, **common)["training_paths"]
    assert resumed["kept"] == 1 and resumed["solved"] >= 1
    alone = reduce.build(scene, tmp_path / "alone.npz", **common | {"cache": tmp_path / "other"})["training_paths"]
    assert alone["solved"] == resumed["solved"] + 1 and alone["kept"] == 0
    assert np.array_equal(_basis(model), _basis(tmp_path / "alone.npz"))
    again = reduce.build(scene, tmp_path / "again.npz", **common)["training_paths"]
    assert again["solved"] == 0 and again["kept"] == alone["solved"]


def test_a_kept_path_serves_again_and_a_changed_scene_is_refused(tmp_path):
    """A path kept without its Newton iterates is solved again when they are asked for (and
    then serves both); a task named from another scene than its file holds now is refused."""
    path = write_once(tmp_path / "scene.toml", PARAMETRIC_SCENE)
    scene = scenes.load(path)
    named = training_paths.scene_key(scene)
    point = {"stiffness": 900.0, "pull": 2.0}
    cache = str(tmp_path / "cache")

    def task(iterates: bool, key: str = named) -> training_paths.PathTask:
        return training_paths.PathTask(str(path), point, 1.0, iterates, training_paths.entry(key, point, 1.0))

    comm = MPI.COMM_WORLD
    assert not training_paths.training_path(task(False), comm, cache)["kept"]
    assert not training_paths.training_path(task(True), comm, cache)["kept"]  # the iterates were missing
    assert training_paths.training_path(task(False), comm, cache)["kept"]
    assert training_paths.training_path(task(True), comm, cache)["kept"]
    training_paths.forget()
    stiffer = scenes.load(write_once(tmp_path / "stiffer.toml", PARAMETRIC_SCENE.replace("500.0", "600.0")))
    assert training_paths.scene_key(stiffer) != named
    with pytest.raises(ParameterError, match="is not the scene the build read"):
        training_paths.training_path(task(False, training_paths.scene_key(stiffer)), comm, cache)


@pytest.mark.mpi
def test_groups_of_one_rank_train_the_model_of_the_whole_run(tmp_path):
    """Under mpiexec -n 2: the greedy's full solves in 2 groups of 1 rank give the basis the
    solves on both ranks give, to round-off (the same points, the same vectors)."""
    scene = scenes.load(write_once(tmp_path / "scene.toml", PARAMETRIC_SCENE))
    common = {"tolerance": 1e-3, "samples": 8, "batch": 2}
    whole = reduce.build(scene, tmp_path / "whole.npz", cache=tmp_path / "whole", **common)
    groups = Groups(1)
    try:
        split = reduce.build(scene, tmp_path / "split.npz", ensemble=groups, cache=tmp_path / "split", **common)
    finally:
        groups.free()
    assert split["training_paths"]["where"] == "2 groups of 1 rank"
    assert [r["point"] for r in split["greedy"]["rounds"]] == [r["point"] for r in whole["greedy"]["rounds"]]
    np.testing.assert_allclose(_basis(tmp_path / "split.npz"), _basis(tmp_path / "whole.npz"), atol=1e-8)


@pytest.mark.serial
@pytest.mark.slow
def test_rom_build_on_parsl_workers_is_the_serial_build(tmp_path, capsys):
    """rom build --batch 2 --engine parsl: the training's paths on 2 workers of 1 rank, the
    model bitwise the serial one's; the printout says where they ran and what was kept."""
    scene = write_once(tmp_path / "scene.toml", PARAMETRIC_SCENE)
    common = ["--tolerance", "1e-3", "--samples", "8", "--batch", "2", "-q"]
    serial = ["rom", "build", str(scene), "-o", str(tmp_path / "s.npz"), "--cache", str(tmp_path / "s"), *common]
    assert main(serial) == 0
    engine = ["--engine", "parsl", "--workers", "2", "--cache", str(tmp_path / "p")]
    assert main(["rom", "build", str(scene), "-o", str(tmp_path / "p.npz"), *common, *engine]) == 0
    said = capsys.readouterr().out
    assert "(Parsl, 2 workers of 1 rank)" in said and "found in the cache" in said
    assert np.array_equal(_basis(tmp_path / "s.npz"), _basis(tmp_path / "p.npz"))


def test_bad_training_ensemble_requests_are_refused_in_one_line(tmp_path, capsys):
    """--batch without --tolerance, --workers without --engine: one line each, exit 2, no model
    file."""
    scene = write_once(tmp_path / "scene.toml", PARAMETRIC_SCENE)
    out = str(tmp_path / "m.npz")
    for extra, said in (
        (["--batch", "2"], "a batch is the full solves of a greedy's round: give a tolerance"),
        (["--tolerance", "1e-3", "--batch", "0"], "greedy batch"),
        (["--workers", "3"], "give --engine parsl"),
    ):
        assert main(["rom", "build", str(scene), "-o", out, "-q", *extra]) == 2
        err = capsys.readouterr().err
        assert said in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not Path(out).exists()


# the imaged cube held at one face (its symmetry planes would make every state one shape): 6
# directions of its breath and 4 of its inverse motion from 4 points
SYMMETRY = "".join(f'[[constraints]]\ntype = "symmetry"\nboundary = "{a}0"\ncomponent = "{a}"\n' for a in "xyz")
IMAGED_CLAMPED = IMAGED.replace(SYMMETRY, '[[constraints]]\ntype = "clamp"\nboundary = "x0"\n')
assert IMAGED_CLAMPED != IMAGED


def test_an_imaged_bodys_paths_from_the_cache_train_the_model_solved_in_place(tmp_path):
    """Both unknowns of an imaged body's training — the breath's snapshots and the inverse
    motion's solution at each μ — solved as tasks into the cache and placed back, train the
    model its in-process training makes, to the last bit; built again, nothing is solved."""
    scene = scenes.load(write_once(tmp_path / "imaged.toml", IMAGED_CLAMPED))
    common = {"samples": 4, "size": 6, "cache": tmp_path / "cache"}
    first = reduce.build(scene, tmp_path / "a.npz", **common)["training_paths"]
    assert first == first | {"solved": 4, "kept": 0}
    again = reduce.build(scene, tmp_path / "b.npz", **common)["training_paths"]
    assert again == again | {"solved": 0, "kept": 4}
    in_place = replace(scene, source=None)  # a scene made in Python: its paths solved by the reductor itself
    reduce.build(in_place, tmp_path / "c.npz", **common)
    arrays = [store.read(tmp_path / name)[1] for name in ("a.npz", "b.npz", "c.npz")]
    assert arrays[0]["vectors"].shape[1] == 6 and arrays[0]["image/basis"].shape[1] == 4
    for name in ("vectors", "image/basis"):
        assert np.array_equal(arrays[0][name], arrays[1][name])
        assert np.array_equal(arrays[0][name], arrays[2][name])


@pytest.mark.mpi
def test_groups_of_one_rank_train_an_imaged_body_as_the_whole_run(tmp_path):
    """Under mpiexec -n 2: an imaged body's paths in 2 groups of 1 rank give the bases the
    solves on both ranks give, to round-off."""
    scene = scenes.load(write_once(tmp_path / "imaged.toml", IMAGED_CLAMPED))
    common = {"samples": 4, "size": 6}
    reduce.build(scene, tmp_path / "whole.npz", cache=tmp_path / "whole", **common)
    groups = Groups(1)
    try:
        split = reduce.build(scene, tmp_path / "split.npz", ensemble=groups, cache=tmp_path / "split", **common)
    finally:
        groups.free()
    assert split["training_paths"]["where"] == "2 groups of 1 rank" and split["training_paths"]["solved"] == 4
    whole, apart = (store.read(tmp_path / name)[1] for name in ("whole.npz", "split.npz"))
    for name in ("vectors", "image/basis"):
        np.testing.assert_allclose(np.abs(apart[name]), np.abs(whole[name]), atol=1e-8)
