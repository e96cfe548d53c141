"""Synthetic patients: a pair of segmentations made by a model whose parameters are known.

A model of an imaged lung (its mesh the lung at end-expiration, t₀) solved at μ gives its
motion w to end-inspiration T; both states, voxelised on one CT-like grid, are the pair of
segmentations a clinic would have. Made on a finer mesh than the one that estimates, and read
back as images only, they test the whole pipeline without an inverse crime: the estimating
model never sees the mesh, the nodes or the motion that made them.

Noise where it arises on segmentations: :func:`flip_boundary` flips a fraction of the voxels on
the segmentation's surface (either side), seeded. Noise on the data themselves, as the published
twin protocol adds it to displacements: :func:`surface_noise`, Gaussian on each surface datum,
its standard deviation a fraction of the RMS of the surface's observed motion, independent or
correlated over a length.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from scipy import ndimage

from lungmech.errors import ParameterError
from lungmech.fem.parametric import ParametricModel
from lungmech.mesh import nodes
from lungmech.registration.image import Image, from_array
from lungmech.registration.metrics import voxelise
from lungmech.registration.vectors import VectorImage
from lungmech.twin.fit import Fit

__all__ = ["displacement_field", "flip_boundary", "image_pair", "surface_noise"]


def image_pair(
    model: ParametricModel, mu: Mapping[str, float], time: float, spacing: float, margin: float = 0.02
) -> tuple[Image, Image]:
    """(end-expiration, end-inspiration) segmentations of the lung ``model`` (a full model of an
    imaged body: ``solve``, ``fields`` and ``model``) at ``mu``, voxelised at ``spacing`` (m) on
    one grid that holds both with ``margin`` (m) around. Collective."""
    if not spacing > 0:
        raise ParameterError(f"the voxel spacing must be a positive length in m (got {spacing})")
    solution = model.solve(mu, times=[model.stepping.start, time])
    model.fields(solution.states[-1], time)
    fe = model.model
    mesh = fe.geometry.mesh
    motion = fe.motion()
    expiration_nodes = mesh.geometry.x.copy()
    with nodes.deformed(motion):
        inspiration_nodes = mesh.geometry.x.copy()
    both = np.vstack([expiration_nodes, inspiration_nodes])
    low = np.min(mesh.comm.allgather(both.min(axis=0)), axis=0) - margin
    high = np.max(mesh.comm.allgather(both.max(axis=0)), axis=0) + margin
    shape = np.ceil((high - low) / spacing).astype(int)
    grid = from_array(np.ones(shape, dtype=bool), spacing=(spacing,) * 3, origin=low + spacing / 2)
    expiration = voxelise(mesh, grid)
    with nodes.deformed(motion):
        inspiration = voxelise(mesh, grid)
    return (
        from_array(expiration, spacing=(spacing,) * 3, origin=low + spacing / 2),
        from_array(inspiration, spacing=(spacing,) * 3, origin=low + spacing / 2),
    )


def displacement_field(
    model: ParametricModel, mu: Mapping[str, float], time: float, grid: Image, smoothing: float = 1.0
) -> VectorImage:
    """The motion from end-expiration to end-inspiration of the lung ``model`` (as
    :func:`image_pair`'s) at ``mu``, as an intensity registration would give it on the voxels
    of ``grid`` (its end-expiration segmentation): the model's w at the centres of the voxels
    inside, carried outward to the others from the nearest inside, then smoothed by a Gaussian
    of ``smoothing`` voxels (standard deviation). Collective."""
    from scipy import ndimage

    from lungmech.fem.quantities import Probe

    solution = model.solve(mu, times=[model.stepping.start, time])
    model.fields(solution.states[-1], time)
    inside = grid.mask
    centres = grid.points(np.argwhere(inside))
    values = np.zeros((*grid.shape, 3))
    values[inside] = Probe(model.model.geometry.mesh, centres.tolist())(model.model.motion())
    nearest = ndimage.distance_transform_edt(~inside, return_distances=False, return_indices=True)
    values = values[tuple(nearest)]  # every voxel: its nearest inside voxel's motion
    if smoothing > 0:
        values = np.stack([ndimage.gaussian_filter(values[..., c], smoothing) for c in range(3)], axis=-1)
    return VectorImage(values, grid.affine)


def flip_boundary(image: Image, fraction: float, seed: int = 0) -> Image:
    """``image`` with ``fraction`` of its surface voxels (those with a neighbour across the
    surface, on either side) flipped, chosen at random (seeded): a segmentation's own noise."""
    if not 0 <= fraction <= 1:
        raise ParameterError(f"the fraction of surface voxels to flip must lie in [0, 1] (got {fraction})")
    mask = image.mask
    surface = mask ^ ndimage.binary_erosion(mask) | ndimage.binary_dilation(mask) ^ mask
    where = np.flatnonzero(surface)
    chosen = np.random.default_rng(seed).choice(where, size=int(round(fraction * where.size)), replace=False)
    flipped = mask.copy().reshape(-1)
    flipped[chosen] = ~flipped[chosen]
    return image.with_mask(flipped.reshape(mask.shape))


def surface_noise(fit: Fit, fraction: float, seed: int = 0, correlation: float = 0.0) -> np.ndarray:
    """An offset for ``fit``'s residual (m, one per row): on each view's surface rows, Gaussian
    noise of standard deviation ``fraction`` × the RMS of the surface's observed normal motion,
    U_n,i = d(x_i) − d₀(x_i) (the end-inspiration segmentation's signed distance at the imaged
    nodes, against end-expiration's); zero on the volume rows. ``correlation`` (m): a length
    over which the noise is correlated, exp(−|x_i − x_j|² / (2 ℓ²)) between nodes (0: none).
    Seeded: the same on every rank."""
    if not 0 <= fraction:
        raise ParameterError(f"the noise must be a non-negative fraction of the surface's motion (got {fraction})")
    if not 0 <= correlation:
        raise ParameterError(f"the noise's correlation length must be a length ≥ 0 in m (got {correlation})")
    rng = np.random.default_rng(seed)
    offset = np.zeros(fit.rows)
    for view, rows in zip(fit.views, fit.surface_rows()):
        motion, _ = view.surface.distance(view.nodes.points)
        if view.baseline is not None:
            motion = motion - view.baseline.distance(view.nodes.points)[0]
        draw = rng.normal(0.0, 1.0, size=len(rows))
        if correlation > 0:  # a Gaussian field on the nodes: L z, L L^T the correlation
            points = view.nodes.points
            squared = np.sum((points[:, None, :] - points[None, :, :]) ** 2, axis=-1)
            kernel = np.exp(-squared / (2 * correlation**2)) + 1e-9 * np.eye(len(points))
            draw = np.linalg.cholesky(kernel) @ draw
        offset[rows] = fraction * float(np.sqrt(np.mean(motion**2))) * draw
    return offset
