"""Segmented images: geometry, units and axes of each file format, round trips, error messages."""

import math
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

from lungmech.errors import ImageError
from lungmech.registration.image import Image, from_array, read, write

pytestmark = pytest.mark.serial  # image files written and read back by one process

FLOAT32 = 1e-6  # NIfTI-1 stores its affine in single precision


def rotation(axis, angle: float) -> np.ndarray:
    """Rodrigues' rotation matrix about ``axis``."""
    k = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def oblique(shape=(7, 8, 9)) -> Image:
    """An asymmetric mask on a rotated grid with anisotropic spacing, away from the origin."""
    mask = np.zeros(shape, dtype=bool)
    mask[1:4, 2:7, 3:5] = True
    mask[5, 0, 8] = True  # a lone voxel in a corner catches flipped or transposed axes
    return from_array(mask, (0.7e-3, 1.1e-3, 2.3e-3), (-0.123456789, 0.04, 0.31), rotation((1, 2, 3), 0.4))


def write_nifti(path: Path, data: np.ndarray, affine_mm: np.ndarray, unit: str = "mm") -> Path:
    """A NIfTI file written by nibabel, independently of lungmech."""
    nifti = nib.Nifti1Image(data, affine_mm)
    nifti.header.set_xyzt_units(xyz=unit)
    nib.save(nifti, path)
    return path


def test_geometry_of_a_grid():
    image = from_array(np.ones((2, 3, 4)), spacing=(1e-3, 2e-3, 3e-3), origin=(0.1, 0.2, 0.3))
    assert image.shape == (2, 3, 4)
    assert np.allclose(image.spacing, [1e-3, 2e-3, 3e-3])
    assert image.voxel_volume == pytest.approx(6e-9)
    assert image.volume == pytest.approx(24 * 6e-9)
    assert np.allclose(image.points([1, 1, 1]), [0.101, 0.202, 0.303])
    lower, upper = image.bounds()  # voxel faces, half a voxel outside the centres
    assert np.allclose(lower, [0.0995, 0.199, 0.2985])
    assert np.allclose(upper, [0.1015, 0.205, 0.3105])
    centres = image.centres()
    assert centres.shape == (24, 3)
    assert np.allclose(centres[1], image.points([0, 0, 1]))  # C order: k varies fastest


def test_points_and_index_are_inverses():
    image = oblique()
    index = np.random.default_rng(0).uniform(-1, 10, size=(50, 3))
    assert np.allclose(image.index(image.points(index)), index, rtol=0, atol=1e-9)
    points = image.points(index)
    assert np.allclose(image.points(image.index(points)), points, rtol=0, atol=1e-15)


def test_image_is_read_only():
    image = oblique()
    with pytest.raises(ValueError):
        image.mask[0, 0, 0] = True
    with pytest.raises(ValueError):
        image.affine[0, 0] = 1.0


def test_ball_volume():
    r, centre = 0.02, np.array([0.001, -0.002, 0.0015])
    grid = from_array(np.ones((52, 44, 36)), spacing=(0.8e-3, 1.0e-3, 1.2e-3), origin=(-0.02, -0.023, -0.02))
    inside = np.linalg.norm(grid.centres() - centre, axis=1) < r
    ball = grid.with_mask(inside.reshape(grid.shape))
    assert ball.volume == pytest.approx(4 / 3 * math.pi * r**3, rel=0.02)
    assert np.allclose(ball.points(np.argwhere(ball.mask)).mean(axis=0), centre, atol=1e-4)


