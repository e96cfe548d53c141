"""Segmented 3-D images with their physical geometry.

An :class:`Image` is a boolean mask (a segmentation, e.g. of a lung in a CT scan) together with
the affine map that places its voxels in space, so that a mesh can be registered to it. Images
come from :func:`from_array` or from a file (:func:`read`) and go to a file with :func:`write`:
NIfTI (``.nii``, ``.nii.gz``) through nibabel, MetaImage and NRRD (``.mha``, ``.mhd``,
``.nrrd``, ``.nhdr``) through SimpleITK when it is installed, and lungmech's own ``.npz``.

Conventions:

* Coordinates are lungmech's: metres, x towards the patient's right, y anterior, z superior.
  That is the RAS+ world space of NIfTI and nibabel, so NIfTI affines are used as they are,
  only converted from the file's unit (millimetres, usually) to metres. DICOM, ITK and
  SimpleITK (hence MetaImage and NRRD read through it) use LPS+: x towards the left, y
  posterior, z superior, in millimetres by convention; their points are converted by flipping
  the signs of x and y.
* ``mask[i, j, k]`` is voxel (i, j, k), and ``affine @ (i, j, k, 1)`` is the position of its
  centre, as in NIfTI and ITK: voxel (0, 0, 0) covers the indices -0.5 to 0.5 on each axis.
"""

from __future__ import annotations

import hashlib
import itertools
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from lungmech.errors import ImageError
from lungmech.registration.itk import itk_affine, itk_geometry, one_line, read_series, simpleitk

__all__ = ["SUFFIXES", "Image", "companions", "from_array", "kind", "read", "stem", "write", "written_by_lungmech"]

# Metres per file unit. NIfTI files that leave the unit unset are nearly always millimetres.
_NIFTI_UNITS = {"meter": 1.0, "mm": 1e-3, "micron": 1e-6, "unknown": 1e-3}
_UNITS = {"m": 1.0, "mm": 1e-3}
SUFFIXES = {
    ".nii": "nifti",
    ".nii.gz": "nifti",
    ".npz": "npz",
    ".mha": "itk",
    ".mhd": "itk",
    ".nrrd": "itk",
    ".nhdr": "itk",
}
_SIGNATURE = "lungmech image"  # in the header of the images lungmech writes, with a digest of the voxels


