"""A scene over a population (lungmech.app.template): [geometry] shape_modes names a library's
modes, the model is solved on the library's mean shape, and shape.mode_<i> parameters move it.

Independent reference: the scene's model built by hand on the mesh the library itself makes at
those coefficients (ShapeModes.geometry: the reference's nodes moved), with no shape map.
"""

import json
import os
import re

from mpi4py import MPI

import numpy as np
import pytest
from fem import write_once

from lungmech.app import scene as scenes
from lungmech.app.cli import main
from lungmech.app.run import build_model, full_order_model
from lungmech.fem.model import Model
from lungmech.fem.parametric import FullOrderModel
from lungmech.fem.quantities import Probe
from lungmech.mesh import box, nodes
from lungmech.registration.library import ShapeModes, shape_modes

BOX = """title = "a block of a small population"
[geometry]
builder = "box"
cells = [4, 2, 2]
lengths = [2.0, 1.0, 1.0]
shape_modes = "modes.npz"
[material]
law = "neo_hookean"
E = 1.0e3
nu = 0.3
[[constraints]]
type = "clamp"
boundary = "x0"
[[loads]]
type = "follower_pressure"
name = "push"
boundary = "x1"
value = 40.0
[[loads]]
type = "body_force"
value = [0.0, 0.0, -30.0]
[output]
fields = false
probes = [[1.5, 0.5, 0.5]]
[parameters.a1]
target = "shape.mode_1"
range = [-2.0, 2.0]
[parameters.a2]
target = "shape.mode_2"
range = [-2.0, 2.0]
"""


def library(geometry) -> ShapeModes:
    """The modes of 8 blocks: two smooth changes of a few cm, mixed at random."""
    comm = geometry.mesh.comm
    space, where = nodes.displacement_space(geometry.mesh)
    X = comm.bcast(nodes.positions(space, where))
    weights = comm.bcast(nodes.masses(space, where))
    changes = [
        0.05 * np.column_stack([X[:, 0] * X[:, 2], np.zeros(len(X)), X[:, 2] ** 2]),
        0.04 * np.column_stack([np.sin(2 * X[:, 1]), X[:, 0] ** 2 / 4, np.zeros(len(X))]),
    ]
    latent = np.random.default_rng(5).normal(size=(8, 2))
    members = [np.einsum("k,knd->nd", z, np.array(changes)) for z in latent]
    return shape_modes(X, members, weights, where.fingerprint, tuple(f"block{i}" for i in range(8)))


@pytest.fixture
def population(tmp_path):
    """(the scene file, its library) in ``tmp_path``."""
    path = write_once(tmp_path / "scene.toml", BOX)
    modes = library(box(MPI.COMM_WORLD, cells=(4, 2, 2), lengths=(2.0, 1.0, 1.0)))
    if MPI.COMM_WORLD.rank == 0:
        modes.save(tmp_path / "modes.npz")
    MPI.COMM_WORLD.Barrier()
    return path, modes


def on_the_moved_mesh(scene, modes, coefficients) -> FullOrderModel:
    """The scene's physics on the library's own mesh at ``coefficients``, built by hand; its
    probes at the material points of the scene's (given on the template, the mean shape)."""
    template, fields = modes.template(scenes.build_geometry(scene.geometry, MPI.COMM_WORLD), len(coefficients))
    displacement = fields[0].copy()
    displacement.x.array[:] = sum(c * f.x.array for c, f in zip(coefficients, fields))
    moves = Probe(template.mesh, scene.output.probes)(displacement)
    geometry = modes.geometry(scenes.build_geometry(scene.geometry, MPI.COMM_WORLD), coefficients)
    model = Model(geometry, scene.material, loads=scene.loads, constraints=scene.constraints)
    return FullOrderModel(model, scene.stepping, probes=np.array(scene.output.probes) + moves)


