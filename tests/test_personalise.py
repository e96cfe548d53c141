"""lungmech personalise on a synthetic patient: the whole pipeline from two segmentations.

The patient is made by lungmech's full model on a finer mesh (the bundled lung's physics, its
weight balanced by the pleural pressure, lying on its back) at known parameters, voxelised at
4 mm at end-expiration and end-inspiration; the estimate registers the scene's coarse lung
(< 2k cells) onto the first image, builds the patient's hyper-reduced model, fits the second.
Without noise the estimate is as good as the full model on the estimate's mesh fitted to the
same images (the discretisation's gap) to 1 % of the range.
"""

import json

from mpi4py import MPI

import numpy as np
import pytest

from lungmech.app import scene as scenes
from lungmech.app.personalise import Setting, personalise, position_values
from lungmech.app.run import full_order_model
from lungmech.errors import ParameterError
from lungmech.twin.synthetic import image_pair

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
range = [-90.0, 0.0]
"""
TRUTH = {"stiffness": 200.0, "breath": 1.15, "posture": -90.0}  # lying on the back


def scene_of(folder, size: float):
    path = folder / f"lung-{size}.toml"
    path.write_text(SCENE.format(h=size))
    return scenes.load(path)


@pytest.fixture(scope="module")
def patient(tmp_path_factory):
    """The synthetic patient's pair of segmentations (its mesh: 0.02 m cells)."""
    folder = tmp_path_factory.mktemp(f"patient-rank{MPI.COMM_WORLD.rank}")
    truth = full_order_model(scene_of(folder, 0.02), start="inverse_motion")
    return folder, image_pair(truth, TRUTH, 1.0, 0.004)


@pytest.mark.slow
def test_a_synthetic_patients_breath_is_found_as_well_as_the_full_model_finds_it(patient):
    """The breath's depth estimated (the stiffness known), supine: the report holds it with its
    interval, unit and the fit; the reduced estimate is within 1 % of the range of the full
    model's own fit on the same mesh, whose error is the gap; the interval, widened by the
    reduction's and the mesh's errors as a bias, holds the truth."""
    folder, (expiration, inspiration) = patient
    out = folder / "out"
    setting = Setting(estimate=("breath",), training=6, size=8, resamples=4, full_fit=True)
    report = personalise(scene_of(folder, 0.035), expiration, inspiration, out, setting)
    assert json.loads((out / "report.json").read_text())["parameters"]["breath"]["value"] == pytest.approx(
        report["parameters"]["breath"]["value"]
    )
    found = report["parameters"]["breath"]["value"]
    full = report["full_order_estimate"]["breath"]
    assert abs(found - TRUTH["breath"]) <= abs(full - TRUTH["breath"]) + 0.01 * 0.8
    assert abs(full - TRUTH["breath"]) < 0.03 * TRUTH["breath"]  # the gap (coarse mesh, 4 mm voxels, registration)
    low, high = report["parameters"]["breath"]["interval"]
    assert low < TRUTH["breath"] < high  # the mesh's own error (against the lung refined once) in its bias
    assert [len(point["steps"]) for point in report["model_check"]] == [2, 2, 2]  # reduction, then the mesh
    assert report["fixed"] == {"posture": -90.0}
    assert report["fit"]["surface_rms"] < 0.001  # m: a quarter of a voxel
    assert report["registration"]["dice"] > 0.97
    assert set(report["seconds"]) >= {"registration", "offline", "estimate", "confirmation"}


def test_positions_and_estimated_names_are_checked_in_one_line(tmp_path):
    scene = scene_of(tmp_path, 0.035)
    assert position_values(scene, "supine") == {"posture": -90.0}
    with pytest.raises(ParameterError, match="outside its range"):
        position_values(scene, "prone")  # the scene's posture stops at upright
    with pytest.raises(ParameterError, match="--position must be one of"):
        position_values(scene, "sideways")
    with pytest.raises(ParameterError, match="unknown parameter 'stiff'"):
        personalise(scene, None, None, tmp_path / "out", Setting(estimate=("stiff",)))
    with pytest.raises(ParameterError, match="outside the scene's load path"):
        personalise(scene, None, None, tmp_path / "out", Setting(inspiration=3.0))
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
        ("missing", "nowhere.npz"),
        ("position", "invalid choice: 'sideways'"),
    ],
)
def test_bad_inputs_get_one_line_and_leave_nothing(case, expected, tmp_path, capsys):
    """Each refused before any work, in one line naming what is wrong, exit 2, nothing written."""
    from lungmech.app.cli import main

    small, large = _cube(tmp_path / "small.npz", 6, 6), _cube(tmp_path / "large.npz", 5, 9)
    far = _cube(tmp_path / "far.npz", 5, 9, shift=(1.0, 0.0, 0.0))
    pair = {"apart": (small, far), "swapped": (large, small), "missing": (small, str(tmp_path / "nowhere.npz"))}
    expiration, inspiration = pair.get(case, (small, large))
    extra = {"estimate": ["--estimate", "stiff"], "tau": ["--tau", "small"], "position": ["--position", "sideways"]}
    out = tmp_path / "out"
    argv = ["personalise", "--expiration", expiration, "--inspiration", inspiration, "-o", str(out), "-q"]
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
