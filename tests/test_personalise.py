"""lungmech personalise on a synthetic patient: the whole pipeline from two segmentations.

The patient is made by lungmech's full model on a finer mesh (the bundled lung's physics, its
weight balanced by the pleural pressure, lying on its back) at known parameters, voxelised at
4 mm at end-expiration and end-inspiration; the estimate registers the scene's coarse lung
(< 2k cells) onto the first image, builds the patient's hyper-reduced model, fits the second.
Without noise the estimate is as good as the full model on the estimate's mesh fitted to the
same images (the discretisation's gap) to 1 % of the range.
"""

import csv
import json
from dataclasses import replace
from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest

from lungmech import meshes
from lungmech.app import scene as scenes
from lungmech.app.personalise import Pair, Setting, estimated, personalise, position_values, prepare
from lungmech.app.run import full_order_model
from lungmech.errors import ParameterError
from lungmech.registration.image import from_array
from lungmech.twin.fit import Fit, estimate
from lungmech.twin.synthetic import displacement_field, image_pair, surface_noise
from lungmech.twin.uncertainty import laplace

SCENE = """
title = "a lung to personalise"
[geometry]
builder = "lung_phantom"
side = "right"
mesh_size = {h}
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
type = "clamp"
boundary = "hilum"
[[loads]]
type = "follower_pressure"
name = "pleural"
boundary = ["pleura", "diaphragm", "mediastinum"]
value = -500.0
ramp = {{ times = [0.0, 1.0], values = [1.0, 2.0] }}
[[loads]]
type = "gravity"
name = "gravity"
density = 315.0
acceleration = [0.0, 0.0, -9.81]
balanced_on = ["pleura", "diaphragm", "mediastinum"]
ramp = {{ times = [0.0, 1.0], values = [1.0, 1.0] }}
[inverse]
tolerance = 1e-9
[stepping]
end = 1.0
max_step = 0.5
[parameters.stiffness]
target = "material.c1"
range = [100.0, 400.0]
scale = "log"
[parameters.breath]
target = "loads.pleural.amplitude"
range = [0.6, 1.4]
[parameters.posture]
target = "loads.gravity.pitch"
range = [-90.0, 90.0]
"""
TRUTH = {"stiffness": 200.0, "breath": 1.15, "posture": -90.0}  # lying on the back


def scene_of(folder, size: float):
    path = folder / f"lung-{size}.toml"
    path.write_text(SCENE.format(h=size))
    return scenes.load(path)


@pytest.fixture(scope="module")
def patient(tmp_path_factory):
    """The synthetic patient's segmentations (its mesh: 0.02 m cells), supine and prone, and
    its supine displacement field as an intensity registration would give it."""
    folder = tmp_path_factory.mktemp(f"patient-rank{MPI.COMM_WORLD.rank}")
    truth = full_order_model(scene_of(folder, 0.02), start="inverse_motion")
    supine = image_pair(truth, TRUTH, 1.0, 0.004)
    return folder, {
        "supine": supine,
        "prone": image_pair(truth, TRUTH | {"posture": 90.0}, 1.0, 0.004),
        "field": displacement_field(truth, TRUTH, 1.0, supine[0], smoothing=1.0),  # supine, smoothed by a voxel
    }


@pytest.fixture(scope="module")
def breathing(patient):
    """The supine patient made ready to estimate its breath (the stiffness known): registered,
    its reduced model built and checked against the full model and the lung refined once."""
    folder, images = patient
    setting = Setting(estimate=("breath",), training=6, size=8)
    return prepare(scene_of(folder, 0.035), [Pair(*images["supine"], "supine")], setting)