@pytest.mark.parametrize("suffix", [".npz", ".mha", ".nrrd"])
def test_exact_round_trip(tmp_path, suffix):
    if suffix != ".npz":
        pytest.importorskip("SimpleITK")
    image = oblique()
    path = tmp_path / "new" / f"lung{suffix}"  # the parent folder does not exist yet
    write(image, path)
    back = read(path)
    assert back.mask.dtype == np.bool_
    assert np.array_equal(back.mask, image.mask)
    assert np.allclose(back.affine, image.affine, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz"])
def test_nifti_round_trip(tmp_path, suffix):
    image = oblique()
    write(image, tmp_path / f"lung{suffix}")
    back = read(tmp_path / f"lung{suffix}")
    assert np.array_equal(back.mask, image.mask)
    assert np.allclose(back.affine, image.affine, rtol=FLOAT32, atol=FLOAT32 * 1e-3)
    header = nib.load(tmp_path / f"lung{suffix}").header
    assert header.get_xyzt_units()[0] == "mm"
    assert (int(header["sform_code"]), int(header["qform_code"])) == (1, 1)
    # An affine that came from NIfTI is already single precision: it survives exactly.
    write(back, tmp_path / f"again{suffix}")
    assert np.allclose(read(tmp_path / f"again{suffix}").affine, back.affine, rtol=1e-12, atol=1e-15)


def test_nifti_affine_is_ras_in_mm(tmp_path):
    affine = np.diag([-1.5, 2.0, 2.5, 1.0])  # i towards the patient's left: LAS
    affine[:3, 3] = [10.0, -20.0, 30.0]
    data = np.zeros((4, 5, 6), dtype=np.uint8)
    data[2, 3, 4] = 1
    image = read(write_nifti(tmp_path / "las.nii.gz", data, affine))
    assert np.allclose(image.points([2, 3, 4]), [0.007, -0.014, 0.040])
    assert np.allclose(image.points(np.argwhere(image.mask)), [[0.007, -0.014, 0.040]])
    assert np.allclose(image.spacing, [1.5e-3, 2e-3, 2.5e-3])
    assert image.voxel_volume == pytest.approx(7.5e-9)


def test_nifti_units(tmp_path):
    data = np.ones((2, 2, 2), dtype=np.uint8)
    affine = np.diag([2.0, 2.0, 2.0, 1.0])
    assert read(write_nifti(tmp_path / "m.nii", data, affine, "meter")).spacing == pytest.approx([2, 2, 2])
    assert read(write_nifti(tmp_path / "um.nii", data, affine, "micron")).spacing == pytest.approx([2e-6] * 3)
    unknown = write_nifti(tmp_path / "unknown.nii", data, affine, "unknown")
    assert read(unknown).spacing == pytest.approx([2e-3] * 3)  # taken as millimetres
    assert read(unknown, unit="m").spacing == pytest.approx([2, 2, 2])


def test_itk_physical_points_are_lps(tmp_path):
    """ITK's own NIfTI reader turns RAS into LPS; going through .mha must give the same points."""
    sitk = pytest.importorskip("SimpleITK")
    write(oblique(), tmp_path / "lung.nii.gz")
    itk = sitk.ReadImage(str(tmp_path / "lung.nii.gz"))
    lps_mm = np.array(itk.TransformIndexToPhysicalPoint((5, 0, 8)))
    assert np.allclose(lps_mm, [-1, -1, 1] * oblique().points([5, 0, 8]) * 1e3, rtol=FLOAT32, atol=FLOAT32)
    sitk.WriteImage(itk, str(tmp_path / "lung.mha"))
    via_itk, via_nibabel = read(tmp_path / "lung.mha"), read(tmp_path / "lung.nii.gz")
    assert np.array_equal(via_itk.mask, via_nibabel.mask)
    assert np.allclose(via_itk.affine, via_nibabel.affine, rtol=FLOAT32, atol=FLOAT32 * 1e-3)


def write_dicom_series(image: Image, folder: Path, patient: str = "Doe^Jane") -> Path:
    """``image`` as a DICOM series, a slice a file (SimpleITK's GDCM writer), its geometry in
    the slices' orientation and positions, a patient's name in every header."""
    sitk = pytest.importorskip("SimpleITK")
    write(image, folder / "source.mha")
    itk = sitk.Cast(sitk.ReadImage(str(folder / "source.mha")), sitk.sitkUInt16)
    (folder / "series").mkdir()
    d = itk.GetDirection()
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k in range(itk.GetDepth()):
        piece = itk[:, :, k]
        tags = {
            "0008|0060": "CT",
            "0010|0010": patient,
            "0020|000d": "1.2.826.0.1.3680043.2.1125.1",
            "0020|000e": "1.2.826.0.1.3680043.2.1125.1.2",
            "0020|0037": "\\".join(f"{v:.12f}" for v in (d[0], d[3], d[6], d[1], d[4], d[7])),
            "0020|0032": "\\".join(f"{v:.12f}" for v in itk.TransformIndexToPhysicalPoint((0, 0, k))),
            "0020|0013": str(k + 1),
            "0008|0018": f"1.2.826.0.1.3680043.2.1125.1.2.{k + 1}",
        }
        for tag, value in tags.items():
            piece.SetMetaData(tag, value)
        writer.SetFileName(str(folder / "series" / f"slice{k:03d}.dcm"))
        writer.Execute(piece)
    (folder / "source.mha").unlink()
    return folder / "series"


def test_a_dicom_series_is_read_from_its_folder(tmp_path):
    """A segmentation as a folder of DICOM slices (a rotated grid, anisotropic voxels): the same
    voxels at the same points as the image it was written from; the patient's name is not read."""
    image = oblique()
    read_back = read(write_dicom_series(image, tmp_path))
    assert read_back.mask.sum() == image.mask.sum()

    def inside(im: Image) -> np.ndarray:  # the voxels' centres inside, in one order (µm)
        points = np.round(im.points(np.argwhere(im.mask)) * 1e6).astype(np.int64)
        return points[np.lexsort(points.T)]

    assert np.array_equal(inside(read_back), inside(image))
    assert np.allclose(np.sort(read_back.spacing), np.sort(image.spacing), rtol=1e-6)
    assert "Doe" not in repr(vars(read_back))


def test_a_dicom_folder_must_hold_one_series(tmp_path):
    pytest.importorskip("SimpleITK")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ImageError, match="holds no DICOM series"):
        read(tmp_path / "empty")
    first = write_dicom_series(oblique(), tmp_path)
    other = tmp_path / "other"
    other.mkdir()
    second = write_dicom_series(oblique(), other)
    for path in second.iterdir():  # the same study, another series
        text = path.read_bytes().replace(b"1.2.826.0.1.3680043.2.1125.1.2", b"1.2.826.0.1.3680043.2.1125.1.3")
        (first / f"b-{path.name}").write_bytes(text)
    with pytest.raises(ImageError, match="holds 2 DICOM series"):
        read(first)


