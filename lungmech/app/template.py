"""A scene's body over a population: the library's mean shape, and its modes as parameters.

A scene whose [geometry] names a library's shape modes (``shape_modes = "modes.npz"``, from
``lungmech shape-modes`` on the scene's mesh) is solved on the library's mean shape, the
template, and its parameters ``shape.mode_<i>`` are the coefficients of the first modes, in the
library's standard deviations (:meth:`lungmech.registration.library.ShapeModes.template`,
:mod:`lungmech.fem.shape`): one model, and one reduced model, for every patient the modes
represent. The model holds as many modes as the highest one a parameter names.
"""

from __future__ import annotations

import copy
import re
from dataclasses import replace
from pathlib import Path

from mpi4py import MPI

from dolfinx import fem

from lungmech.app import scene as scenes
from lungmech.app.scene import Scene, build_geometry
from lungmech.errors import SceneError
from lungmech.fem.shape import KIND
from lungmech.mesh.geometry import Geometry
from lungmech.registration.library import ShapeModes

__all__ = ["body_modes", "build_template", "mode_count", "with_surface_probes"]


def mode_count(scene: Scene) -> int:
    """The highest shape mode a parameter of ``scene`` names (0: none)."""
    numbers = [
        int(found.group(1))
        for p in scene.parameters
        if (found := re.fullmatch(rf"{KIND}\.mode_([1-9][0-9]*)", p.target)) is not None
    ]
    return max(numbers, default=0)


def build_template(scene: Scene, comm: MPI.Comm) -> tuple[Geometry, list[fem.Function]]:
    """The scene's mesh and its shape modes: the mesh as [geometry] describes it and no modes,
    or with ``shape_modes`` the library's mean shape and the first :func:`mode_count` modes
    (σ-scaled fields, m). A library of another mesh, or with fewer modes, is refused in one line."""
    geometry = build_geometry(scene.geometry, comm)
    if "shape_modes" not in scene.geometry:
        return geometry, []
    path = Path(scene.geometry["shape_modes"])
    library = ShapeModes.load(path)
    count = mode_count(scene)
    if count > len(library.modes):
        raise SceneError(
            f"geometry.shape_modes: '{path}' holds {len(library.modes)} modes; a parameter names mode {count}"
        )
    if count == 0:
        return library.geometry(geometry, []), []
    return library.template(geometry, count)


def body_modes(scene: Scene, geometry: Geometry) -> list[fem.Function]:
    """Zero shape modes on ``geometry``, a hyper-reduced model's body of sampled cells, for
    :func:`lungmech.rom.body.place_functions` to fill from the model file (as many as
    :func:`build_template` made)."""
    if "shape_modes" not in scene.geometry:
        return []
    mesh = geometry.mesh
    space = fem.functionspace(mesh, ("Lagrange", mesh.geometry.cmaps[0].degree, (mesh.geometry.dim,)))
    return [fem.Function(space, name=f"shape_mode_{k + 1}") for k in range(mode_count(scene))]


def with_surface_probes(scene: Scene, comm: MPI.Comm) -> Scene:
    """``scene`` whose probes are its mesh's surface nodes (on a population's scene, its
    template's: the same material points for every patient), in the order
    :func:`lungmech.twin.surface.surface_nodes` gives them: a model a patient's surface data are
    fitted with (``lungmech personalise --model``)."""
    from lungmech.twin.surface import surface_nodes

    geometry, _ = build_template(scene, comm)
    points = surface_nodes(geometry.mesh).points
    table = copy.deepcopy(scene.table)
    table.setdefault("output", {})["probes"] = points.tolist()
    found = scenes.parse(table, folder=scene.folder, source=scene.source)
    return replace(found, values=dict(scene.values))
