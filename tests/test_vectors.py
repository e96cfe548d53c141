"""Displacement fields as vector images: ITK's LPS millimetres read as lungmech's RAS metres,
trilinear values between voxels, and fields that do not cover the lung refused."""

import numpy as np
import pytest

from lungmech.errors import ImageError
from lungmech.registration.vectors import VectorImage, read_vectors, write_vectors

pytestmark = pytest.mark.serial  # files written and read back by one process


def affine_field(shape=(6, 7, 5)) -> tuple[VectorImage, np.ndarray, np.ndarray]:
    """u(x) = A x + b on a rotated grid of 2 × 3 × 4 mm voxels: trilinear sampling is exact."""
    angle = 0.3
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    affine = np.eye(4)
    affine[:3, :3] = rotation * [0.002, 0.003, 0.004]
    affine[:3, 3] = [0.10, -0.05, 0.02]
    A = np.array([[0.01, 0.02, -0.03], [0.0, 0.05, 0.01], [0.02, 0.0, 0.04]])
    b = np.array([0.001, -0.002, 0.003])
    index = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).reshape(-1, 3)
    points = (affine[:3, :3] @ index.T).T + affine[:3, 3]
    return VectorImage((points @ A.T + b).reshape(*shape, 3), affine), A, b


def test_an_affine_field_is_sampled_exactly_between_voxels():
    field, A, b = affine_field()
    rng = np.random.default_rng(3)
    index = rng.uniform(0, 1, size=(20, 3)) * (np.array(field.values.shape[:3]) - 1)
    points = (field.affine[:3, :3] @ index.T).T + field.affine[:3, 3]
    assert np.allclose(field.at(points), points @ A.T + b, rtol=0, atol=1e-15)
    with pytest.raises(ImageError, match="does not cover the lung: 1 points lie outside"):
        field.at(np.vstack([points[:2], field.affine[:3, 3] - 0.01]))


@pytest.mark.parametrize("suffix", [".npz", ".mha", ".nii.gz"])
def test_a_field_comes_back_as_written(tmp_path, suffix):
    if suffix != ".npz":
        pytest.importorskip("SimpleITK")
    field, _, _ = affine_field()
    write_vectors(field, tmp_path / f"u{suffix}")
    back = read_vectors(tmp_path / f"u{suffix}")
    exact = 1e-7 if suffix == ".nii.gz" else 1e-12  # NIfTI-1 keeps its affine in single precision
    assert np.allclose(back.values, field.values, rtol=0, atol=1e-12)
    assert np.allclose(back.affine, field.affine, rtol=0, atol=exact)


def test_itk_vectors_are_lps_millimetres():
    """A field written by SimpleITK itself, (1, 2, 3) mm in LPS at every voxel, is (−1, −2, 3)
    mm in lungmech's axes, and its origin flips alike."""
    sitk = pytest.importorskip("SimpleITK")
    import tempfile
    from pathlib import Path

    data = np.broadcast_to(np.array([1.0, 2.0, 3.0]), (4, 5, 6, 3)).copy()  # [k, j, i, c]
    itk = sitk.GetImageFromArray(data, isVector=True)
    itk.SetOrigin((10.0, 20.0, 30.0))
    itk.SetSpacing((2.0, 2.0, 2.0))
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "u.mha"
        sitk.WriteImage(itk, str(path))
        read = read_vectors(path)
    assert read.values.shape == (6, 5, 4, 3)
    assert np.allclose(read.values, [-1e-3, -2e-3, 3e-3])
    assert np.allclose(read.affine[:3, 3], [-0.010, -0.020, 0.030])


def test_bad_fields_are_refused_in_one_line(tmp_path):
    sitk = pytest.importorskip("SimpleITK")
    with pytest.raises(ImageError, match="not found"):
        read_vectors(tmp_path / "none.mha")
    sitk.WriteImage(sitk.Image(4, 4, 4, sitk.sitkFloat32), str(tmp_path / "scalar.mha"))
    with pytest.raises(ImageError, match="holds 1 values per voxel in 3-D; a displacement field holds 3"):
        read_vectors(tmp_path / "scalar.mha")
    np.savez(tmp_path / "nan.npz", field=np.full((2, 2, 2, 3), np.nan), affine=np.eye(4))
    with pytest.raises(ImageError, match="not finite"):
        read_vectors(tmp_path / "nan.npz")