def test_label_selection(tmp_path):
    data = np.zeros((5, 5, 5), dtype=np.int16)
    data[:2] = 1
    data[3:] = 7
    path = write_nifti(tmp_path / "lobes.nii.gz", data, np.eye(4))
    assert np.count_nonzero(read(path, label=7).mask) == 50
    assert np.array_equal(read(path, label=1).mask, data == 1)
    with pytest.raises(ImageError, match=r"is not binary \(its labels are 0, 1, 7\); choose one with --label"):
        read(path)
    with pytest.raises(ImageError, match="no voxel labelled 3; its labels are 0, 1, 7"):
        read(path, label=3)


def test_many_labels_are_abbreviated(tmp_path):
    data = np.arange(64, dtype=np.uint8).reshape(4, 4, 4)
    with pytest.raises(ImageError, match=r"0, 1, 2, 3, 4, 5, 6, 7, 8, 9, \.\.\. \(64 values\)"):
        read(write_nifti(tmp_path / "many.nii.gz", data, np.eye(4)))


def test_trailing_singleton_axis_is_dropped(tmp_path):
    path = write_nifti(tmp_path / "t.nii.gz", np.ones((3, 4, 5, 1), dtype=np.uint8), np.eye(4))
    assert read(path).shape == (3, 4, 5)


@pytest.mark.parametrize(
    ("shape", "message"),
    [
        ((10, 10, 10, 3), r"is 4-D \(shape \(10, 10, 10, 3\)\); a segmentation must be 3-D"),
        ((10, 10), r"is 2-D \(shape \(10, 10\)\); a segmentation must be 3-D"),
    ],
)
def test_not_3d(tmp_path, shape, message):
    path = write_nifti(tmp_path / "bad.nii.gz", np.ones(shape, dtype=np.uint8), np.eye(4))
    with pytest.raises(ImageError, match=f"image '.*bad.nii.gz' {message}"):
        read(path)
    with pytest.raises(ImageError, match=message):
        from_array(np.ones(shape))


