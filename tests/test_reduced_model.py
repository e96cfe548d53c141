"""Reduced models are models: solve(mu) like the full one, trained over a parameter box, saved
with everything they need."""

import shutil
import tomllib

from mpi4py import MPI

import numpy as np
import pytest
from fem import BOX, pushed_block

from lungmech.app import reduce as reduce_app
from lungmech.app import scene as scenes
from lungmech.errors import ParameterError
from lungmech.fem.parameters import Parameters
from lungmech.mesh import box
from lungmech.rom.reductor import POD, TrainingSet, errors, reduce


@pytest.fixture(scope="module")
def full():
    return pushed_block()


@pytest.fixture(scope="module")
def reduced(full):
    return reduce(full, POD(20), TrainingSet(Parameters(BOX).sample(16, seed=1)))


def test_full_and_reduced_answer_the_same_calls(full, reduced):
    mu = {"E": 8.0, "p": 1.2}
    f, r = full.solve(mu), reduced.solve(mu)
    assert f.times.tolist() == r.times.tolist() == [0.5, 1.0, 1.5, 2.0]
    assert set(f.outputs) == set(r.outputs) == {"volume", "strain_energy", "probes", "loads/push"}
    assert r.states.shape == (4, reduced.size) and f.states.shape[0] == 4
    assert r.outputs["loads/push"] == pytest.approx([0.6, 1.2, 0.6, 0.0])
    assert r.parameters == f.parameters == {"E": 8.0, "nu": 0.3, "p": 1.2}


def test_unseen_points_of_the_box(full, reduced):
    """Ten points the basis never saw (another seed): energy-norm error ≤ 1e-3, volume ≤ 1e-4."""
    worst = []
    for mu in Parameters(BOX).sample(10, seed=77):
        e = errors(reduced, full.solve(mu), reduced.solve(mu))
        worst.append((e.energy, e.volume_change))
    energy, volume = np.max(worst, axis=0)
    assert energy <= 1e-3 and volume <= 1e-4


def test_a_basis_of_one_training_point_does_not_cover_the_box(full):
    """The error measure can fail: one point's load path does not span the box."""
    poor = reduce(full, POD(2), TrainingSet([{"E": 5.0, "nu": 0.2, "p": 0.2}]))
    e = errors(poor, full.solve({"E": 20.0, "nu": 0.45, "p": 2.0}), poor.solve({"E": 20.0, "nu": 0.45, "p": 2.0}))
    assert e.energy > 1e-3


def test_reduced_parameters_are_checked(reduced):
    with pytest.raises(ParameterError, match="outside its range"):
        reduced.solve({"E": 50.0})


MESHED = """
title = "block from a mesh file"
[geometry]
file = "block.xdmf"
[material]
law = "neo_hookean"
E = 10.0
nu = 0.3
[[constraints]]
type = "clamp"
boundary = "x0"
[[loads]]
type = "follower_pressure"
boundary = "x1"
value = 1.0
name = "push"
[parameters.stiffness]
target = "material.E"
range = [5.0, 20.0]
[parameters.pressure]
target = "loads.push.value"
range = [0.2, 2.0]
[output]
fields = false
"""


@pytest.mark.serial  # makes and removes the scene's files from one process
def test_a_saved_model_holds_its_scene_and_mesh(tmp_path):
    """Built from a scene on a mesh file, the model file solves after the scene and mesh are gone."""
    from lungmech.mesh import write

    source = tmp_path / "source"
    source.mkdir()
    write(box(MPI.COMM_WORLD, cells=(3, 2, 2)), source / "block.xdmf")
    (source / "scene.toml").write_text(MESHED)
    scene = scenes.load(source / "scene.toml")
    reduce_app.build(scene, tmp_path / "model.npz", samples=4, size=10)
    before = reduce_app.load(tmp_path / "model.npz").solve({"stiffness": 12.0, "pressure": 1.5})
    shutil.rmtree(source)
    after = reduce_app.load(tmp_path / "model.npz").solve({"stiffness": 12.0, "pressure": 1.5})
    assert after.outputs["volume"] == pytest.approx(before.outputs["volume"], rel=1e-12)
    with reduce_app.embedded_scene(tmp_path / "model.npz") as inside:
        assert inside.title == "block from a mesh file" and [p.name for p in inside.parameters] == [
            "stiffness",
            "pressure",
        ]


def test_training_points_cover_the_box_and_are_stored(tmp_path):
    table = tomllib.loads(MESHED.replace('file = "block.xdmf"', 'builder = "box"\ncells = [2, 2, 2]'))
    scene = scenes.parse(table)
    summary = reduce_app.build(scene, tmp_path / "m.npz", samples=4, size=6)
    model = reduce_app.load(tmp_path / "m.npz")
    assert len(model.training) == 4 and summary["size"] <= 6
    stiffness = [point["stiffness"] for point in model.training]
    assert min(stiffness) < 9.0 < 14.0 < max(stiffness)  # spread over [5, 20], not bunched


def test_reduced_sensitivities_are_the_derivatives_of_the_reduced_model(full, reduced):
    """d(outputs)/dμ of the reduced model = central differences of its own solves; and close to the
    full model's (the basis spans the box)."""
    mu = {"E": 9.0, "nu": 0.33, "p": 1.3}
    exact = reduced.solve(mu, sensitivities=True)
    full_exact = full.solve(mu, sensitivities=True)
    for i, p in enumerate(BOX):
        h = 1e-4 * (p.range[1] - p.range[0])
        up, down = reduced.solve(mu | {p.name: mu[p.name] + h}), reduced.solve(mu | {p.name: mu[p.name] - h})
        for name in ("volume", "strain_energy"):
            fd = (up.outputs[name] - down.outputs[name]) / (2 * h)
            # abs: the solves' own convergence over 2h, a chord step's last ‖r‖ ~1e-13 of the first
            assert exact.sensitivities[name][:, i] == pytest.approx(fd, rel=1e-5, abs=1e-8 * np.abs(fd).max())
            assert exact.sensitivities[name][:, i] == pytest.approx(
                full_exact.sensitivities[name][:, i], rel=1e-3, abs=1e-6 * np.abs(fd).max()
            )


def test_a_model_file_of_another_version_is_refused_with_what_to_do(tmp_path):
    import json

    from lungmech.errors import ModelFileError
    from lungmech.rom import store

    path = tmp_path / "old.npz"
    if MPI.COMM_WORLD.rank == 0:
        np.savez(path, metadata=json.dumps({"format": "lungmech-rom/1"}), vectors=np.zeros((3, 1)), values=np.ones(1))
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(ModelFileError, match="another lungmech version.*rebuild it"):
        store.read(path)


def test_bad_training_counts_are_one_line_errors(tmp_path):
    table = tomllib.loads(MESHED.replace('file = "block.xdmf"', 'builder = "box"\ncells = [2, 2, 2]'))
    scene = scenes.parse(table)
    with pytest.raises(ParameterError, match="training samples must be >= 1"):
        reduce_app.build(scene, tmp_path / "m.npz", samples=0)
    with pytest.raises(ParameterError, match="training seed must be >= 0"):
        reduce_app.build(scene, tmp_path / "m.npz", samples=2, seed=-1)
    assert not (tmp_path / "m.npz").exists()
