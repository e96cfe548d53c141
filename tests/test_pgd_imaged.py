"""A PGD fitted to full solves of an imaged lung (lungmech.pgd.imaged): the breath from the image
and the lung's unloaded reference ξ(μ) fitted together, over two of the personalised lung's
parameters (its stiffness and the breath's depth; lying on its back). Its outputs are exact functions of
its fitted state — the probes' displacement from the reference u = w − ξ, the volume, the
reference volume —, its derivatives the splines' own; it answers as the full model does to the
fit's error; written by ``pgd build --samples`` and answered from the file. The same PGD built
a priori (lungmech.pgd.imaged_newton), no full solve, answers as the full model does to 1e-2."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest
from test_personalise import SCENE

from lungmech.app import reduce
from lungmech.app import scene as scenes
from lungmech.app.cli import main
from lungmech.app.run import full_order_model
from lungmech.fem.parametric import Outputs
from lungmech.parallel.linalg import norms
from lungmech.parallel.owned import owned_size
from lungmech.pgd.fitted import fitted
from lungmech.pgd.fitting import FIT
from lungmech.pgd.greedy import Options
from lungmech.pgd.imaged_newton import build_imaged
from lungmech.rom.basis import inner_product

PROBES = [[0.05, 0.0, 0.1], [0.05, 0.02, 0.05]]  # m: inside the phantom's right lung
POINTS = [
    {"stiffness": 150.0, "breath": 1.25},
    {"stiffness": 320.0, "breath": 0.75},
    {"stiffness": 390.0, "breath": 1.38},
]


def written(folder: Path) -> Path:
    path = folder / "imaged.toml"
    if MPI.COMM_WORLD.rank == 0:
        posture = SCENE.index("[parameters.posture]")  # the lung lying on its back: two parameters
        path.write_text(SCENE[:posture].format(h=0.04) + f"[output]\nprobes = {PROBES}\n")
    MPI.COMM_WORLD.barrier()
    return path


@pytest.fixture(scope="module")
def imaged(tmp_path_factory):
    """The imaged lung's PGD built by the CLI from 16 full solves and loaded from its file (with
    fields), and the full model."""
    folder = Path(MPI.COMM_WORLD.bcast(str(tmp_path_factory.mktemp("pgd-imaged"))))
    scene_file = written(folder)
    out = folder / "imaged-pgd.npz"
    args = ["pgd", "build", str(scene_file), "--samples", "16", "--cache", str(folder / "cache"), "-o", str(out)]
    assert main([*args, "-q"]) == 0
    full = full_order_model(scenes.load(scene_file), start="inverse_motion")
    return folder, out, reduce.load(out, fields=True), full


@pytest.mark.slow
def test_its_outputs_are_exact_functions_of_its_breath_and_reference(imaged):
    """At a point and at t₀ and T: the PGD's state made a field — the breath Q z and the
    reference ξ(μ) handed to the model — gives the model's own volume and probes (u = w − ξ)
    as the PGD answered them, to round-off."""
    _, _, pgd, _ = imaged
    outputs = Outputs(pgd.model, PROBES)
    solution = pgd.solve(POINTS[1], times=[0.0, 1.0])
    for i, t in enumerate(solution.times):
        pgd.fields(solution.states[i], float(t))
        own = outputs()
        assert own["volume"] == pytest.approx(solution.outputs["volume"][i], rel=1e-11)
        probes = solution.outputs["probes"][i]
        assert np.abs(own["probes"] - probes).max() <= 1e-10 * np.abs(probes).max()
    assert solution.start.kind == "imaged" and solution.start.details["from_image"] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.slow
def test_it_answers_as_the_full_model_to_the_fits_error(imaged):
    """At three points it was not fitted at (one near the box's corner): the volume change
    within 2e-3 of the full model's, the probes' displacement from the reference within 2e-3 of
    its size, the reference volume within 5e-4 of its change from the image (measured, 9 terms
    from 16 solves: at most 4.5e-4, 5.8e-4 and 7.3e-5)."""
    _, _, pgd, full = imaged
    for point in POINTS:
        a, b = pgd.solve(point, times=[0.0, 1.0]), full.solve(point, times=[0.0, 1.0])
        change = b.outputs["volume"][1] - b.outputs["volume"][0]
        assert abs((a.outputs["volume"][1] - a.outputs["volume"][0]) - change) <= 2e-3 * abs(change)
        probes = b.outputs["probes"]
        assert np.abs(a.outputs["probes"] - probes).max() <= 2e-3 * np.abs(probes).max()
        reference, image = b.start.details["reference_volume"], b.start.details["imaged_volume"]
        assert abs(a.start.details["reference_volume"] - reference) <= 5e-4 * abs(image - reference)


@pytest.mark.slow
def test_its_derivatives_are_its_splines_own(imaged):
    """d(outputs)/dμ at t₀ and T against central differences of the PGD itself (1e-5): the
    probes' through the breath's and the reference's splines, the volume's."""
    _, _, pgd, _ = imaged
    point = POINTS[0]
    found = pgd.solve(point, times=[0.0, 1.0], sensitivities=True).sensitivities
    for j, name in enumerate(pgd.parameters.names):
        h = 1e-4 * max(abs(point[name]), 1.0)
        ahead = pgd.solve(point | {name: point[name] + h}, times=[0.0, 1.0]).outputs
        behind = pgd.solve(point | {name: point[name] - h}, times=[0.0, 1.0]).outputs
        for output in ("probes", "volume"):
            difference = (np.asarray(ahead[output]) - np.asarray(behind[output])) / (2 * h)
            size = np.abs(difference).max()
            assert np.abs(np.asarray(found[output])[..., j] - difference).max() <= 1e-5 * size + 1e-14


@pytest.mark.slow
def test_the_file_answers_without_fields(imaged):
    """The file loaded as ``rom solve`` loads it answers as the one with fields; ``rom solve
    --set`` answers from it."""
    folder, out, pgd, _ = imaged
    plain = reduce.load(out)
    a, b = plain.solve(POINTS[2]), pgd.solve(POINTS[2])
    assert np.array_equal(a.outputs["probes"], b.outputs["probes"])
    assert main(["rom", "solve", str(out), "--set", "breath=1.1", "-o", str(folder / "answer"), "-q"]) == 0


A_PRIORI = ["--modes", "12", "--intervals", "1"]  # 12 terms on the axes' 4 × 4 Gauss points


@pytest.mark.slow
def test_a_priori_it_answers_as_the_full_model(imaged):
    """Built a priori by the CLI, no full solve: the lung's reference ξ(μ) by a Newton–PGD of
    its inverse problem, the breath from the image on it by another (lungmech.pgd.imaged_newton).
    At the three points: at t₀ it is the image, the reference volume within 1e-4 of its change
    from the image (measured: 1.0e-5 at most); at T the state within 1e-2 of the full model's in
    the energy norm (4.0e-3), the volume change within 1e-2 of itself (3.1e-4), the probes'
    displacement from the reference within 1e-2 of its size (5.1e-3); its estimate within a
    factor 5 of its largest error (5.6e-3); ``rom solve --set`` answers from its file."""
    folder, _, _, full = imaged
    out = folder / "a-priori.npz"
    assert main(["pgd", "build", str(folder / "imaged.toml"), *A_PRIORI, "-o", str(out), "-q"]) == 0
    pgd = reduce.load(out, fields=True)
    assert "the reference ξ(μ) by its own" in pgd.built["method"] and "samples" not in pgd.built
    model = full.model
    W = inner_product(model, "energy")
    owned = owned_size(model.space)
    with model.kept_state():
        model.reset()
        rest = model.state.x.array[:owned].copy()
    errors = []
    for point in POINTS:
        a, b = pgd.solve(point, times=[0.0, 1.0]), full.solve(point, times=[0.0, 1.0])
        assert a.start.details["from_image"] == pytest.approx(0.0, abs=1e-12)
        reference, image = b.start.details["reference_volume"], b.start.details["imaged_volume"]
        assert abs(a.start.details["reference_volume"] - reference) <= 1e-4 * abs(image - reference)
        error, exact = b.states[1][:owned] - pgd.reconstruct(a, 1), b.states[1][:owned] - rest
        errors.append(float(norms(error[:, None], W, MPI.COMM_WORLD)[0] / norms(exact[:, None], W, MPI.COMM_WORLD)[0]))
        change = b.outputs["volume"][1] - b.outputs["volume"][0]
        assert abs((a.outputs["volume"][1] - a.outputs["volume"][0]) - change) <= 1e-2 * abs(change)
        probes = b.outputs["probes"]
        assert np.abs(a.outputs["probes"] - probes).max() <= 1e-2 * np.abs(probes).max()
    W.destroy()
    assert max(errors) <= 1e-2, errors
    assert max(errors) / 5 <= a.indicator <= 5 * max(errors)
    assert main(["rom", "solve", str(out), "--set", "breath=0.7", "-o", str(folder / "a-priori"), "-q"]) == 0


@pytest.mark.slow
def test_its_file_is_a_recipe_of_a_patients_pgd(imaged):
    """``personalise --model`` reads a fitted PGD's recipe: a PGD of at most its --modes terms
    (the default 20) fitted to its 16 breaths, on the file's own scene."""
    from lungmech.app.recipe import recipe_scene

    folder, out, _, _ = imaged
    with recipe_scene(out, None) as (recipe, scene):
        assert (recipe.method, recipe.size, recipe.training, recipe.tau) == ("pgd", 20, 16, None)
        assert [p.name for p in scene.parameters] == ["stiffness", "breath"] and scene.inverse is not None


@pytest.mark.mpi
@pytest.mark.parametrize("how", ["fitted", "a priori"])
def test_an_imaged_pgd_on_two_ranks_answers_as_one_ranks(tmp_path_factory, how):
    """The same PGD built on the world's ranks and on this rank alone: the probes (u = w − ξ)
    and the reference volume at random points agree to 1e-9 (a priori, measured: the probes to
    6.4e-11, the reference volume to 6e-14)."""
    folder = Path(MPI.COMM_WORLD.bcast(str(tmp_path_factory.mktemp("pgd-imaged-mpi"))))
    scene = scenes.load(written(folder))
    found = {}
    for name, comm in (("world", MPI.COMM_WORLD), ("self", MPI.COMM_SELF)):
        full = full_order_model(scene, comm, start="inverse_motion")
        if how == "fitted":
            found[name] = fitted(full, 8, 1, replace(FIT, max_terms=6), PROBES)[0]
        else:
            found[name] = build_imaged(full, PROBES, 1, Options(max_terms=12))[0]
    for point in found["self"].parameters.sample(3, seed=9):
        a, b = found["world"].solve(point, times=[0.0, 1.0]), found["self"].solve(point, times=[0.0, 1.0])
        difference = np.abs(a.outputs["probes"] - b.outputs["probes"]).max() / np.abs(b.outputs["probes"]).max()
        print(
            how,
            "probes",
            difference,
            "reference",
            a.start.details["reference_volume"] / b.start.details["reference_volume"] - 1,
        )
        assert difference <= 1e-9
        assert a.start.details["reference_volume"] == pytest.approx(b.start.details["reference_volume"], rel=1e-9)