def test_empty(tmp_path):
    path = write_nifti(tmp_path / "empty.nii.gz", np.zeros((3, 3, 3), dtype=np.uint8), np.eye(4))
    with pytest.raises(ImageError, match=r"image '.*empty.nii.gz' is empty"):
        read(path)
    with pytest.raises(ImageError, match="is empty"):
        from_array(np.zeros((3, 3, 3), dtype=bool))
    with pytest.raises(ImageError, match="is empty"):
        oblique().with_mask(np.zeros((7, 8, 9)))


def test_missing_file_and_bad_suffix(tmp_path):
    with pytest.raises(ImageError, match=r"image file '.*nowhere.nii.gz' not found"):
        read(tmp_path / "nowhere.nii.gz")
    (tmp_path / "lung.png").write_bytes(b"\x89PNG")
    with pytest.raises(ImageError, match=r"image '.*lung.png' has an unknown suffix; use one of .nii, "):
        read(tmp_path / "lung.png")
    with pytest.raises(ImageError, match="unknown suffix"):
        write(oblique(), tmp_path / "lung.vtk")


@pytest.mark.parametrize("name", ["bad.nii.gz", "bad.nii", "bad.npz", "bad.mha", "bad.nrrd"])
def test_corrupt_file(tmp_path, name):
    if name.endswith((".mha", ".nrrd")):
        pytest.importorskip("SimpleITK")
    path = tmp_path / name
    path.write_bytes(b"this is not an image\n" * 20)
    with pytest.raises(ImageError, match=f"cannot read image '.*{name}': ") as error:
        read(path)
    assert "\n" not in str(error.value)


def test_truncated_nifti(tmp_path):
    write(oblique((40, 40, 40)), tmp_path / "whole.nii.gz")
    (tmp_path / "cut.nii.gz").write_bytes((tmp_path / "whole.nii.gz").read_bytes()[:200])
    with pytest.raises(ImageError, match="cannot read image '.*cut.nii.gz'"):
        read(tmp_path / "cut.nii.gz")


def test_npz_without_the_arrays(tmp_path):
    np.savez(tmp_path / "other.npz", data=np.ones((2, 2, 2)))
    with pytest.raises(ImageError, match="expected arrays 'mask' and 'affine'"):
        read(tmp_path / "other.npz")


def test_missing_simpleitk(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "SimpleITK", None)  # makes the import fail
    (tmp_path / "lung.mha").write_bytes(b"")
    with pytest.raises(ImageError, match="pip install SimpleITK"):
        read(tmp_path / "lung.mha")
    with pytest.raises(ImageError, match="pip install SimpleITK"):
        write(oblique(), tmp_path / "out" / "lung.nrrd")
    assert not (tmp_path / "out").exists()


def test_sheared_affine_cannot_go_to_itk(tmp_path):
    pytest.importorskip("SimpleITK")
    affine = np.diag([1e-3, 1e-3, 1e-3, 1.0])
    affine[0, 1] = 0.5e-3
    with pytest.raises(ImageError, match="sheared"):
        write(Image(np.ones((2, 2, 2), dtype=bool), affine), tmp_path / "lung.mha")


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"spacing": (1e-3, 0.0, 1e-3)}, "spacing must be three positive lengths"),
        ({"origin": (0.0, 0.0)}, "origin must be a finite 3-D point"),
        ({"direction": np.diag([1.0, 2.0, 1.0])}, "direction must be an orthogonal"),
    ],
)
def test_bad_grid(arguments, message):
    with pytest.raises(ImageError, match=message):
        from_array(np.ones((2, 2, 2)), **arguments)


def test_bad_image():
    with pytest.raises(ImageError, match="must be a 3-D boolean array, got 3-D uint8"):
        Image(np.ones((2, 2, 2), dtype=np.uint8), np.eye(4))
    with pytest.raises(ImageError, match="singular"):
        Image(np.ones((2, 2, 2), dtype=bool), np.diag([1.0, 1.0, 0.0, 1.0]))
    with pytest.raises(ImageError, match="last row"):
        Image(np.ones((2, 2, 2), dtype=bool), np.ones((4, 4)))
    with pytest.raises(ImageError, match="not binary"):
        from_array(np.full((2, 2, 2), 0.5))
    with pytest.raises(ImageError, match="has shape"):
        oblique().with_mask(np.ones((2, 2, 2)))
    with pytest.raises(ImageError, match="unknown unit 'cm'"):
        read("lung.nii.gz", unit="cm")
