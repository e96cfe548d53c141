"""Pictures of shape registration (matplotlib, off-screen).

- :func:`registration_slices`: three orthogonal slices through a segmentation with the mesh's
  boundary (and optionally a reference surface, e.g. the starting position) cut by each slice.
- :func:`shape_spectrum`: singular values and compactness of a shape-mode library, and its
  leave-one-out generalisation error.
- :func:`surface_sections`: several surfaces (e.g. a mean shape and its modes) cut by three
  orthogonal planes.

:func:`plane_section` is the geometry behind the slices, public for reuse.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import dolfinx
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import numpy.typing as npt  # noqa: E402
from matplotlib.artist import Artist  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from lungmech.errors import RegistrationError  # noqa: E402
from lungmech.parallel import on_root  # noqa: E402
from lungmech.registration.image import Image  # noqa: E402
from lungmech.registration.metrics import boundary_triangles  # noqa: E402

__all__ = ["plane_section", "registration_slices", "shape_spectrum", "surface_sections"]

_DPI = 150
_MASK_GREY = "0.72"
_MESH_COLOUR = "tab:red"
_REFERENCE_COLOUR = "tab:blue"
_AXES = "ijk"


def plane_section(triangles: npt.ArrayLike, normal: npt.ArrayLike, offset: float) -> list[npt.NDArray[np.float64]]:
    """Where a triangulated surface crosses the plane ``normal · x = offset``.

    Args:
        triangles: Vertex coordinates (n, 3, 3) of the surface's triangles.
        normal: The plane's normal (any length, not zero).
        offset: ``normal · x`` on the plane.

    Returns:
        Polylines of shape (p, 3), p >= 2, chained through the triangles that share an edge. A
        section of a closed surface gives closed polylines (last point = first point).

    A vertex lying on the plane counts as above it, so every triangle is cut by exactly zero or
    two of its edges and touching triangles do not leave stray bits.
    """
    triangles = np.asarray(triangles, dtype=np.float64).reshape(-1, 3, 3)
    normal = np.asarray(normal, dtype=np.float64)
    if normal.shape != (3,) or not np.any(normal):
        raise RegistrationError(f"a plane needs a non-zero 3-D normal, got {normal}")
    # Shared vertices become one: each cut edge then has one crossing point, computed once, so
    # the pieces from neighbouring triangles join exactly.
    vertices, ids = np.unique(triangles.reshape(-1, 3), axis=0, return_inverse=True)
    ids = ids.reshape(-1, 3)
    height = vertices @ normal - offset
    above = height >= 0
    start, end = ids, np.roll(ids, -1, axis=1)  # the edges of each triangle
    cut = above[start] != above[end]  # two or none per triangle
    # The cut edges, two by two (row-major order), as (lower, upper) vertex pairs: one key per
    # edge, whichever triangle it is seen from.
    lower = np.where(above[start], end, start)[cut]
    upper = np.where(above[start], start, end)[cut]
    edges, links = np.unique(np.stack([lower, upper], axis=1), axis=0, return_inverse=True)
    a, b = vertices[edges[:, 0]], vertices[edges[:, 1]]
    t = height[edges[:, 0]] / (height[edges[:, 0]] - height[edges[:, 1]])
    points = a + t[:, None] * (b - a)
    return [points[chain] for chain in _chains(links.reshape(-1, 2), len(points))]


def registration_slices(
    mesh: dolfinx.mesh.Mesh,
    image: Image,
    path: str | Path,
    *,
    title: str = "",
    reference: npt.ArrayLike | None = None,
    reference_label: str = "reference",
) -> None:
    """A PNG of three orthogonal slices through ``image`` with the cut of the mesh's boundary.

    The slices are ``k``, ``j`` and ``i`` = const (in that order) through the voxel nearest the
    centroid of the segmentation, with the mask in grey, in millimetres along the two in-plane
    voxel axes (from voxel 0). The mesh (in its current configuration) is cut by each slice
    plane; ``reference``, the triangles (n, 3, 3) of another surface in metres, e.g. the starting
    position, is drawn dashed. Parent folders are created. Collective: only rank 0 draws (and
    needs ``reference``); an error there is raised on every rank.
    """
    triangles = boundary_triangles(mesh)
    on_root(mesh.comm, lambda: _slices(triangles, image, path, title, reference, reference_label))


def _slices(
    triangles: np.ndarray,
    image: Image,
    path: str | Path,
    title: str,
    reference: npt.ArrayLike | None,
    reference_label: str,
) -> None:
    surfaces: list[tuple[np.ndarray, str, Literal["-", "--"], str]] = [(triangles, _MESH_COLOUR, "-", "mesh")]
    if reference is not None:
        reference = np.asarray(reference, dtype=np.float64).reshape(-1, 3, 3)
        surfaces.append((reference, _REFERENCE_COLOUR, "--", reference_label))

    voxels = np.argwhere(image.mask)
    centre = np.rint(voxels.mean(axis=0)).astype(int)
    # The same frame for a slice that misses the segmentation (the centroid of two lungs lies
    # between them): the whole segmentation's box.
    box = np.array([voxels.min(axis=0), voxels.max(axis=0)])
    spacing_mm = image.spacing * 1e3
    inverse = np.linalg.inv(image.affine[:3, :3])
    fig, axes = plt.subplots(1, 3, figsize=(13.5, 5.2))
    for ax, normal_axis in zip(axes, (2, 1, 0)):
        p, q = (axis for axis in range(3) if axis != normal_axis)
        level = centre[normal_axis]
        plane = image.mask.take(level, axis=normal_axis)  # indexed [p, q]
        lower, upper = -0.5 * spacing_mm[[p, q]], (np.array(plane.shape) - 0.5) * spacing_mm[[p, q]]
        ax.imshow(
            plane.T,  # rows are q: p runs across, q upwards
            origin="lower",
            extent=(lower[0], upper[0], lower[1], upper[1]),
            cmap=ListedColormap(["white", _MASK_GREY]),
            vmin=0,
            vmax=1,
            interpolation="nearest",
        )
        # The slice plane index[normal_axis] == level, as normal · x = offset in metres.
        normal = inverse[normal_axis]
        offset = level + normal @ image.affine[:3, 3]
        drawn = [box[:, [p, q]] * spacing_mm[[p, q]]]  # the view covers the segmentation...
        for triangles, colour, style, _ in surfaces:
            sections = plane_section(triangles, normal, offset)
            curves = [image.index(curve)[:, [p, q]] * spacing_mm[[p, q]] for curve in sections]
            ax.add_collection(LineCollection(curves, colors=colour, linestyles=style, linewidths=1.6))
            drawn += curves  # ... and the curves
        _frame(ax, np.concatenate(drawn), lower, upper)
        ax.set_title(f"{_AXES[normal_axis]} = {level}")
        ax.set_xlabel(_axis_label(image, p))
        ax.set_ylabel(_axis_label(image, q))
    handles: list[Artist] = [Patch(facecolor=_MASK_GREY, label="segmentation")]
    handles += [Line2D([], [], color=c, linestyle=style, label=name) for _, c, style, name in surfaces]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), frameon=False)
    if title:
        fig.suptitle(title)
    fig.tight_layout(rect=(0.0, 0.07, 1.0, 1.0))  # room for the legend below the panels
    _save(fig, path)


def shape_spectrum(
    singular_values: npt.ArrayLike,
    path: str | Path,
    *,
    leave_one_out: npt.ArrayLike | None = None,
    title: str = "",
) -> None:
    """A PNG of a shape-mode library's spectrum (call on one rank).

    Left: σ_k / σ_1 on a log scale against k = 1..m, with the cumulative compactness
    Σ_{i<=k} σ_i² / Σ σ² on a second axis. Right, with ``leave_one_out`` (RMS errors in metres
    against 0, 1, ... modes, as from :func:`lungmech.registration.library.leave_one_out`): that
    error in millimetres. Parent folders are created.
    """
    sigma = np.asarray(singular_values, dtype=np.float64)
    if sigma.ndim != 1 or len(sigma) == 0 or not sigma[0] > 0:
        raise RegistrationError(f"need a non-empty list of singular values, the first positive, got {sigma}")
    k = np.arange(1, len(sigma) + 1)
    energy = sigma**2
    panels = 1 if leave_one_out is None else 2
    fig, axes = plt.subplots(1, panels, figsize=(5.5 * panels, 4.2), squeeze=False)
    ax = axes[0, 0]
    ax.semilogy(k, sigma / sigma[0], "o-", color="tab:blue", label="σ$_k$ / σ$_1$")
    ax.set_xlabel("mode k")
    ax.set_ylabel("σ$_k$ / σ$_1$", color="tab:blue")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    twin = ax.twinx()
    twin.plot(k, np.cumsum(energy) / energy.sum(), "s--", color="tab:orange", ms=4, label="compactness")
    twin.set_ylim(0.0, 1.05)
    twin.set_ylabel("cumulative compactness", color="tab:orange")
    ax.set_title("Spectrum")
    ax.legend(handles=ax.get_lines() + twin.get_lines(), loc="center right")
    if leave_one_out is not None:
        error = np.asarray(leave_one_out, dtype=np.float64) * 1e3
        ax = axes[0, 1]
        ax.plot(np.arange(len(error)), error, "o-", color="tab:green")
        ax.set_xlabel("number of modes")
        ax.set_ylabel("leave-one-out RMS error (mm)")
        ax.set_ylim(bottom=0.0)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_title("Generalisation")
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    _save(fig, path)


def surface_sections(surfaces: dict[str, npt.ArrayLike], path: str | Path, *, title: str = "") -> None:
    """A PNG of surfaces (label -> triangles (n, 3, 3), metres) cut by the planes x, y and z =
    const through the first surface's centroid, e.g. a mean shape and its modes (one rank)."""
    if not surfaces:
        raise RegistrationError("no surface to draw")
    meshes = {label: np.asarray(t, dtype=np.float64).reshape(-1, 3, 3) for label, t in surfaces.items()}
    centre = next(iter(meshes.values())).reshape(-1, 3).mean(axis=0)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    fig, axes = plt.subplots(1, 3, figsize=(13, 5.2))
    for ax, normal_axis in zip(axes, (2, 1, 0)):
        p, q = [a for a in range(3) if a != normal_axis]
        for (label, triangles), colour in zip(meshes.items(), colours):
            normal = np.eye(3)[normal_axis]
            curves = [1e3 * c[:, [p, q]] for c in plane_section(triangles, normal, centre[normal_axis])]
            style = "-" if label == next(iter(meshes)) else "--"
            ax.add_collection(LineCollection(curves, colors=colour, linestyles=style, linewidths=1.5, label=label))
        ax.autoscale()
        ax.set_aspect("equal")
        ax.set_title(f"{'xyz'[normal_axis]} = {1e3 * centre[normal_axis]:.0f} mm")
        ax.set_xlabel(f"{'xyz'[p]} (mm)")
        ax.set_ylabel(f"{'xyz'[q]} (mm)")
    handles = [
        Line2D([], [], color=c, linestyle="-" if i == 0 else "--", label=label)
        for i, (label, c) in enumerate(zip(meshes, colours))
    ]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), frameon=False)
    if title:
        fig.suptitle(title)
    fig.tight_layout(rect=(0.0, 0.07, 1.0, 1.0))
    _save(fig, path)


