"""One lung out of a segmentation holding both (lungmech.registration.lungs), and a lung as the
union of its labels: on both lungs of tests/lungs.py, written outside lungmech, on one grid."""

from __future__ import annotations

import nibabel
import numpy as np
import pytest
from lungs import chest

from lungmech.app.patient_images import Reading
from lungmech.errors import ImageError, ParameterError
from lungmech.registration import image
from lungmech.registration.lungs import lung_of

SPACING = 0.004


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    """The chest's labels and its files: a binary mask of both lungs, the labels (1 right, 2
    left), the right lung in two "lobes" (3 below its middle, 4 above), and the binary mask
    with no orientation in its header."""
    from mpi4py import MPI

    folder = tmp_path_factory.mktemp(f"chest-rank{MPI.COMM_WORLD.rank}")
    labels, affine = chest(SPACING)
    millimetres = np.diag([1e3, 1e3, 1e3, 1.0]) @ affine
    lobes = labels.copy()
    right = labels == 1
    middle = np.argwhere(right)[:, 2].mean()
    above = np.zeros_like(right)
    above[:, :, int(middle) :] = True
    lobes[right & ~above], lobes[right & above] = 3, 4

    def write(name: str, data: np.ndarray, oriented: bool = True):
        nifti = nibabel.Nifti1Image(data.astype(np.uint8), millimetres)
        if not oriented:
            nifti.set_sform(None, code=0)
            nifti.set_qform(None, code=0)
        nifti.header.set_xyzt_units(xyz="mm")
        path = folder / name
        nibabel.save(nifti, path)
        return path

    return labels, {
        "binary": write("both.nii.gz", labels > 0),
        "labels": write("labels.nii.gz", labels),
        "lobes": write("lobes.nii.gz", lobes),
        "unoriented": write("unoriented.nii.gz", labels > 0, oriented=False),
    }


@pytest.mark.parametrize("side, label", [("right", 1), ("left", 2)])
def test_each_lung_of_a_mask_of_both_is_its_own_body(both, side, label):
    labels, files = both
    lung = lung_of(image.read(files["binary"]), side)
    assert np.array_equal(lung.image.mask, labels == label)
    assert lung.side == side and lung.islands == 0.0
    assert lung.image.source == files["binary"]  # (its messages name the file)


def test_a_lung_is_the_union_of_its_labels(both):
    labels, files = both
    assert np.array_equal(image.read(files["lobes"], label=(3, 4)).mask, labels == 1)
    assert np.array_equal(image.read(files["lobes"], label=[3, 4, 2]).mask, labels > 0)
    with pytest.raises(ImageError, match="no voxel labelled 5, 6; its labels are 0, 2, 3, 4"):
        image.read(files["lobes"], label=(3, 5, 6))


def test_islands_are_left_out_and_counted(both):
    labels, files = both
    speckled = labels > 0
    speckled[0, 0, 0] = speckled[-1, -1, -1] = True  # two stray voxels, far from either lung
    lung = lung_of(image.read(files["binary"]).with_mask(speckled), "left")
    assert np.array_equal(lung.image.mask, labels == 2)
    assert lung.islands == pytest.approx(2 / speckled.sum())


def test_a_mask_of_one_lung_is_that_lung(both):
    labels, files = both
    right = image.read(files["labels"], label=1)
    assert np.array_equal(lung_of(right, "right").image.mask, labels == 1)
    with pytest.raises(ImageError, match="holds one body, a right lung, where the left lung was asked for"):
        lung_of(right, "left")


def test_sides_need_an_orientation(both):
    _, files = both
    with pytest.raises(ImageError, match="'unoriented.nii.gz' has no orientation in its header: which of its two"):
        lung_of(image.read(files["unoriented"]), "right")


def bridged(labels: np.ndarray, width: int) -> np.ndarray:
    """Both lungs joined by a bar ``width`` voxels square across the mediastinum, at the right
    lung's mid height and depth."""
    joined = labels > 0
    j, k = np.argwhere(labels == 1)[:, 1:].mean(axis=0).astype(int)
    start = np.argwhere(labels[:, j, k] == 2)[:, 0].max()
    stop = np.argwhere(labels[:, j, k] == 1)[:, 0].min()
    joined[start : stop + 1, j : j + width, k : k + width] = True
    return joined


def test_lungs_that_touch_at_a_thin_junction_are_parted(both):
    labels, files = both
    joined = bridged(labels, 2)
    lung = lung_of(image.read(files["binary"]).with_mask(joined), "right")
    assert not (lung.image.mask & (labels == 2)).any() and (lung.image.mask >= (labels == 1)).all()
    assert lung.islands == 0.0
    bar = joined & (labels == 0)
    assert 0 < (lung.image.mask & bar).sum() < bar.sum()  # the bar's halves go to the nearer lung


def test_lungs_fused_wide_need_labels(both):
    labels, files = both
    with pytest.raises(ImageError, match="holds one body, .* where the right lung was asked for: if the lungs touch"):
        lung_of(image.read(files["binary"]).with_mask(bridged(labels, 12)), "right")


def test_a_reading_makes_a_pair_for_each_lung(both):
    labels, files = both
    pairs = Reading(lung="both").pairs(files["binary"], files["binary"], "prone")
    assert [(p.side, p.position) for p in pairs] == [("right", "prone"), ("left", "prone")]
    assert np.array_equal(pairs[1].inspiration.mask, labels == 2)
    assert [p.name(pairs) for p in pairs] == ["prone-right", "prone-left"]
    assert len(Reading(label=(1,)).pairs(files["labels"], files["labels"])) == 1
    with pytest.raises(ParameterError, match="--lung must be one of right, left, both"):
        Reading(lung="middle")
