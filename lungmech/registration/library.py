"""From a library of mappings of one reference mesh to shape modes, and back to new geometries.

Every mapping φ_j = Id + u_j of the reference Ω (one per patient, from :func:`register`) is
written in one node order (the canonical, partition-independent order of
:mod:`lungmech.parallel.layout`). The similarity part of each mapping (position, orientation, size)
is removed by composition, φ̃_j = S_j⁻¹ ∘ φ_j with S_j its mass-weighted Procrustes fit; the rest
is centred on the sample mean and reduced by a POD in the mass inner product
(u, v)_M = (1/|Ω|) ∫_Ω u·v dX with lumped nodal masses, so that norms read as RMS displacements
in metres. Coefficients of a shape are in standard deviations of the library.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from mpi4py import MPI

import numpy as np
from dolfinx import fem
from dolfinx import mesh as dmesh

from lungmech.errors import ParameterError, RegistrationError
from lungmech.mesh import nodes
from lungmech.mesh.geometry import Geometry
from lungmech.parallel import linalg
from lungmech.registration import align, metrics
from lungmech.registration.align import Similarity, procrustes
from lungmech.registration.image import Image
from lungmech.registration.sobolev import Options, register

__all__ = [
    "POSES",
    "Library",
    "Projection",
    "ShapeModes",
    "leave_one_out",
    "mapping_library",
    "pose_of",
    "shape_modes",
    "without_similarity",
]

FORMAT = "lungmech-shape-modes/1"

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Library:
    """Mappings of one reference mesh onto several images (nodes in canonical order).

    Attributes:
        names: One per image.
        reference: Reference node positions (n, 3).
        weights: Normalised lumped nodal masses (n,).
        displacements: The mappings' displacements (N, n, 3), similarity included.
        fingerprint: Of the reference mesh's node layout.
        reports: Registration summary and metrics per image.
    """

    names: tuple[str, ...]
    reference: np.ndarray
    weights: np.ndarray
    displacements: np.ndarray
    fingerprint: str
    reports: tuple[dict, ...]

    def shape_changes(self, pose: str = "similarity") -> np.ndarray:
        """The displacements with each mapping's ``pose`` removed (N, n, 3): "similarity"
        (position, orientation and size) or "rigid" (position and orientation: the size stays a
        change of shape, as a population's mechanics needs)."""
        return np.array([without_similarity(self.reference, u, self.weights, pose) for u in self.displacements])

    def modes(self, pose: str = "similarity") -> ShapeModes:
        changes = self.shape_changes(pose)
        return shape_modes(self.reference, changes, self.weights, self.fingerprint, self.names, pose)

    def leave_one_out(self, pose: str = "similarity") -> np.ndarray:
        return leave_one_out(self.shape_changes(pose), self.weights)


def mapping_library(mesh: dmesh.Mesh, images: Mapping[str, Image], options: Options = Options()) -> Library:
    """Register ``mesh`` (left unchanged) onto every image (collective)."""
    if len(images) < 2:
        raise RegistrationError(f"a mapping library needs at least 2 images, got {len(images)}")
    space, where = nodes.displacement_space(mesh)
    # The library and its POD work on replicated nodal arrays (one reference mesh's nodes per
    # image): the canonical arrays that rank 0 gathers are broadcast to every rank on purpose.
    reference = mesh.comm.bcast(nodes.positions(space, where))
    weights = mesh.comm.bcast(nodes.masses(space, where))
    displacements, reports = [], []
    for name, image in images.items():
        result = register(mesh, image, options)
        with nodes.deformed(result.displacement) as mapped:
            report = {"name": name} | metrics.report(mapped, image) | result.summary()
        log.info(
            "%s: Dice %.4f, mean surface distance %.2f voxels, min det F %.3f, %d iterations",
            name,
            report["dice"],
            report["mean_surface_distance_voxels"],
            report["min_det_F"],
            report["iterations"],
        )
        displacements.append(mesh.comm.bcast(nodes.gather(result.displacement, where)))
        reports.append(report)
    return Library(tuple(images), reference, weights, np.array(displacements), where.fingerprint, tuple(reports))


POSES = ("similarity", "rigid")  # what a library's shape changes are taken without


def pose_of(
    reference: np.ndarray, displacement: np.ndarray, weights: np.ndarray, pose: str = "similarity"
) -> Similarity:
    """S, the best fit of φ = Id + displacement among the similarities (``pose`` "similarity")
    or the rigid motions ("rigid")."""
    if pose not in POSES:
        raise RegistrationError(f"a pose is removed as 'similarity' or 'rigid', not {pose!r}")
    return procrustes(reference, reference + displacement, weights, scaling=pose == "similarity")


def without_similarity(
    reference: np.ndarray, displacement: np.ndarray, weights: np.ndarray, pose: str = "similarity"
) -> np.ndarray:
    """The displacement of S⁻¹ ∘ φ, φ = Id + displacement, S its :func:`pose_of` (``pose``
    "similarity", or "rigid": the size is kept)."""
    fit = pose_of(reference, displacement, weights, pose)
    return fit.inverse()(reference + displacement) - reference


@dataclass(frozen=True)
class Projection:
    """A mapping on a library's modes: ``coefficients`` (standard deviations of the library),
    what the modes leave out, ``rms`` over the body (mass-weighted) and ``largest`` at a node
    (m), and its ``pose`` S, the fit it was taken without: the mapped body is S(χ(X))."""

    coefficients: np.ndarray
    rms: float
    largest: float
    pose: Similarity


@dataclass(frozen=True)
class ShapeModes:
    """Mean shape and modes of a library of mappings of one reference mesh (nodes canonical).

    Attributes:
        reference: Reference node positions (n, 3).
        weights: Normalised lumped nodal masses (n,).
        mean: Mean displacement (n, 3).
        modes: M-orthonormal modes (m, n, 3).
        singular_values: Of the centred, mass-weighted library (m,), metres.
        coefficients: Of each library member on the modes (N, m), in standard deviations.
        fingerprint: Of the reference mesh's layout; a mesh with another refuses the modes.
        names: Library members.
        pose: What each mapping was taken without: "similarity" (position, orientation and
            size: shape alone) or "rigid" (the size kept, as a population's model needs).
    """

    reference: np.ndarray
    weights: np.ndarray
    mean: np.ndarray
    modes: np.ndarray
    singular_values: np.ndarray
    coefficients: np.ndarray
    fingerprint: str
    names: tuple[str, ...]
    pose: str = "similarity"

    def __post_init__(self) -> None:
        if self.pose not in POSES:
            raise RegistrationError(f"shape modes: pose must be one of {', '.join(POSES)}, not {self.pose!r}")
        n, m = len(self.reference), len(self.singular_values)
        shapes = {"weights": (n,), "mean": (n, 3), "modes": (m, n, 3), "coefficients": (len(self.names), m)}
        for name, shape in shapes.items():
            if np.shape(getattr(self, name)) != shape:
                raise RegistrationError(
                    f"shape modes: '{name}' has shape {np.shape(getattr(self, name))}, expected {shape}"
                )

    @property
    def deviations(self) -> np.ndarray:
        """Standard deviation of the library along each mode (RMS metres)."""
        return self.singular_values / np.sqrt(max(len(self.names) - 1, 1))

    def compactness(self) -> np.ndarray:
        """Fraction of the library's variance captured by the first 1, 2, ... modes."""
        energy = self.singular_values**2
        return np.cumsum(energy) / energy.sum()

    def displacement(self, coefficients: Sequence[float]) -> np.ndarray:
        """Mean + Σ c_k σ_k mode_k, c in standard deviations (fewer than the modes: the rest 0)."""
        c = np.asarray(coefficients, dtype=float)
        if not np.all(np.isfinite(c)):
            raise ParameterError(f"shape coefficients must be finite numbers, got {list(c)}")
        if c.ndim != 1 or len(c) > len(self.modes):
            raise RegistrationError(f"give at most {len(self.modes)} shape coefficients, got {c.size}")
        return self.mean + np.einsum("k,knd->nd", c * self.deviations[: len(c)], self.modes[: len(c)])

    def project(self, displacement: np.ndarray, count: int) -> Projection:
        """A new mapping's displacement (n, 3, canonical order, its pose included) on the mean
        and the first ``count`` modes: its pose removed as the library's was, the coefficients
        c (standard deviations) of (u − mean) along each mode in the mass inner product, and
        what the modes leave out, RMS and largest over the nodes (m)."""
        if not isinstance(count, int) or isinstance(count, bool) or not 0 <= count <= len(self.modes):
            raise RegistrationError(f"project on 0 to {len(self.modes)} shape modes, got {count!r}")
        u = np.asarray(displacement, dtype=float)
        if u.shape != self.reference.shape:
            raise RegistrationError(
                f"a mapping of these modes' reference has shape {self.reference.shape}, got {u.shape}"
            )
        fit = pose_of(self.reference, u, self.weights, self.pose)
        residual = fit.inverse()(self.reference + u) - self.reference - self.mean
        coefficients = np.empty(count)
        for k in range(count):
            along = _inner(residual, self.modes[k], self.weights)
            coefficients[k] = along / self.deviations[k]
            residual = residual - along * self.modes[k]
        left = np.linalg.norm(residual, axis=1)
        return Projection(coefficients, _norm(residual, self.weights), float(left.max(initial=0.0)), fit)

    def geometry(self, reference: Geometry, coefficients: Sequence[float]) -> Geometry:
        """``reference`` mapped by a shape: its nodes are moved in place, and it is returned.

        Pass a freshly read reference. The boundary names and tags are the reference's, so a
        scene's loads and constraints apply. A shape that inverts a cell is refused.
        """
        space, where = nodes.displacement_space(reference.mesh)
        if where.fingerprint != self.fingerprint:
            raise RegistrationError(
                "the mesh is not the reference these shape modes were built on "
                f"(fingerprint {where.fingerprint}, modes {self.fingerprint})"
            )
        u = fem.Function(space)
        nodes.scatter(self.displacement(coefficients), u, where)
        before = align.cell_volumes(reference.mesh)
        nodes.move_nodes(u)
        ratio = align.cell_volumes(reference.mesh) / before
        smallest = reference.mesh.comm.allreduce(float(ratio.min()) if len(ratio) else np.inf, op=MPI.MIN)
        if smallest <= 0.0:
            raise RegistrationError(f"shape {list(coefficients)} inverts cells of the mesh: too far from the library")
        return reference

    def template(self, reference: Geometry, count: int) -> tuple[Geometry, list[fem.Function]]:
        """The population's template and its first ``count`` modes as a model's shape modes.

        ``reference`` (freshly read) is moved in place by the mean shape and returned with the
        vector fields σ_k mode_k (m) on it: a model on the template whose shape coefficients
        (:mod:`lungmech.fem.shape`) are c, in standard deviations, is the model on
        :meth:`geometry` (reference, c) — without a new mesh.
        """
        if not isinstance(count, int) or isinstance(count, bool) or not 1 <= count <= len(self.modes):
            raise RegistrationError(f"a template takes 1 to {len(self.modes)} shape modes, got {count!r}")
        moved = self.geometry(reference, [])
        space, where = nodes.displacement_space(moved.mesh)
        fields = []
        for k in range(count):
            field = fem.Function(space, name=f"shape_mode_{k + 1}")
            nodes.scatter(self.deviations[k] * self.modes[k], field, where)
            fields.append(field)
        return moved, fields

    def save(self, path: str | Path) -> None:
        """Write to ``.npz`` (arrays plus JSON metadata); call on one rank."""
        path = Path(path)
        if path.suffix != ".npz":
            raise RegistrationError(f"shape modes are saved as .npz, not {path.suffix!r}")
        path.parent.mkdir(parents=True, exist_ok=True)
        metadata = {"format": FORMAT, "fingerprint": self.fingerprint, "names": list(self.names), "pose": self.pose}
        np.savez(
            path,
            reference=self.reference,
            weights=self.weights,
            mean=self.mean,
            modes=self.modes,
            singular_values=self.singular_values,
            coefficients=self.coefficients,
            metadata=json.dumps(metadata),
        )

    @classmethod
    def load(cls, path: str | Path) -> ShapeModes:
        path = Path(path)
        if not path.is_file():
            raise RegistrationError(f"shape modes file '{path}' not found")
        try:
            with np.load(path, allow_pickle=False) as data:
                metadata = json.loads(str(data["metadata"]))
                arrays = {
                    k: data[k] for k in ("reference", "weights", "mean", "modes", "singular_values", "coefficients")
                }
            if metadata["format"] != FORMAT:
                raise ValueError(f"format {metadata['format']!r}")
            modes = cls(
                **arrays,
                fingerprint=str(metadata["fingerprint"]),
                names=tuple(metadata["names"]),
                pose=str(metadata.get("pose", "similarity")),  # (files before the pose was kept)
            )
        except Exception as error:  # numpy, zipfile and json raise many kinds
            raise RegistrationError(f"'{path}' is not a shape-modes file ({type(error).__name__}: {error})") from None
        return modes


def shape_modes(
    reference: np.ndarray,
    displacements: Sequence[np.ndarray] | np.ndarray,
    weights: np.ndarray,
    fingerprint: str,
    names: Sequence[str] | None = None,
    pose: str = "similarity",
) -> ShapeModes:
    """Mass-weighted POD, centred on the mean, of displacements (n, 3) each, taken without
    their ``pose`` (see :func:`without_similarity`) already."""
    data = np.asarray(displacements, dtype=float)
    if data.ndim != 3 or data.shape[1:] != reference.shape or len(data) < 2:
        raise RegistrationError(f"need at least 2 displacements of shape {reference.shape}, got {data.shape}")
    mean = data.mean(axis=0)
    modes, singular, coefficients = _pod(data - mean, weights)
    names = tuple(names) if names is not None else tuple(f"shape_{j}" for j in range(len(data)))
    deviations = singular / np.sqrt(len(data) - 1)
    scaled = coefficients / deviations
    return ShapeModes(reference, weights, mean, modes, singular, scaled, fingerprint, names, pose)


def _pod(centred: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """M-orthonormal modes (m, n, 3), singular values and coefficients (N, m) of centred samples
    (N, n, 3), by the one POD of :mod:`lungmech.parallel.linalg` (the library is replicated on every
    rank: no communication). A centred library has rank N − 1 at most; the rest is round-off."""
    mass = np.repeat(weights, centred.shape[2])  # M on the flattened (node, component) rows
    columns = centred.reshape(len(centred), -1).T
    decomposition = linalg.pod(columns, lambda V: mass[:, None] * V, MPI.COMM_SELF)
    modes = decomposition.modes.T.reshape(-1, *centred.shape[1:])
    return modes, decomposition.values, decomposition.coefficients


def leave_one_out(displacements: Sequence[np.ndarray] | np.ndarray, weights: np.ndarray) -> np.ndarray:
    """RMS generalisation error (metres) against the number of modes 0, 1, ..., N − 2.

    Each member is left out in turn, modes are built from the others, and the member's distance
    from the span of (mean + modes) is measured in the mass norm.
    """
    data = np.asarray(displacements, dtype=float)
    count = len(data)
    if count < 3:
        raise RegistrationError(f"leave-one-out needs at least 3 shapes, got {count}")
    errors = np.zeros((count, count - 1))
    for j in range(count):
        others = np.delete(data, j, axis=0)
        mean = others.mean(axis=0)
        modes, _, _ = _pod(others - mean, weights)
        residual = data[j] - mean
        errors[j, 0] = _norm(residual, weights)
        for m, mode in enumerate(modes[: count - 2], start=1):
            residual = residual - _inner(residual, mode, weights) * mode
            errors[j, m] = _norm(residual, weights)
        errors[j, len(modes) + 1 :] = errors[j, len(modes)]
    return np.sqrt(np.mean(errors**2, axis=0))


def _inner(a: np.ndarray, b: np.ndarray, weights: np.ndarray) -> float:
    return float(np.einsum("n,nd,nd->", weights, a, b))


def _norm(a: np.ndarray, weights: np.ndarray) -> float:
    return np.sqrt(_inner(a, a, weights))