def _chains(links: npt.NDArray[np.intp], n: int) -> list[list[int]]:
    """Node sequences walking every link (m, 2) of a graph of n nodes once.

    Open chains are walked from their ends, so a closed section comes back as one closed loop and
    a dashed line runs on along it, rather than restarting at every tiny segment.
    """
    neighbours: list[list[int]] = [[] for _ in range(n)]
    for link, (u, v) in enumerate(links.tolist()):
        neighbours[u].append(link)
        neighbours[v].append(link)
    used = np.zeros(len(links), dtype=bool)
    chains = []
    for start in sorted(range(n), key=lambda u: len(neighbours[u]) % 2 == 0):  # odd degree first
        while True:
            chain, u = [start], start
            while (found := next((k for k in neighbours[u] if not used[k]), None)) is not None:
                used[found] = True
                u = int(links[found, 0] + links[found, 1] - u)
                chain.append(u)
            if len(chain) == 1:
                break
            chains.append(chain)
    return chains


def _frame(ax: plt.Axes, points: npt.NDArray[np.float64], lower: npt.ArrayLike, upper: npt.ArrayLike) -> None:
    """Limits around ``points`` (mm) with a margin, within the image; equal scales."""
    low, high = points.min(axis=0), points.max(axis=0)
    margin = 0.08 * (high - low).max() + 1e-9
    low, high = np.maximum(low - margin, lower), np.minimum(high + margin, upper)
    ax.set_xlim(low[0], high[0])
    ax.set_ylim(low[1], high[1])
    ax.set_aspect("equal")


def _axis_label(image: Image, axis: int) -> str:
    """The voxel axis and the lungmech axis it runs closest to, e.g. ``i (mm) ≈ +x``."""
    direction = image.affine[:3, axis]
    closest = int(np.argmax(np.abs(direction)))
    return f"{_AXES[axis]} (mm) ≈ {'+' if direction[closest] > 0 else '−'}{'xyz'[closest]}"


def _save(fig: plt.Figure, path: str | Path) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
