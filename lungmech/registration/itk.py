"""ITK's files and conventions: SimpleITK's images, their LPS millimetres, their errors.

DICOM, ITK and SimpleITK (hence MetaImage and NRRD read through it) place voxels in LPS+: x
towards the patient's left, y posterior, z superior, in millimetres by convention. lungmech's
axes are RAS+ in metres (:mod:`lungmech.registration.image`), so x and y flip.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from lungmech.errors import ImageError

__all__ = ["LPS", "itk_affine", "itk_geometry", "one_line", "read_series", "simpleitk"]

LPS = np.diag([-1.0, -1.0, 1.0])  # RAS <-> LPS; its own inverse


def simpleitk(path: Path) -> Any:
    """SimpleITK, or one line on how to install it for the file ``path``."""
    try:
        import SimpleITK as sitk
    except ImportError:
        raise ImageError(f"image '{path}' needs SimpleITK for its format: pip install SimpleITK") from None
    return sitk


def itk_affine(itk: Any, scale: float) -> npt.NDArray[np.float64]:
    """The affine (voxel index → lungmech's RAS position) of an ITK image, whose geometry is
    LPS in units of 1/``scale`` m (ITK's millimetres: 1e-3)."""
    dim = itk.GetDimension()
    origin = np.array(itk.GetOrigin())[:3]
    spacing = np.array(itk.GetSpacing())[:3]
    direction = np.array(itk.GetDirection()).reshape(dim, dim)[:3, :3]
    affine = np.eye(4)
    affine[:3, :3] = LPS @ direction * spacing * scale
    affine[:3, 3] = LPS @ origin * scale
    return affine


def itk_geometry(affine: npt.NDArray[np.float64], path: Path) -> tuple[npt.NDArray[np.float64], ...]:
    """Origin, spacing and direction of an affine, in ITK's LPS millimetres."""
    axes = LPS @ affine[:3, :3] * 1e3
    spacing = np.linalg.norm(axes, axis=0)
    direction = axes / spacing
    if not np.allclose(direction.T @ direction, np.eye(3), atol=1e-6):
        raise ImageError(f"cannot write image '{path}': its affine is sheared, which ITK cannot store")
    return LPS @ affine[:3, 3] * 1e3, spacing, direction


def read_series(folder: Path) -> Any:
    """The one DICOM series in ``folder`` as an ITK image (its slices ordered by position, the
    geometry from their orientation and positions, by ITK's GDCM reader). Only the pixels and
    their geometry are read: none of the headers' other tags (the patient's name, say) is."""
    sitk = simpleitk(folder)
    try:
        series = list(sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(folder)))
    except Exception as e:
        raise ImageError(f"cannot read the DICOM folder '{folder}': {one_line(e)}") from e
    if len(series) != 1:
        held = "no DICOM series" if not series else f"{len(series)} DICOM series"
        raise ImageError(f"image folder '{folder}' holds {held}: give a folder of one segmentation's series")
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), series[0]))
    reader.MetaDataDictionaryArrayUpdateOff()  # (ITK's default: the tags stay unread)
    try:
        itk = reader.Execute()
    except Exception as e:
        raise ImageError(f"cannot read the DICOM series in '{folder}': {one_line(e)}") from e
    return itk


def one_line(error: Exception) -> str:
    """An error's message on one line (SimpleITK's span lines and end with the useful part)."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return lines[-1].removeprefix("sitk::ERROR: ") if lines else type(error).__name__