@dataclass(frozen=True, eq=False)  # eq=False: arrays have no single truth value
class Image:
    """A 3-D segmentation placed in space.

    Args:
        mask: Boolean array of shape (n0, n1, n2) indexed ``[i, j, k]``, with at least one
            voxel set.
        affine: (4, 4) map from voxel indices ``(i, j, k, 1)`` (voxel centres) to lungmech
            coordinates in metres.

    Both arrays are exposed read-only: an image does not change once made (use
    :meth:`with_mask` for another segmentation on the same grid).
    """

    mask: npt.NDArray[np.bool_]
    affine: npt.NDArray[np.float64]
    source: Path | None = None  # the file it was read from, if any
    oriented: bool = True  # whether the header places it in the patient frame (NIfTI: an sform or qform code)

    def __post_init__(self) -> None:
        mask = self.mask
        if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_ or mask.ndim != 3:
            found = f"{mask.ndim}-D {mask.dtype}" if isinstance(mask, np.ndarray) else type(mask).__name__
            raise ImageError(f"an image mask must be a 3-D boolean array, got {found}")
        if not mask.any():
            raise ImageError(f"the mask is empty (shape {mask.shape}): no voxel is set")
        try:
            affine = np.array(self.affine, dtype=np.float64)
        except (TypeError, ValueError):
            raise ImageError(f"an image affine must be a 4x4 matrix of numbers, got {self.affine!r}") from None
        if affine.shape != (4, 4) or not np.isfinite(affine).all():
            raise ImageError(f"an image affine must be a finite 4x4 matrix, got shape {affine.shape}")
        if not np.array_equal(affine[3], [0.0, 0.0, 0.0, 1.0]):
            raise ImageError(f"the last row of an image affine must be (0, 0, 0, 1), got {affine[3]}")
        if np.linalg.cond(affine[:3, :3]) > 1e12:
            raise ImageError(f"the image affine is singular: {affine.tolist()}")
        # Read-only views: the caller's arrays stay writable, but not through the image.
        mask = mask.view()
        mask.flags.writeable = False
        affine.flags.writeable = False
        object.__setattr__(self, "mask", mask)
        object.__setattr__(self, "affine", affine)

    @property
    def shape(self) -> tuple[int, int, int]:
        """Number of voxels along i, j and k."""
        n0, n1, n2 = self.mask.shape
        return n0, n1, n2

    @property
    def spacing(self) -> npt.NDArray[np.float64]:
        """Distance between neighbouring voxel centres along i, j and k, in metres."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    @property
    def voxel_volume(self) -> float:
        """Volume of one voxel, in cubic metres."""
        return float(abs(np.linalg.det(self.affine[:3, :3])))

    @property
    def volume(self) -> float:
        """Volume of the segmented region (the voxels set in the mask), in cubic metres."""
        return np.count_nonzero(self.mask) * self.voxel_volume

    def points(self, index: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Positions in metres of voxel indices (fractional allowed), of shape (..., 3)."""
        index = np.asarray(index, dtype=np.float64)
        return index @ self.affine[:3, :3].T + self.affine[:3, 3]

    def index(self, points: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Fractional voxel indices of positions in metres, of shape (..., 3); inverse of :meth:`points`.

        ``np.rint(image.index(p)).astype(int)`` is the voxel containing ``p`` (when inside the image).
        """
        points = np.asarray(points, dtype=np.float64)
        return (points - self.affine[:3, 3]) @ np.linalg.inv(self.affine[:3, :3]).T

    def centres(self) -> npt.NDArray[np.float64]:
        """Positions in metres of all voxel centres, shape (n0 * n1 * n2, 3), in C order of the mask.

        This materialises every voxel; for the segmented voxels only, use
        ``image.points(np.argwhere(image.mask))``.
        """
        return self.points(np.indices(self.shape).reshape(3, -1).T)

    def bounds(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Lower and upper corners in metres of the axis-aligned box around the whole image.

        The box covers the voxels themselves, not just their centres (an oblique image's box
        is the box around its eight rotated corners).
        """
        corners = self.points(list(itertools.product(*[(-0.5, n - 0.5) for n in self.shape])))
        return corners.min(axis=0), corners.max(axis=0)

    def with_mask(self, mask: npt.ArrayLike) -> Image:
        """The same grid with another mask (boolean or 0/1, of the same shape)."""
        mask = _binary(np.asarray(mask), None, "the new mask")
        if mask.shape != self.shape:
            raise ImageError(f"the new mask has shape {mask.shape}, the image has {self.shape}")
        return Image(mask, self.affine, oriented=self.oriented)


def from_array(
    mask: npt.ArrayLike,
    spacing: npt.ArrayLike = (0.001, 0.001, 0.001),
    origin: npt.ArrayLike = (0.0, 0.0, 0.0),
    direction: npt.ArrayLike | None = None,
) -> Image:
    """An image from a 3-D array on a regular grid, with ITK-style geometry in lungmech axes.

    Args:
        mask: Boolean or 0/1 array indexed ``[i, j, k]``.
        spacing: Distance between voxel centres along i, j and k, in metres.
        origin: Position in metres of the centre of voxel (0, 0, 0).
        direction: Orthogonal 3x3 matrix whose columns are the directions of the i, j and k
            axes in lungmech coordinates; identity by default.
    """
    data = _spatial(np.asarray(mask), "the array")
    spacing = np.asarray(spacing, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    direction = np.eye(3) if direction is None else np.asarray(direction, dtype=np.float64)
    if spacing.shape != (3,) or not (np.isfinite(spacing).all() and (spacing > 0).all()):
        raise ImageError(f"spacing must be three positive lengths in metres, got {spacing}")
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise ImageError(f"origin must be a finite 3-D point, got {origin}")
    if direction.shape != (3, 3) or not np.allclose(direction.T @ direction, np.eye(3), atol=1e-6):
        raise ImageError(f"direction must be an orthogonal 3x3 matrix (axis columns), got {direction.tolist()}")
    return Image(_binary(data, None, "the array"), _affine(direction * spacing, origin))


def read(path: str | Path, *, label: int | Sequence[int] | None = None, unit: str | None = None) -> Image:
    """Read a segmentation from a file, or from a folder of one DICOM series.

    Args:
        path: A ``.nii`` or ``.nii.gz`` file (NIfTI, affine as nibabel chooses it from the
            sform and qform), a ``.mha``, ``.mhd``, ``.nrrd`` or ``.nhdr`` file (needs
            SimpleITK), a ``.npz`` file from :func:`write`, or a folder holding one DICOM
            series (needs SimpleITK; only its pixels and geometry are read, no other tag).
        label: Select the voxels with this value, or with any of these values (a lung as its
            lobes' labels). Without it, the image must be binary (boolean, or values 0 and 1
            only).
        unit: Length unit of the file's geometry, ``"m"`` or ``"mm"``, overriding what the file
            says. By default, NIfTI's header unit is used (millimetres when it is unset), and
            ITK formats and DICOM are taken as millimetres. Ignored for ``.npz``, which is always in metres.

    Raises:
        ImageError: The file is missing, unreadable or not a usable 3-D segmentation.
    """
    path = Path(path)
    format_ = "dicom" if path.is_dir() else kind(path)
    if unit is not None and unit not in _UNITS:
        raise ImageError(f"unknown unit {unit!r} for image '{path}'; use 'm' or 'mm'")
    if not path.exists():
        raise ImageError(f"image file '{path}' not found")
    what = f"image '{path}'"
    scale = None if unit is None else _UNITS[unit]
    oriented = True
    if format_ == "dicom":
        data, affine = _from_itk(read_series(path), path, scale)
    elif format_ == "nifti":
        data, affine, oriented = _read_nifti(path, scale)
    elif format_ == "itk":
        data, affine = _read_itk(path, scale)
    else:
        data, affine = _read_npz(path)
    mask = _binary(data, label, what)
    try:
        return Image(np.ascontiguousarray(mask), affine, path, oriented)
    except ImageError as e:
        raise ImageError(f"{what}: {e}") from None


def write(image: Image, path: str | Path) -> None:
    """Write an image to a file, creating parent folders; the format follows the suffix.

    NIfTI files get uint8 data and a millimetre affine as both sform and qform (code 1,
    scanner). NIfTI-1 stores the affine in single precision (about 7 digits, tens of
    nanometres across a chest), so only affines read from NIfTI come back exactly; ``.npz``,
    ``.mha`` and ``.nrrd`` keep double precision. ITK formats (needs SimpleITK) cannot store a
    sheared affine.
    """
    path = Path(path)
    format_ = kind(path)
    nib = _nibabel(path) if format_ == "nifti" else None  # imported first, to fail before touching the disk
    sitk = simpleitk(path) if format_ == "itk" else None
    data = image.mask.astype(np.uint8)
    signature = _signature(data)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if format_ == "nifti":
            assert nib is not None  # imported above for this format
            affine = _scaled(image.affine, 1e3)
            nifti = nib.Nifti1Image(data, affine)
            nifti.set_sform(affine, code=1)
            nifti.set_qform(affine, code=1)
            nifti.header.set_xyzt_units(xyz="mm")
            nifti.header["descrip"] = signature
            nib.save(nifti, path)
        elif format_ == "itk":
            assert sitk is not None  # imported above for this format
            origin, spacing, direction = itk_geometry(image.affine, path)
            # ITK arrays are indexed [k, j, i].
            itk = sitk.GetImageFromArray(np.ascontiguousarray(data.transpose(2, 1, 0)))
            itk.SetOrigin(origin.tolist())
            itk.SetSpacing(spacing.tolist())
            itk.SetDirection(direction.ravel().tolist())
            itk.SetMetaData("written_by", signature)
            sitk.WriteImage(itk, str(path), True)  # True: compress
        else:
            np.savez_compressed(path, mask=image.mask, affine=image.affine, written_by=signature)
    except ImageError:
        raise
    except Exception as e:
        raise ImageError(f"cannot write image '{path}': {one_line(e)}") from e


def written_by_lungmech(path: str | Path) -> bool:
    """Whether the image file ``path`` was written by :func:`write` and its voxels are unchanged
    (its header carries a digest of them)."""
    path = Path(path)
    try:
        return _stored_signature(path) == _signature(read(path).mask.astype(np.uint8))
    except Exception:  # any reader's failure: not a file lungmech can vouch for
        return False


def companions(path: str | Path) -> list[str]:
    """The names of the files written next to an image file: a MetaImage's or NRRD header's data."""
    path = Path(path)
    name = path.name.lower()
    if name.endswith(".mhd"):
        return [f"{stem(path)}.zraw"]
    if name.endswith(".nhdr"):
        return [f"{stem(path)}.raw.gz"]
    return []


def _signature(data: npt.NDArray[np.uint8]) -> str:
    """lungmech's mark on an image, with the first 40 hex digits of the voxels' SHA-256 (fits NIfTI's 80 bytes)."""
    digest = hashlib.sha256(str(data.shape).encode() + np.ascontiguousarray(data).tobytes()).hexdigest()
    return f"{_SIGNATURE} {digest[:40]}"


def _stored_signature(path: Path) -> str:
    format_ = kind(path)
    if format_ == "nifti":
        import nibabel as nib

        header = nib.load(path).header  # a NIfTI header, indexable by field (the stubs say FileBasedHeader)
        return header["descrip"].item().decode(errors="replace").strip()  # type: ignore[index]
    if format_ == "itk":
        import SimpleITK as sitk

        reader = sitk.ImageFileReader()
        reader.SetFileName(str(path))
        reader.ReadImageInformation()
        return reader.GetMetaData("written_by") if reader.HasMetaDataKey("written_by") else ""
    with np.load(path, allow_pickle=False) as npz:
        return str(npz["written_by"])


def kind(path: Path) -> str:
    """The format of an image file from its suffix (any case): nifti, npz or itk."""
    name = path.name.lower()
    for suffix, format_ in SUFFIXES.items():
        if name.endswith(suffix):
            return format_
    raise ImageError(f"image '{path}' has an unknown suffix; use one of {', '.join(SUFFIXES)}")


def stem(path: Path) -> str | None:
    """The file name without its image suffix (any case), or None for a non-image."""
    name = path.name
    for suffix in SUFFIXES:
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return None


def _read_nifti(path: Path, scale: float | None) -> tuple[npt.NDArray[Any], npt.NDArray[np.float64], bool]:
    """Voxels, affine (m) and whether the header orients them (an sform or qform code > 0;
    without one nibabel's affine is a bare scaling, in no patient frame)."""
    nib = _nibabel(path)
    try:
        nifti = nib.load(path)
        if not isinstance(nifti, nib.Nifti1Image):  # Nifti2Image is a subclass
            raise TypeError(f"not a NIfTI image but {type(nifti).__name__}")
        data = np.asanyarray(nifti.dataobj)  # applies scl_slope/inter, if any
        affine = np.array(nifti.affine, dtype=np.float64)
        unit = nifti.header.get_xyzt_units()[0]
        oriented = int(nifti.header["sform_code"]) > 0 or int(nifti.header["qform_code"]) > 0
    except Exception as e:  # nibabel raises many kinds (ImageFileError, OSError, EOFError, zlib.error...)
        raise ImageError(f"cannot read image '{path}': {one_line(e)}") from e
    data = _spatial(data, f"image '{path}'")
    return data, _scaled(affine, _NIFTI_UNITS.get(unit, 1e-3) if scale is None else scale), oriented


def _read_itk(path: Path, scale: float | None) -> tuple[npt.NDArray[Any], npt.NDArray[np.float64]]:
    sitk = simpleitk(path)
    try:
        itk = sitk.ReadImage(str(path))
    except Exception as e:
        raise ImageError(f"cannot read image '{path}': {one_line(e)}") from e
    return _from_itk(itk, path, scale)


def _from_itk(itk: Any, path: Path, scale: float | None) -> tuple[npt.NDArray[Any], npt.NDArray[np.float64]]:
    """An ITK image's voxels, indexed [i, j, k], and its affine in lungmech's metres."""
    sitk = simpleitk(path)
    try:
        components = itk.GetNumberOfComponentsPerPixel()
        data = sitk.GetArrayFromImage(itk).transpose()  # ITK arrays are [k, j, i]
        affine = itk_affine(itk, 1e-3 if scale is None else scale)
    except Exception as e:
        raise ImageError(f"cannot read image '{path}': {one_line(e)}") from e
    if components != 1:
        raise ImageError(f"image '{path}' has {components} values per voxel; a segmentation has one")
    return _spatial(data, f"image '{path}'"), affine


def _read_npz(path: Path) -> tuple[npt.NDArray[Any], npt.NDArray[np.float64]]:
    # Checked first: np.load takes anything else for a pickle and complains about that.
    if not zipfile.is_zipfile(path):
        raise ImageError(f"cannot read image '{path}': not a .npz archive")
    try:
        with np.load(path, allow_pickle=False) as npz:
            data, affine = npz["mask"], npz["affine"]
    except Exception as e:
        reason = f"{one_line(e)} (expected arrays 'mask' and 'affine')"
        raise ImageError(f"cannot read image '{path}': {reason}") from e
    return _spatial(data, f"image '{path}'"), affine


def _nibabel(path: Path) -> Any:
    try:
        import nibabel as nib
    except ImportError:
        raise ImageError(f"image '{path}' needs nibabel for its format: pip install nibabel") from None
    return nib


def _spatial(data: npt.NDArray[Any], what: str) -> npt.NDArray[Any]:
    """The 3-D array, dropping trailing axes of length 1 (e.g. a NIfTI time axis)."""
    shape = data.shape
    while data.ndim > 3 and data.shape[-1] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        raise ImageError(f"{what} is {len(shape)}-D (shape {shape}); a segmentation must be 3-D")
    return data


def _binary(data: npt.NDArray[Any], label: int | Sequence[int] | None, what: str) -> npt.NDArray[np.bool_]:
    """The boolean mask of ``data``: the voxels equal to ``label`` (or to any of several), or
    of a 0/1 image."""
    if label is not None:
        wanted = [label] if isinstance(label, int | np.integer) else list(label)
        if missing := [value for value in wanted if not np.any(data == value)]:
            shown = ", ".join(str(value) for value in missing)
            raise ImageError(f"{what} has no voxel labelled {shown}; its labels are {_labels(data)}")
        return np.isin(data, wanted)
    if data.dtype == np.bool_:
        mask = data
    else:
        mask = data != 0
        if not (data[mask] == 1).all():
            raise ImageError(
                f"{what} is not binary (its labels are {_labels(data)}); choose one with --label (label= in Python)"
            )
    if not mask.any():
        raise ImageError(f"{what} is empty (shape {data.shape}): no voxel is set")
    return mask


def _labels(data: npt.NDArray[Any], most: int = 10) -> str:
    values = np.unique(data)
    shown = ", ".join(str(v) for v in values[:most].tolist())
    return shown if len(values) <= most else f"{shown}, ... ({len(values)} values)"


def _affine(axes: npt.NDArray[np.float64], origin: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    affine = np.eye(4)
    affine[:3, :3] = axes
    affine[:3, 3] = origin
    return affine


def _scaled(affine: npt.NDArray[np.float64], factor: float) -> npt.NDArray[np.float64]:
    """The affine with positions multiplied by ``factor`` (a change of length unit)."""
    return np.diag([factor, factor, factor, 1.0]) @ affine