@pytest.mark.slow
def test_a_synthetic_patients_breath_is_found_as_well_as_the_full_model_finds_it(breathing):
    """Without noise: the reduced estimate is within 1 % of the range of the full model's own
    fit on the same mesh (whose error is the gap), and within 2 % of the truth; the interval,
    widened by the reduction's and the mesh's errors as a bias, holds the truth."""
    report = estimated(breathing, Setting(estimate=("breath",), resamples=4, full_fit=True))
    found = report["parameters"]["breath"]["value"]
    full = report["full_order_estimate"]["breath"]
    assert abs(found - TRUTH["breath"]) <= abs(full - TRUTH["breath"]) + 0.01 * 0.8
    assert abs(found - TRUTH["breath"]) < 0.02 * TRUTH["breath"]  # the gap: coarse mesh, 4 mm voxels, registration
    low, high = report["parameters"]["breath"]["interval"]
    assert low < TRUTH["breath"] < high  # the mesh's own error (against the lung refined once) in its bias
    assert [len(point["steps"]) for point in report["model_check"]] == [2, 2, 2]  # reduction, then the mesh
    assert report["fixed"] == {"supine": {"posture": -90.0}} and report["data_noise"] == 0.0
    assert report["fit"]["surface_rms"] < 0.001  # m: a quarter of a voxel
    assert report["registration"][0]["dice"] > 0.97
    assert set(report["seconds"]) >= {"registration", "offline", "estimate", "confirmation"}


@pytest.mark.slow
def test_a_pgd_of_the_patients_breaths_finds_the_breath_as_the_reduced_model_does(patient, breathing):
    """The patient's model a PGD fitted to 16 breaths (the breath and the lung's reference ξ(μ),
    answered by evaluation), no mesh check: its estimate within 1 % of the range of the reduced
    model's (POD–ECSW), its interval holding that estimate (the truth lies beyond both by the
    coarse mesh's own error, which only the mesh check adds to the bias)."""
    folder, images = patient
    setting = Setting(estimate=("breath",), training=16, size=12, method="pgd", mesh_check=False)
    ready = prepare(scene_of(folder, 0.035), [Pair(*images["supine"], "supine")], setting)
    report = estimated(ready, replace(setting, resamples=0))
    reduced = estimated(breathing, Setting(estimate=("breath",), resamples=0))
    found, other = report["parameters"]["breath"]["value"], reduced["parameters"]["breath"]["value"]
    assert abs(found - other) <= 0.01 * 0.8
    low, high = report["parameters"]["breath"]["interval"]
    assert low < other < high
    assert report["model"]["method"] == "pgd" and report["model"]["tau"] is None


@pytest.mark.slow
def test_at_ten_percent_noise_the_interval_holds_the_truth(breathing):
    """Gaussian noise of 10 % of the surface's RMS motion on every surface datum (seeded): the
    estimate moves, the noise level the residual shows is the fit's own and the added noise's
    together, the interval grows and holds the truth."""
    quiet = estimated(breathing, Setting(estimate=("breath",), resamples=0))
    noisy = estimated(breathing, Setting(estimate=("breath",), resamples=4, noise=0.1, seed=3))
    assert noisy["parameters"]["breath"]["value"] != pytest.approx(quiet["parameters"]["breath"]["value"], abs=1e-4)
    added = surface_noise(breathing.fit(), 0.1, seed=3)  # the same draw: seeded
    assert noisy["noise_sigma"] == pytest.approx(np.hypot(quiet["noise_sigma"], np.sqrt(np.mean(added**2))), rel=0.15)
    low, high = noisy["parameters"]["breath"]["interval"]
    assert low < TRUTH["breath"] < high
    assert high - low > np.subtract(*quiet["parameters"]["breath"]["interval"][::-1])