def test_a_scene_over_a_population_is_the_scene_on_the_patients_mesh(population):
    path, modes = population
    scene = scenes.load(path)
    assert [p.unit for p in scene.parameters] == ["sd", "sd"]  # the library's standard deviations
    template = full_order_model(scene)
    for c in ([1.5, -1.0], [-0.7, 1.8]):
        ours = template.solve({"a1": c[0], "a2": c[1]}).outputs
        exact = on_the_moved_mesh(scene, modes, c).solve({}).outputs
        assert ours["volume"][-1] == pytest.approx(exact["volume"][-1], rel=1e-9)
        assert ours["strain_energy"][-1] == pytest.approx(exact["strain_energy"][-1], rel=1e-7)
        assert np.abs(ours["probes"] - exact["probes"]).max() <= 1e-7 * np.abs(exact["probes"]).max()


def test_a_scene_without_shape_parameters_is_the_mean_shape(population):
    path, modes = population
    text = BOX.split("[parameters.a1]")[0]
    scene = scenes.parse(scenes.tomllib.loads(text), folder=path.parent)
    model = build_model(scene)
    assert model.shape is None
    mean = modes.geometry(scenes.build_geometry(scene.geometry, MPI.COMM_WORLD), [])
    assert model.geometry.volume() == pytest.approx(mean.volume(), rel=1e-12)


@pytest.mark.slow
def test_one_hyper_reduced_model_file_serves_the_population(population, tmp_path):
    """rom build --hyper ecsw over the shape box → rom solve --set at a shape it was not
    trained on, on its sampled cells alone and with the library no longer on disk (the model
    file holds it): the full run's answer there within the basis' error."""
    path, _ = population
    model = tmp_path / "population.npz"
    build = ["--samples", "8", "--size", "8", "--hyper", "ecsw", "--ecsw-tolerance", "1e-4", "-q"]
    assert main(["rom", "build", str(path), "-o", str(model), *build]) == 0
    point = ["--set", "a1=0.9", "--set", "a2=-1.3"]
    assert main(["run", str(path), "-o", str(tmp_path / "full"), *point, "-q"]) == 0
    if MPI.COMM_WORLD.rank == 0:
        os.rename(tmp_path / "modes.npz", tmp_path / "elsewhere.npz")
    MPI.COMM_WORLD.Barrier()
    assert main(["rom", "solve", str(model), "-o", str(tmp_path / "reduced"), *point, "-q"]) == 0
    reduced, full = (json.loads((tmp_path / name / "summary.json").read_text()) for name in ("reduced", "full"))
    assert reduced["solver"].startswith("hyper-reduced (ECSW")
    change = full["deformed_volume"] - full["start_volume"]  # measured: 1.7e-3 of it (8 vectors, τ = 1e-4)
    assert abs(reduced["deformed_volume"] - full["deformed_volume"]) <= 5e-3 * abs(change)
    assert reduced["start_volume"] == pytest.approx(full["start_volume"], rel=1e-12)  # the shape's own


