"""Which lung an image holds, the reference chosen for it, and registrations that say whether
they converged: on a right and a left lung of realistic shape written outside lungmech's own
phantom (tests/lungs.py), and on the bundled phantoms."""

from __future__ import annotations

import json

from mpi4py import MPI

import nibabel
import numpy as np
import pytest
from lungs import LEFT, RIGHT

from lungmech import meshes
from lungmech.app.cli import main
from lungmech.app.registration import choose_reference
from lungmech.errors import RegistrationError
from lungmech.mesh import from_file
from lungmech.mesh.lung_shape import LungShape
from lungmech.registration import image, phantom, side
from lungmech.registration.image import Image

LUNGS = {"right": RIGHT, "left": LEFT}


@pytest.fixture(scope="module")
def lungs() -> dict[str, Image]:
    return {name: lung.image(0.002) for name, lung in LUNGS.items()}


@pytest.mark.parametrize("name", ["right", "left"])
def test_the_side_of_a_lung_is_read_from_its_shape(name, lungs):
    found = side.of_image(lungs[name])
    assert found.side == name, found
    mirrored = phantom.voxelise(LungShape(side=name), 0.004)  # lungmech's own phantom, too
    assert side.of_image(mirrored).side == name
    assert side.of_mesh(from_file(meshes.reference(f"lung_phantom_{name}"), MPI.COMM_WORLD).mesh).side == name


def test_a_header_that_mirrors_the_patient_frame_mirrors_the_side(lungs):
    """The same voxels, with x pointing the other way in the header: the other lung."""
    right = lungs["right"]
    flip = np.diag([-1.0, 1.0, 1.0, 1.0])
    assert side.of_image(Image(right.mask, flip @ right.affine)).side == "left"


def test_a_header_without_orientation_needs_side(tmp_path, lungs, capsys):
    """sform and qform codes 0: nibabel's affine is a bare scaling, in no patient frame."""
    path = tmp_path / "bare.nii.gz"
    scan = nibabel.Nifti1Image(lungs["left"].mask.astype(np.uint8), np.diag([2.0, 2.0, 2.0, 1.0]))
    scan.set_sform(None, code=0)
    scan.set_qform(None, code=0)
    nibabel.save(scan, path)
    bare = image.read(path)
    assert not bare.oriented and side.of_image(bare).side is None
    assert main(["register", str(path), "-o", str(tmp_path / "out"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "cannot tell which lung it holds: the image's header has no orientation" in err and "--side" in err
    chosen, decided = choose_reference(bare, side="left")
    assert chosen == meshes.reference("lung_phantom_left") and decided["lung"] == "left"


def test_the_reference_is_the_lungs_own_side(lungs):
    chosen, decided = choose_reference(lungs["left"])
    assert chosen == meshes.reference("lung_phantom_left") and decided["image"]["side"] == "left"
    with pytest.raises(RegistrationError, match="is a right lung and the image holds a left one"):
        choose_reference(lungs["left"], "lung_phantom_right")
    with pytest.raises(RegistrationError, match="holds a left lung by its shape .*, not the right one --side names"):
        choose_reference(lungs["left"], side="right")
    chosen, decided = choose_reference(lungs["left"], "lung_phantom_right", accept_other_side=True)
    assert chosen == meshes.reference("lung_phantom_right") and decided["reference_side"] == "right"


@pytest.mark.slow
def test_a_descent_held_by_the_det_f_limit_has_not_converged():
    """A limit the descent must press against (det F ≥ 0.9 for a lung 20 % smaller than the
    reference) stops it on the constraint: reported as not converged, with the reason."""
    from lungmech.registration.sobolev import Options, register

    geometry = from_file(meshes.reference("lung_phantom_right"), MPI.COMM_SELF)
    target = phantom.voxelise(LungShape(height=0.2, width=0.09, depth=0.13), 0.004)
    result = register(geometry.mesh, target, Options(min_jacobian=0.9, similarity=False, stages=(1.0,)))
    assert not result.converged
    assert result.stages[-1]["reason"].startswith("held by the det F limit"), result.stages


@pytest.mark.slow
@pytest.mark.parametrize("spacing", [2, pytest.param(1, marks=pytest.mark.long)])  # 1 mm: 35 and 105 s
@pytest.mark.parametrize("name", ["right", "left"])
def test_a_realistic_lung_registers_closely_or_says_it_did_not_converge(name, spacing, tmp_path, capsys):
    """Default options, the reference chosen from the image: Dice ≥ 0.98 and HD95 ≤ 2 voxels, or
    exit 2 saying the descent did not converge (and why): never a poor fit called converged."""
    path = tmp_path / f"{name}.nii.gz"
    image.write(LUNGS[name].image(1e-3 * spacing), path)
    code = main(["register", str(path), "-o", str(tmp_path / "out"), "-q"])
    out, err = capsys.readouterr()
    if code == 0:
        report = json.loads((tmp_path / "out" / "report.json").read_text())
        assert report["side"]["lung"] == name and report["converged"]
        assert report["dice"] >= 0.98 and report["hd95"] <= 2 * 1e-3 * spacing, report
    else:
        assert code == 2 and "the registration did not converge (stages ended by: " in err, err
        assert not (tmp_path / "out").exists()


def test_a_cohort_of_the_other_side_is_refused(tmp_path, lungs, capsys):
    """shape-modes: images of left lungs onto the right phantom would map faces onto the wrong
    ones; refused before any registration (the default reference is the images' side's)."""
    paths = []
    for j, spacing in enumerate((0.002, 0.0025)):
        paths.append(tmp_path / f"left{j}.nii.gz")
        image.write(LEFT.image(spacing), paths[-1])
    argv = ["shape-modes", *map(str, paths), "-o", str(tmp_path / "modes"), "-q"]
    assert main([*argv, "--reference", "lung_phantom_right"]) == 2
    err = capsys.readouterr().err
    assert (
        "left0: it holds a left lung" in err
        and "holds a left lung and the reference" in err
        and "is a right one" in err
    ), err
    assert not (tmp_path / "modes").exists()
    chosen, _ = choose_reference(image.read(paths[0]))
    assert chosen == meshes.reference("lung_phantom_left")