@pytest.mark.slow
def test_a_second_position_separates_the_stiffness_from_the_breath(patient):
    """Supine and prone together, the stiffness and the breath estimated: each pair is its own
    registration and model, the posture fixed per pair; the prone pair's gravity narrows the
    stiffness's deviation, which supine alone leaves wide (a stiffer lung under a deeper
    breath looks alike)."""
    folder, images = patient
    setting = Setting(estimate=("stiffness", "breath"), training=4, size=6, resamples=0, mesh_check=False)
    both = prepare(scene_of(folder, 0.035), [Pair(*images[p], p) for p in ("supine", "prone")], setting)
    report = estimated(both, setting)
    assert report["fixed"] == {"supine": {"posture": -90.0}, "prone": {"posture": 90.0}}
    assert [pair["pair"] for pair in report["fit"]["pairs"]] == ["supine", "prone"]
    assert all(pair["surface_rms"] < 0.001 for pair in report["fit"]["pairs"])
    supine = Fit(both.views[:1], both.estimated)
    alone = laplace(estimate(supine), supine)
    together = laplace(estimate(both.fit()), both.fit())
    assert np.sqrt(together.covariance[0, 0]) < np.sqrt(alone.covariance[0, 0])
    assert abs(report["parameters"]["breath"]["value"] - TRUTH["breath"]) < 0.05 * TRUTH["breath"]


@pytest.mark.slow
def test_a_displacement_field_inside_the_lung_joins_the_data(patient):
    """The supine pair with its displacement field (smoothed by a 4 mm voxel, taken one per
    8 mm): the field's rows weighed by its noise against the surface's, the stiffness's
    deviation narrower than the surface alone leaves it, and the report says so."""
    from lungmech.twin.displacement import Displacement

    folder, images = patient
    setting = Setting(estimate=("stiffness", "breath"), training=4, size=6, resamples=0, mesh_check=False)
    pair = Pair(*images["supine"], "supine", Displacement(images["field"], 0.008))
    ready = prepare(scene_of(folder, 0.035), [pair], setting)
    first = estimate(ready.fit())
    weighed = ready.weighed(first.residual)
    found = estimate(weighed.fit(), start=first.values)
    (inside,) = weighed.fit().interior_rows()
    surface = np.setdiff1d(np.arange(len(found.residual)), inside)
    alone = np.linalg.inv(found.jacobian[surface].T @ found.jacobian[surface])
    joined = np.linalg.inv(found.jacobian.T @ found.jacobian)
    assert joined[0, 0] < 0.5 * alone[0, 0]  # the field tells the stiffness apart
    report = estimated(ready, setting)
    interior = report["fit"]["pairs"][0]["interior"]
    assert interior["points"] >= 10 and interior["smoothing"] == 0.008
    assert interior["weight"] == pytest.approx(weighed.views[0].interior.weight)
    assert interior["rms"] < 0.002  # m
    assert report["parameters"]["breath"]["value"] == pytest.approx(TRUTH["breath"], rel=0.05)


def chest(image, gap: int = 10):
    """A segmentation of both lungs: ``image``'s right lung and its mirror image across a
    mediastinum ``gap`` voxels wide (a left lung breathing alike: the weight's pitch turns about
    the left-right axis, which the mirror keeps), on one grid whose x axis is ``image``'s."""
    assert np.allclose(image.affine[:3, :3], np.diag(image.spacing))  # (axis-aligned, as image_pair makes it)
    mask = image.mask
    both = np.concatenate([mask[::-1], np.zeros((gap, *mask.shape[1:]), dtype=bool), mask], axis=0)
    origin = image.affine[:3, 3] - np.array([(len(mask) + gap) * image.spacing[0], 0.0, 0.0])
    return from_array(both, spacing=image.spacing, origin=origin)


