"""A displacement field as an image: a vector per voxel, read and written.

A field computed elsewhere — a registration of two intensity images, from end-expiration to
end-inspiration, say — comes as a vector image: ``.nii``/``.nii.gz``, ``.mha``/``.mhd`` or
``.nrrd`` (read by SimpleITK), or lungmech's ``.npz`` (``field`` (nx, ny, nz, 3) in m and
``affine`` in m, lungmech's axes). ITK's convention holds for the first kind, whatever the
container: positions and vectors are in LPS millimetres (ITK writes NIfTI displacement fields
so, as ANTs and elastix do); lungmech's axes are RAS (x towards the patient's right, y anterior,
z superior) in metres, so x and y flip and millimetres become metres. A field whose vectors are
in another frame must be converted before it is given.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from lungmech.errors import ImageError
from lungmech.registration.image import kind
from lungmech.registration.itk import LPS, itk_affine, one_line, simpleitk

__all__ = ["VectorImage", "read_vectors", "write_vectors"]


@dataclass(frozen=True)
class VectorImage:
    """A vector per voxel: ``values`` (nx, ny, nz, 3) in m, lungmech's axes; ``affine`` from a
    voxel's index to its centre's position (m); ``source``, the file read."""

    values: npt.NDArray[np.float64]
    affine: npt.NDArray[np.float64]
    source: str | None = None

    def at(self, points: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """The field at ``points`` (n, 3; m), trilinear between voxel centres; a point beyond
        the outer voxels' centres is refused."""
        from scipy.ndimage import map_coordinates

        points = np.atleast_2d(np.asarray(points, dtype=float))
        index = (np.linalg.inv(self.affine) @ np.column_stack([points, np.ones(len(points))]).T)[:3]
        shape = np.array(self.values.shape[:3])[:, None]
        outside = np.any((index < -1e-9) | (index > shape - 1 + 1e-9), axis=0)
        if outside.any():
            where = ", ".join(f"{v:.4f}" for v in points[np.argmax(outside)])
            name = f"'{Path(self.source).name}'" if self.source else "the displacement field"
            raise ImageError(
                f"{name} does not cover the lung: {int(outside.sum())} points lie outside its voxels, "
                f"the first at ({where}) m"
            )
        return np.column_stack([map_coordinates(self.values[..., c], index, order=1, mode="nearest") for c in range(3)])


def read_vectors(path: str | Path, unit: str | None = None) -> VectorImage:
    """The vector image in ``path`` (see the module's doc); ``unit`` ("m" or "mm") overrides
    the length unit of an ITK-read file's positions and vectors (default mm)."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"displacement field '{path}' not found")
    if unit not in (None, "m", "mm"):
        raise ImageError(f"unknown unit {unit!r} for displacement field '{path}'; use 'm' or 'mm'")
    if kind(path) == "npz":
        try:
            with np.load(path, allow_pickle=False) as npz:
                values, affine = np.asarray(npz["field"], dtype=float), np.asarray(npz["affine"], dtype=float)
        except Exception as e:
            raise ImageError(
                f"cannot read displacement field '{path}': {one_line(e)} (expected 'field', 'affine')"
            ) from e
    else:
        sitk = simpleitk(path)
        scale = 1.0 if unit == "m" else 1e-3
        try:
            itk = sitk.ReadImage(str(path))
            components = itk.GetNumberOfComponentsPerPixel()
            data = sitk.GetArrayFromImage(itk)  # [k, j, i, c]
            affine = itk_affine(itk, scale)
        except Exception as e:
            raise ImageError(f"cannot read displacement field '{path}': {one_line(e)}") from e
        if components != 3 or data.ndim != 4:
            raise ImageError(
                f"displacement field '{path}' holds {components} values per voxel in {itk.GetDimension()}-D; "
                "a displacement field holds 3 per voxel in 3-D"
            )
        values = (data.transpose(2, 1, 0, 3) @ LPS) * scale  # LPS mm → RAS m (LPS is its own inverse)
    if values.ndim != 4 or values.shape[3] != 3 or affine.shape != (4, 4):
        raise ImageError(f"displacement field '{path}' is not a 3-D field of 3-D vectors (shape {values.shape})")
    if not np.isfinite(values).all():
        raise ImageError(f"displacement field '{path}' holds values that are not finite numbers")
    return VectorImage(values, affine, str(path))


def write_vectors(field: VectorImage, path: str | Path) -> None:
    """``field`` to ``path``: ``.npz`` as is, or an ITK format (SimpleITK; LPS millimetres)."""
    path = Path(path)
    if kind(path) == "npz":
        np.savez_compressed(path, field=field.values, affine=field.affine)
        return
    sitk = simpleitk(path)
    axes = LPS @ field.affine[:3, :3] * 1e3
    spacing = np.linalg.norm(axes, axis=0)
    itk = sitk.GetImageFromArray(np.ascontiguousarray((field.values @ LPS * 1e3).transpose(2, 1, 0, 3)), isVector=True)
    itk.SetOrigin((LPS @ field.affine[:3, 3] * 1e3).tolist())
    itk.SetSpacing(spacing.tolist())
    itk.SetDirection((axes / spacing).ravel().tolist())
    sitk.WriteImage(itk, str(path), True)
