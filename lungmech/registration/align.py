"""Similarity transforms x -> s R x + t: the initial fit of a mesh to an image, and their removal
from a mapping.

The initial fit matches moments: centroids (translation), volumes (isotropic scale) and, when
asked, the principal axes of the second moments (rotation; the axis signs are those closest to
the identity, since scans share an anatomical orientation). The removal is a weighted
Procrustes fit (Umeyama 1991) of the mapped nodes by a similarity S, after which S⁻¹ ∘ φ carries
only the shape change.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

from mpi4py import MPI

import numpy as np
from dolfinx import mesh as dmesh

from lungmech.errors import RegistrationError
from lungmech.registration.image import Image

__all__ = ["Similarity", "moments_fit", "procrustes"]


@dataclass(frozen=True)
class Similarity:
    """The map x -> scale · rotation · x + translation."""

    scale: float = 1.0
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Images of points (n, 3)."""
        return self.scale * np.asarray(points) @ self.rotation.T + self.translation

    def inverse(self) -> Similarity:
        rotation = self.rotation.T
        return Similarity(1.0 / self.scale, rotation, -(rotation @ self.translation) / self.scale)

    def as_dict(self) -> dict:
        return {"scale": self.scale, "rotation": self.rotation.tolist(), "translation": self.translation.tolist()}


@dataclass(frozen=True)
class Moments:
    """Volume, centroid and covariance (second central moment / volume) of a solid."""

    volume: float
    centroid: np.ndarray
    covariance: np.ndarray


def mesh_moments(mesh: dmesh.Mesh) -> Moments:
    """Moments of a tetrahedral mesh in its current configuration (collective; vertices only,
    so exact for straight-sided cells)."""
    owned = mesh.topology.index_map(mesh.topology.dim).size_local
    x = mesh.geometry.x[mesh.geometry.dofmaps[0][:owned, :4]]  # (cells, 4, 3)
    volume = np.abs(cell_volumes(mesh))
    # ∫ x dx = V mean(vertices); ∫ x xᵀ dx = V/20 (Σ x_i x_iᵀ + (Σ x_i)(Σ x_i)ᵀ)
    total = x.sum(axis=1)
    first = (volume[:, None] * total / 4.0).sum(axis=0)
    second = np.einsum(
        "c,cij->ij", volume / 20.0, np.einsum("cvi,cvj->cij", x, x) + np.einsum("ci,cj->cij", total, total)
    )
    sums = np.concatenate([[volume.sum()], first, second.ravel()])
    mesh.comm.Allreduce(MPI.IN_PLACE, sums, op=MPI.SUM)
    return _moments(sums[0], sums[1:4], sums[4:].reshape(3, 3))


def cell_volumes(mesh: dmesh.Mesh) -> np.ndarray:
    """Signed volumes of this rank's owned cells (their vertices; the sign is the orientation)."""
    owned = mesh.topology.index_map(mesh.topology.dim).size_local
    x = mesh.geometry.x[mesh.geometry.dofmaps[0][:owned, :4]]  # the vertices come first in every cell
    return np.linalg.det(x[:, 1:] - x[:, :1]) / 6.0


def image_moments(image: Image) -> Moments:
    """Moments of the segmented voxels (each voxel's own extent included)."""
    points = image.points(np.argwhere(image.mask).astype(float))
    volume = len(points) * image.voxel_volume
    centroid = points.mean(axis=0)
    centred = points - centroid
    # A box voxel of edges a_k (columns of the affine) adds a a^T / 12 to the covariance.
    edges = image.affine[:3, :3]
    covariance = centred.T @ centred / len(points) + edges @ edges.T / 12.0
    return Moments(volume, centroid, covariance)


def _moments(volume: float, first: np.ndarray, second: np.ndarray) -> Moments:
    centroid = first / volume
    return Moments(volume, centroid, second / volume - np.outer(centroid, centroid))


def moments_fit(mesh: dmesh.Mesh, image: Image, rotation: bool = True) -> Similarity:
    """The similarity that maps the mesh's moments onto the segmentation's."""
    source, target = mesh_moments(mesh), image_moments(image)
    scale = (target.volume / source.volume) ** (1.0 / 3.0)
    rotate = _principal_rotation(source.covariance, target.covariance) if rotation else np.eye(3)
    return Similarity(scale, rotate, target.centroid - scale * rotate @ source.centroid)


def _principal_rotation(source: np.ndarray, target: np.ndarray, gap: float = 0.05) -> np.ndarray:
    """The rotation taking the source's principal axes to the target's, nearest the identity.

    Nearly equal second moments leave the axes undefined: then no rotation is guessed.
    """
    values_s, axes_s = np.linalg.eigh(source)
    values_t, axes_t = np.linalg.eigh(target)
    for values in (values_s, values_t):
        if np.min(np.diff(values)) < gap * values[-1]:
            return np.eye(3)
    candidates = []
    for signs in itertools.product((1.0, -1.0), repeat=3):
        rotation = axes_t @ np.diag(signs) @ axes_s.T
        if np.linalg.det(rotation) > 0:
            candidates.append(rotation)
    return max(candidates, key=np.trace)


def procrustes(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None, scaling: bool = True
) -> Similarity:
    """The similarity S minimising Σ w_i |S(source_i) − target_i|² (no reflections); without
    ``scaling``, the rigid motion (scale 1) minimising it."""
    source, target = np.asarray(source, dtype=float), np.asarray(target, dtype=float)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3:
        raise RegistrationError(f"procrustes needs two (n, 3) point sets, got {source.shape} and {target.shape}")
    w = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    mean_s, mean_t = w @ source, w @ target
    cs, ct = source - mean_s, target - mean_t
    u, singular, vt = np.linalg.svd((ct * w[:, None]).T @ cs)
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ flip @ vt
    variance = w @ np.sum(cs**2, axis=1)
    scale = float(np.trace(np.diag(singular) @ flip) / variance) if scaling else 1.0
    return Similarity(scale, rotation, mean_t - scale * rotation @ mean_s)
