"""The registration commands: phantom → register → shape-modes → shape, and their errors."""

import json

from mpi4py import MPI

import numpy as np
import pytest

from lungmech import mesh as geometry
from lungmech import meshes
from lungmech.app.cli import main
from lungmech.mesh.lung_shape import LungShape
from lungmech.registration import image

REFERENCE = str(meshes.reference("lung_phantom_right"))


@pytest.mark.slow
def test_phantom_register_and_outputs(tmp_path, capsys):
    target = tmp_path / "patient.nii.gz"
    assert main(["phantom", "-o", str(target), "--height", "0.22", "--dome", "0.22", "--spacing", "2.5"]) == 0
    segmentation = image.read(target)
    assert segmentation.volume == pytest.approx(LungShape(height=0.22, dome=0.22).volume(), rel=0.01)
    out = tmp_path / "fit"
    assert main(["register", str(target), "--reference", REFERENCE, "-o", str(out), "-q"]) == 0
    assert "Dice" in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert report["dice"] >= 0.97 and report["mean_surface_distance_voxels"] <= 1.0 and report["min_det_F"] > 0.2
    assert (out / "registration.png").stat().st_size > 10_000
    mapped = geometry.from_file(out / "registered.vtu", MPI.COMM_WORLD)
    assert set(mapped.boundaries) >= {"pleura", "diaphragm", "mediastinum", "hilum"}
    assert mapped.volume() == pytest.approx(report["volume_mesh"], rel=1e-9)
    with np.load(out / "mapping.npz") as mapping:
        assert mapping["reference"].shape == mapping["displacement"].shape


@pytest.mark.slow
def test_shape_modes_of_a_synthetic_cohort_and_a_new_shape(tmp_path):
    out = tmp_path / "modes"
    args = ["shape-modes", "--synthetic", "4", "--latent", "1", "--spacing", "2.5", "--reference", REFERENCE]
    assert main([*args, "-o", str(out), "-q"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["images"] == 4 and len(report["leave_one_out_rms"]) == 3
    assert report["compactness"][-1] == pytest.approx(1.0)
    assert (out / "singular_values.png").is_file()
    new = tmp_path / "new.vtu"
    shape = ["shape", str(out / "shape_modes.npz"), "--reference", REFERENCE, "-o", str(new), "-c"]
    assert main([*shape, "1.5"]) == 0
    larger = geometry.from_file(new, MPI.COMM_WORLD).volume()
    assert main([*shape, "-1.5"]) == 0  # its own earlier output is replaced
    assert 0 < geometry.from_file(new, MPI.COMM_WORLD).volume() != larger


@pytest.mark.parametrize(
    "argv, message",
    [
        (["register", "missing.nii.gz", "--reference", REFERENCE], "not found"),
        (["register", "{npz}", "--reference", "missing.msh"], "not found"),
        (["register", "{npz}", "--reference", REFERENCE, "--stages", "2,x"], "--stages"),
        (["register", "{npz}", "--reference", REFERENCE, "--min-jacobian", "2"], "min_jacobian"),
        (["shape-modes", "{npz}", "--synthetic", "3", "--reference", REFERENCE], "one of the two"),
        (["shape", "missing.npz", "--reference", REFERENCE, "-c", "1", "-o", "x.xdmf"], "not found"),
        (["phantom", "-o", "{tmp}/p.nii.gz", "--dome", "0.9"], "dome"),
    ],
)
def test_bad_input_gives_one_clear_error(argv, message, tmp_path, capsys):
    npz = tmp_path / "labels.npz"
    labels = np.zeros((10, 10, 10), dtype=np.uint8)
    labels[3:7, 3:7, 3:7] = 1
    image.write(image.from_array(labels, spacing=(0.002,) * 3), npz)
    argv = [a.format(npz=npz, tmp=tmp_path) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("lungmech: error:") and message in err and "Traceback" not in err


@pytest.mark.mpi
def test_shape_modes_and_shape_commands_under_mpi(tmp_path):
    """Every rank takes part (collective volumes, one writer per file) and nothing hangs."""
    comm = MPI.COMM_WORLD
    folder = comm.bcast(tmp_path, root=0)  # one folder for all ranks
    reference = folder / "ball.vtu"
    geometry.write(geometry.ellipsoid(comm, (0.03, 0.03, 0.03), mesh_size=0.01), reference)
    if comm.rank == 0:
        for j, axes in enumerate([(0.03, 0.035, 0.04), (0.032, 0.03, 0.036), (0.035, 0.033, 0.03)]):
            h = 0.0025
            n = 40
            x = (np.indices((n, n, n)).reshape(3, -1).T - n / 2) * h
            mask = (np.sum((x / axes) ** 2, axis=1) < 1).reshape(n, n, n)
            image.write(
                image.from_array(mask, spacing=(h,) * 3, origin=(-n / 2 * h,) * 3), folder / "images" / f"e{j}.npz"
            )
    comm.Barrier()
    out = folder / "modes"
    assert main(["shape-modes", str(folder / "images"), "--reference", str(reference), "-o", str(out), "-q"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["images"] == 3 and report["worst"]["dice"] >= 0.97
    assert (out / "singular_values.png").stat().st_size > 10_000
    new = folder / "new.vtu"
    assert (
        main(["shape", str(out / "shape_modes.npz"), "--reference", str(reference), "-c", "1,-1", "-o", str(new)]) == 0
    )
    assert geometry.from_file(new, comm).volume() > 0


@pytest.mark.slow
def test_an_unconverged_registration_is_kept_only_when_asked(tmp_path, capsys):
    target = tmp_path / "patient.nii.gz"
    assert main(["phantom", "-o", str(target), "--spacing", "4"]) == 0
    args = ["register", str(target), "--reference", REFERENCE, "--max-iterations", "1", "--stages", "1", "-q"]
    capsys.readouterr()
    assert main([*args, "-o", str(tmp_path / "fit")]) == 2
    assert "did not converge" in capsys.readouterr().err and not (tmp_path / "fit").exists()
    assert main([*args, "-o", str(tmp_path / "fit"), "--accept-unconverged"]) == 0
    assert "converged: no (kept: --accept-unconverged)" in capsys.readouterr().out
    assert json.loads((tmp_path / "fit" / "report.json").read_text())["converged"] is False