@pytest.mark.slow
def test_both_lungs_of_one_segmentation_share_their_parameters(patient, tmp_path):
    """One pair of segmentations holding both lungs, read as a pair for each (--lung both):
    each lung registered from the scene's lung of its side and given its model, the breath
    shared, found near the truth. (The command's --lung: the bad inputs below.)"""
    from lungmech.app.patient_images import Reading
    from lungmech.registration.image import write

    folder, images = patient
    for name, image in zip(("exp", "insp"), images["supine"]):
        write(chest(image), tmp_path / f"chest-{name}.npz")
    pairs = Reading(lung="both").pairs(tmp_path / "chest-exp.npz", tmp_path / "chest-insp.npz")
    setting = Setting(estimate=("breath",), training=4, size=6, resamples=0, mesh_check=False)
    report = estimated(prepare(scene_of(folder, 0.04), pairs, setting), setting)
    assert [pair["pair"] for pair in report["fit"]["pairs"]] == ["supine-right", "supine-left"]
    assert all(pair["surface_rms"] < 0.001 for pair in report["fit"]["pairs"])
    assert report["parameters"]["breath"]["value"] == pytest.approx(TRUTH["breath"], rel=0.03)


@pytest.mark.slow
def test_a_model_files_recipe_is_refused_beside_other_physics_or_another_recipe(patient, tmp_path, capsys):
    """A model file's recipe (--model: the cohort's below, which the 2-rank cohort test runs)
    beside a scene of other physics, or beside a recipe given again, is refused in one line,
    nothing written."""
    from lungmech.app.cli import main

    model = _cohort_files(patient, tmp_path, hyper=False)
    capsys.readouterr()
    other = tmp_path / "other.toml"
    other.write_text(SCENE.format(h=0.035).replace("c2 = 400.0", "c2 = 500.0"))
    pair = ["--expiration", str(tmp_path / "first-exp.npz"), "--inspiration", str(tmp_path / "first-insp.npz")]
    for extra, said in (
        (["--scene", str(other)], "was built for other physics than this scene's: material.c2"),
        (["--size", "6"], "leave out --method, --size, --training, --tau"),
        (["--method", "pgd"], "--model gives the patient's model its recipe (method, basis size, training, τ)"),
    ):
        assert main(["personalise", *pair, "--model", str(model), *extra, "-o", str(tmp_path / "no"), "-q"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and said in err, err
    assert not (tmp_path / "no").exists()


@pytest.mark.slow
@pytest.mark.mpi
def test_a_cohort_on_two_ranks_runs_a_patient_a_group(patient, tmp_path):
    """A 2-row cohort CSV (two patients, one imaged lying on its back, one on its front), each
    patient's model made by a model file's recipe (--model: a POD of 4 vectors from 3 breaths,
    ECSW at 1e-3, on the file's own scene), under mpiexec with --group-size 1 (a patient on each
    rank at once): a folder and report per patient, its own position fixed, and a row of
    cohort.csv each with its estimate, near the truth. (One rank runs the same tasks one after
    the other, on the same ensemble layer: tests/test_ensemble.py.)"""
    _cohort(patient, tmp_path, ["--group-size", "1"])


@pytest.mark.slow
@pytest.mark.mpi
def test_a_patient_on_two_ranks_is_estimated_as_on_one(patient):
    """The whole estimate on a distributed mesh (registration, reduced model, fit) agrees with
    the one each rank makes alone on COMM_SELF: the surface nodes, the breath, the noise."""
    folder, images = patient
    setting = Setting(estimate=("breath",), training=4, size=6, resamples=0, mesh_check=False)
    found = {}
    for name, comm in (("alone", MPI.COMM_SELF), ("together", MPI.COMM_WORLD)):
        scene = scene_of(folder, 0.035)
        ready = prepare(scene, [Pair(*images["supine"], "supine")], setting, comm)
        found[name] = (estimated(ready, setting, comm=comm), ready.views[0].nodes.points)
    (alone, nodes), (together, spread) = found["alone"], found["together"]
    # The registration stops at its tolerance and sums in another order on a distributed mesh:
    # its nodes agree to a tenth of a millimetre or so (measured 0.01–0.2 mm; a 4 mm voxel's
    # 1/20 at most), listed in the order of their coordinates, which such differences may swap.
    from scipy.spatial import cKDTree

    moved = cKDTree(nodes).query(spread)[0].max()
    breaths = [found[name][0]["parameters"]["breath"]["value"] for name in ("alone", "together")]
    assert nodes.shape == spread.shape and moved < 5e-4, moved
    assert breaths[1] == pytest.approx(breaths[0], rel=5e-3), breaths
    assert together["noise_sigma"] == pytest.approx(alone["noise_sigma"], rel=5e-2)


COHORT = {"first": "supine", "second": "prone"}  # two patients: the one lung in each position


def _cohort_files(patient, folder, hyper: bool = True) -> Path:
    """The cohort's images and CSV in ``folder`` (every rank's), and its model file (built:
    hyper-reduced, or without ``hyper`` a Galerkin model of 2 vectors from 2 breaths, what a
    refusal needs)."""
    from lungmech.app.cli import main
    from lungmech.registration.image import write

    own, images = patient  # (own: this rank's folder; ``folder`` is every rank's)
    comm = MPI.COMM_WORLD
    lines = ["patient,expiration,inspiration,position"]
    for name, position in COHORT.items():
        for phase, image in zip(("exp", "insp"), images[position]):
            if comm.rank == 0:
                write(image, folder / f"{name}-{phase}.npz")
        lines.append(f"{name},{name}-exp.npz,{name}-insp.npz,{position}")
    if comm.rank == 0:
        (folder / "cohort.csv").write_text("\n".join(lines) + "\n")
    comm.barrier()
    model = folder / "lung.npz"
    scene_of(own, 0.035)
    built = ["rom", "build", str(own / "lung-0.035.toml"), "-o", str(model)]
    recipe = (
        ["--size", "4", "--samples", "3", "--hyper", "ecsw", "--ecsw-tolerance", "1e-3"]
        if hyper
        else ["--size", "2", "--samples", "2"]
    )
    assert main([*built, *recipe, "-q"]) == 0
    return model


def _cohort(patient, folder, extra=()):
    from lungmech.app.cli import main

    model, out = _cohort_files(patient, folder), folder / "cohort-out"
    argv = ["personalise", "--cohort", str(folder / "cohort.csv"), "--model", str(model)]
    argv += ["--estimate", "breath", "--resamples", "0", "--no-mesh-check"]
    assert main([*argv, "-o", str(out), "-q", *extra]) == 0
    rows = list(csv.DictReader((out / "cohort.csv").open()))
    assert [row["patient"] for row in rows] == list(COHORT)
    for row in rows:
        assert row["failed"] == ""
        assert float(row["breath [1]"]) == pytest.approx(TRUTH["breath"], rel=0.03)
        report = json.loads((out / row["patient"] / "report.json").read_text())
        assert report["parameters"]["breath"]["value"] == pytest.approx(float(row["breath [1]"]))
        position = COHORT[row["patient"]]
        assert report["fixed"] == {position: {"posture": -90.0 if position == "supine" else 90.0}}
        assert {f"{kind}-{position}.png" for kind in ("fit", "pressure_volume", "ventilation")} <= set(
            report["pictures"]
        )
        assert report["model"]["recipe_from"] == str(model)
        assert report["model"]["training"] == 3 and report["model"]["tau"] == 1e-3
        assert report["model"]["basis_sizes"][0] <= 4
    return model


@pytest.mark.serial  # writes its scenes into the one folder every rank shares: each rank would truncate the other's
def test_positions_and_estimated_names_are_checked_in_one_line(tmp_path):
    scene = scene_of(tmp_path, 0.035)
    assert position_values(scene, "prone") == {"posture": 90.0}
    upright = tmp_path / "upright.toml"
    upright.write_text(SCENE.format(h=0.035).replace("range = [-90.0, 90.0]", "range = [-90.0, 0.0]"))
    with pytest.raises(ParameterError, match="outside its range"):
        position_values(scenes.load(upright), "prone")  # this scene's posture stops at upright
    with pytest.raises(ParameterError, match="--position must be one of"):
        position_values(scene, "sideways")
    nothing = [Pair(None, None)]  # (refused before the images are looked at)
    with pytest.raises(ParameterError, match="unknown parameter 'stiff'"):
        personalise(scene, nothing, tmp_path / "out", Setting(estimate=("stiff",)))
    with pytest.raises(ParameterError, match="outside the scene's load path"):
        personalise(scene, nothing, tmp_path / "out", Setting(inspiration=3.0))
    with pytest.raises(ParameterError, match="the data noise"):
        personalise(scene, nothing, tmp_path / "out", Setting(noise=-0.1))
    with pytest.raises(ParameterError, match="at least one pair"):
        personalise(scene, [], tmp_path / "out")
    with pytest.raises(ParameterError, match="a PGD is fitted to at least 8 training breaths"):
        personalise(scene, nothing, tmp_path / "out", Setting(method="pgd", training=6))
    with pytest.raises(ParameterError, match="made by 'pod' or 'pgd'"):
        personalise(scene, nothing, tmp_path / "out", Setting(method="svd"))
    assert not (tmp_path / "out").exists()


def _cube(path, low: int, size: int, shift=(0.0, 0.0, 0.0)):
    """A cube of ``size`` voxels (2 mm) at index ``low`` in a 20³ grid, written to ``path``."""
    from lungmech.registration.image import from_array, write

    mask = np.zeros((20, 20, 20), dtype=bool)
    mask[low : low + size, low : low + size, low : low + size] = True
    write(from_array(mask, spacing=(0.002,) * 3, origin=shift), path)
    return str(path)


@pytest.mark.parametrize(
    "case, expected",
    [
        ("apart", "do not overlap in space"),
        ("swapped", "no more than"),
        ("estimate", "unknown parameter 'stiff'"),
        ("tau", "--tau must be a number or 'none'"),
        ("pgd-tau", "a PGD (--method pgd) has none"),
        ("missing", "nowhere.npz"),
        ("position", "invalid choice: 'sideways'"),
        ("unpaired", "once for each pair of images (got 2 and 1)"),
        ("positions", "give --position once for each pair"),
        ("groups", "give --cohort"),
        ("both", "leave out --expiration"),
        ("cohort-column", "has no column 'inspiration'"),
        ("cohort-name", "must be a plain name"),
        ("cohort-image", "inspiration image 'gone.npz' not found"),
        ("cohort-position", "position must be one of"),
        ("model", "model file"),
        ("unoriented", "has no orientation in its header"),
        ("tolerance", "no reduced model of the bundled lung's trade"),
        ("tolerance-size", "--tolerance gives the patient's model its recipe"),
        ("model-tolerance", "give one"),
        ("label", "--label takes integers, comma-separated (got '1,x')"),
        ("lung-side", "holds one body, a lung of no clear side"),
        ("lung-file", "the right and the left lung each need a reference lung of their side"),
    ],
)
def test_bad_inputs_get_one_line_and_leave_nothing(case, expected, tmp_path, capsys):
    """Each refused before any work, in one line naming what is wrong, exit 2, nothing written."""
    from lungmech.app.cli import main

    small, large = _cube(tmp_path / "small.npz", 6, 6), _cube(tmp_path / "large.npz", 5, 9)
    far = _cube(tmp_path / "far.npz", 5, 9, shift=(1.0, 0.0, 0.0))
    pair = {"apart": (small, far), "swapped": (large, small), "missing": (small, str(tmp_path / "nowhere.npz"))}
    if case == "unoriented":  # a NIfTI file without sform or qform: in no patient frame
        import nibabel as nib

        data = np.zeros((20, 20, 20), dtype=np.uint8)
        data[5:14, 5:14, 5:14] = 1
        image = nib.Nifti1Image(data, np.diag([2.0, 2.0, 2.0, 1.0]))
        image.set_sform(None, code=0)
        image.set_qform(None, code=0)
        nib.save(image, tmp_path / "plain.nii.gz")
        pair["unoriented"] = (small, str(tmp_path / "plain.nii.gz"))
    if case == "lung-file":  # two cubes side by side: a right and a left "lung"
        from lungmech.registration.image import from_array, write

        for name, size in (("two-small", 4), ("two-large", 6)):
            mask = np.zeros((40, 20, 20), dtype=bool)
            mask[2 : 2 + size, 5 : 5 + size, 5 : 5 + size] = mask[30 : 30 + size, 5 : 5 + size, 5 : 5 + size] = True
            write(from_array(mask, spacing=(0.002,) * 3), tmp_path / f"{name}.npz")
        pair["lung-file"] = (str(tmp_path / "two-small.npz"), str(tmp_path / "two-large.npz"))
        (tmp_path / "file.toml").write_text(
            SCENE.format(h=0.035)
            .replace('builder = "lung_phantom"\nside = "right"', f'file = "{meshes.reference("lung_phantom_right")}"')
            .replace("mesh_size = 0.035\n", "")
        )
    expiration, inspiration = pair.get(case, (small, large))
    cohorts = {
        "cohort-column": "patient,expiration\nA,small.npz\n",
        "cohort-name": "patient,expiration,inspiration\n../A,small.npz,large.npz\n",
        "cohort-image": "patient,expiration,inspiration\nA,small.npz,gone.npz\n",
        "cohort-position": "patient,expiration,inspiration,position\nA,small.npz,large.npz,sideways\n",
    }
    (tmp_path / "cohort.csv").write_text(cohorts.get(case, "patient,expiration,inspiration\nA,small.npz,large.npz\n"))
    cohort = ["--cohort", str(tmp_path / "cohort.csv")]
    extra = {
        "estimate": ["--estimate", "stiff"],
        "tau": ["--tau", "small"],
        "pgd-tau": ["--method", "pgd", "--tau", "1e-3"],
        "position": ["--position", "sideways"],
        "unpaired": ["--expiration", small],
        "positions": ["--expiration", small, "--inspiration", large, "--position", "supine"],
        "groups": ["--group-size", "1"],
        "both": cohort,
        "model": ["--model", str(tmp_path / "none.npz")],
        "tolerance": ["--tolerance", "1e-9"],
        "tolerance-size": ["--tolerance", "1e-2", "--size", "4"],
        "model-tolerance": ["--tolerance", "1e-2", "--model", str(tmp_path / "none.npz")],
        "label": ["--label", "1,x"],
        "lung-side": ["--lung", "left"],
        "lung-file": ["--lung", "both", "--scene", str(tmp_path / "file.toml")],
    }
    out = tmp_path / "out"
    argv = ["personalise", "-o", str(out), "-q"]
    if case.startswith("cohort"):
        argv += cohort
    else:
        argv += ["--expiration", expiration, "--inspiration", inspiration]
    assert main(argv + extra.get(case, [])) == 2
    said = capsys.readouterr().err
    assert said.count("\n") == 1 and expected in said, said
    assert not out.exists()


def test_an_output_folder_that_holds_the_images_is_refused(tmp_path, capsys):
    """Even a folder lungmech wrote before: replacing it would take the images with it."""
    from lungmech.app.cli import main

    folder = tmp_path / "earlier"
    folder.mkdir()
    (folder / ".lungmech-output").write_text("")  # (any marker: refused on the inputs before it is read)
    small, large = _cube(folder / "small.npz", 6, 6), _cube(folder / "large.npz", 5, 9)
    argv = ["personalise", "--expiration", small, "--inspiration", large, "-o", str(folder), "-q"]
    assert main(argv) == 2
    said = capsys.readouterr().err
    assert said.count("\n") == 1 and "holds the input" in said
    assert sorted(p.name for p in folder.iterdir()) == [".lungmech-output", "large.npz", "small.npz"]