@pytest.mark.parametrize(
    "change, message",
    [
        (('shape_modes = "modes.npz"\n', ""), "parameters.a1.target: shape.mode_1 is a shape mode's coefficient: name"),
        (("modes.npz", "missing.npz"), "geometry.shape_modes: shape modes file '.*missing.npz' not found"),
        (
            ("shape.mode_2", "shape.mode_3"),
            "geometry.shape_modes: '.*modes.npz' holds 2 modes; a parameter names mode 3",
        ),
        (("[-2.0, 2.0]", "[-60.0, 60.0]"), "the shape at a1 = -?60, a2 = -?60 folds the mesh"),
    ],
)
def test_a_bad_population_scene_gets_one_line(population, change, message, capsys):
    path, _ = population
    bad = write_once(path.with_name("bad.toml"), BOX.replace(*change))
    assert main(["run", str(bad), "-o", str(path.with_name("out")), "-q"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(message, err[0]), err


def test_a_nonlinear_pgd_over_shape_coefficients_a_priori_is_refused_in_one_line(population, capsys):
    """The neo-Hookean block bending under its weight (its tip moves about a third of its
    length: large rotations) and its follower pressure: the Newton–PGD from its tangent at
    rest diverges, and is refused in one line within a few iterations, nothing written. (The
    linear block's a priori PGD over the shape: tests/test_pgd_shape.py; a nonlinear one that
    converges: tests/test_pgd_newton.py.)"""
    path, _ = population
    out = path.with_name("pgd.npz")
    assert main(["pgd", "build", str(path), "-o", str(out), "--modes", "4", "-q"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "did not converge" in err[0] and "give --samples" in err[0], err
    assert not out.exists()


IMAGED = {  # the block as imaged under its loads (ramped from 1 to 2): its reference ξ(μ) moves with the shape
    "[output]": "[inverse]\ntolerance = 1e-9\n[output]",
    "value = 40.0\n": "value = 40.0\nramp = { times = [0.0, 1.0], values = [1.0, 2.0] }\n",
    "-30.0]\n": "-30.0]\nramp = { times = [0.0, 1.0], values = [1.0, 2.0] }\n",
}


@pytest.mark.slow
@pytest.mark.parametrize(
    "imaged",
    [False, pytest.param(True, marks=pytest.mark.long)],  # imaged: 15 s, make test-long (2 ranks: test_pgd_fitted)
    ids=["at rest on its mesh", "imaged"],
)
def test_a_fitted_pgd_follows_the_shape(population, tmp_path, imaged):
    """`pgd build --samples` over the shape box → `rom solve --set` at a shape it was not fitted
    at: the full run's start volume (the shape's own: a cubic in a), its deformed volume,
    strain energy and probe within the fit's error (before the volume followed the shape: 1.95
    m³ where the full model gives 2.15); on an imaged block, its reference volume too; d(volume)/da
    the PGD's own central differences."""
    from lungmech.app import reduce

    path, _ = population
    if imaged:
        text = BOX
        for old, new in IMAGED.items():
            assert old in text
            text = text.replace(old, new)
        path = write_once(path.with_name("imaged.toml"), text)
    model = tmp_path / "pgd.npz"
    assert main(["pgd", "build", str(path), "-o", str(model), "--samples", "24", "-q"]) == 0
    point = ["--set", "a1=0.9", "--set", "a2=-1.3"]
    assert main(["run", str(path), "-o", str(tmp_path / "full"), *point, "-q"]) == 0
    assert main(["rom", "solve", str(model), "-o", str(tmp_path / "pgd"), *point, "-q"]) == 0
    pgd, full = (json.loads((tmp_path / name / "summary.json").read_text()) for name in ("pgd", "full"))
    assert pgd["start_volume"] == pytest.approx(full["start_volume"], rel=1e-9)  # (the full start: w to 1e-9)
    # measured: 2.4e-4 of the change, 2.7e-6, 5.6e-5 of the motion (24 solves: 15 terms, held out 3.6e-4);
    # imaged, 7.5e-4, 9e-6, 2.8e-5 and the reference volume 1.4e-4 of its distance from the image's
    change = full["deformed_volume"] - full["start_volume"]
    assert abs(pgd["deformed_volume"] - full["deformed_volume"]) <= 3e-3 * abs(change), (pgd, full)
    assert pgd["strain_energy"] == pytest.approx(full["strain_energy"], rel=1e-4)
    motion = np.abs(full["probes"]["displacement"]).max()
    assert np.abs(np.subtract(pgd["probes"]["displacement"], full["probes"]["displacement"])).max() <= 1e-3 * motion
    if imaged:
        apart = full["reference_volume"] - full["start_volume"]
        assert abs(pgd["reference_volume"] - full["reference_volume"]) <= 1e-3 * abs(apart)
    loaded = reduce.load(model)
    mu = {"a1": 0.9, "a2": -1.3}
    found = loaded.solve(mu, sensitivities=True)
    for j, name in enumerate(("a1", "a2")):
        h = 1e-5
        ahead, behind = (loaded.solve(mu | {name: mu[name] + s}).outputs["volume"] for s in (h, -h))
        assert found.sensitivities["volume"][-1, j] == pytest.approx((ahead[-1] - behind[-1]) / (2 * h), rel=1e-6)
    assert found.start.details["volume"] == pytest.approx(full["start_volume"], rel=1e-9)
