"""What a segmentation tells of a lung's state: its surface, as a distance field, and its volume.

A segmentation of the lung at end-inspiration locates its surface, not its material points: the
motion inside it, or along it, is not in the image. The data a fitted motion w is judged on are
therefore, for each surface node x_i of the lung imaged at end-expiration,

    d_i(μ) = d(x_i + w_i(μ)),

d the signed distance to the end-inspiration segmentation's surface (m, < 0 inside;
:func:`lungmech.registration.field.signed_distance`), and the volume the segmentation encloses,
V = (voxels inside) × (voxel volume). A node's distance moves with the normal part of its
motion: ∂d_i/∂μ = ∇d(x_i + w_i) · ∂w_i/∂μ.

The surface nodes carry their lumped areas a_i (a third of each boundary triangle's area at each
of its vertices). A volume mismatch ΔV is a mean normal offset ΔV / Σ a_i of the surface, and is
weighed as one more node's distance: the volume is the sum of the same surface's offsets, so
weighing it by the variance that sum would have (σ (Σ a_i²)^½) would count the surface twice.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import dolfinx
import numpy as np

from lungmech.errors import ParameterError
from lungmech.registration.field import ImageFunction, signed_distance
from lungmech.registration.image import Image

__all__ = ["Surface", "SurfaceNodes", "surface_data", "surface_nodes"]


@dataclass(frozen=True, eq=False)
class Surface:
    """A segmented state as data: ``distance``, the signed distance to its surface (m, < 0
    inside, with its gradient), ``volume`` (m³) and ``voxel``, its largest spacing (m)."""

    distance: ImageFunction | Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
    volume: float
    voxel: float

    def seen_from(self, rotation: np.ndarray, translation: np.ndarray) -> Surface:
        """The same surface in the frame that x ↦ R x + t maps into the image's (a rigid
        motion): its distance d(R x + t), whose gradient is Rᵀ ∇d; its volume is unchanged."""
        R, t, image = np.asarray(rotation, dtype=float), np.asarray(translation, dtype=float), self.distance

        def distance(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            values, gradients = image(np.asarray(points, dtype=float) @ R.T + t)
            return values, gradients @ R

        return replace(self, distance=distance)


def surface_data(image: Image, smoothing: float = 1.0) -> Surface:
    """The data of a segmentation: its signed distance, smoothed by ``smoothing`` voxels (a
    Gaussian's standard deviation; it rounds the voxels' staircase), and its volume."""
    if not image.mask.any():
        raise ParameterError("the segmentation is empty: no voxel lies inside the lung")
    volume = float(image.mask.sum()) * float(np.prod(image.spacing))
    return Surface(signed_distance(image, smoothing), volume, float(np.max(image.spacing)))


@dataclass(frozen=True)
class SurfaceNodes:
    """The boundary vertices of a mesh, the same on every rank: ``points`` (n, 3) in m, their
    lumped ``areas`` (n,) in m², and the boundary's ``triangles`` (m, 3), indices into
    ``points`` (for pictures; none for a cloud of points)."""

    points: np.ndarray
    areas: np.ndarray
    triangles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))

    @property
    def area(self) -> float:
        """Σ a_i in m²: a volume change over it is the surface's mean normal offset."""
        return float(np.sum(self.areas))

    def moved(self, displacement: np.ndarray) -> SurfaceNodes:
        """The same nodes moved by ``displacement`` (n, 3; m), their areas those of the moved
        triangles (a template's surface at a patient's shape)."""
        points = self.points + np.asarray(displacement, dtype=float)
        corners = points[self.triangles]
        shares = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
        areas = np.bincount(self.triangles.reshape(-1), weights=np.repeat(shares / 3.0, 3), minlength=len(points))
        return SurfaceNodes(points, areas, self.triangles)


def surface_nodes(mesh: dolfinx.mesh.Mesh) -> SurfaceNodes:
    """The vertices of ``mesh``'s boundary (a tetrahedral mesh's exterior triangles) with their
    lumped areas, ordered by coordinates so that any partition gives the same list. Collective."""
    if mesh.topology.dim != 3 or mesh.geometry.dim != 3:
        raise ParameterError("surface data need a 3-D tetrahedral mesh of the lung")
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim - 1, tdim)
    mesh.topology.create_connectivity(tdim - 1, 0)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    owned = facets[facets < mesh.topology.index_map(tdim - 1).size_local]
    vertices = dolfinx.mesh.entities_to_geometry(mesh, tdim - 1, owned)[:, :3]
    x = mesh.geometry.x
    triangles = x[vertices]  # (facets, 3 corners, 3)
    areas = 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)
    corners = triangles.reshape(-1, 3)
    shares = np.repeat(areas / 3.0, 3)
    gathered = mesh.comm.allgather((corners, shares))
    corners = np.concatenate([c for c, _ in gathered])
    shares = np.concatenate([s for _, s in gathered])
    # one row per vertex: the same coordinates on every rank that holds it (rounded to 1e-12 m)
    key = np.round(corners, 12)
    unique, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    lumped = np.bincount(inverse.reshape(-1), weights=shares, minlength=len(unique))
    triangles = inverse.reshape(-1, 3)
    return SurfaceNodes(np.ascontiguousarray(corners[first]), lumped, triangles)  # the nodes as they are (unique sorts)
