"""A scene at other discretisations: its mesh refined or remeshed, its elements' degree changed.

A :class:`Discretisation` names one: ``level`` k > 0 is the scene's mesh refined k times
(nested: the same polyhedron, each edge halved k times, :mod:`lungmech.mesh.refine`), k < 0
the body remeshed by its builder at 2^|k| times its mesh size (another, coarser polyhedron),
``degree`` the elements' polynomial degree (of the displacement), and ``mixed`` the
Taylor–Hood formulation P_k–P_{k−1} in place of the scene's displacement formulation (where
its law has a volumetric split: :func:`mixed_allowed`). :func:`at` gives the scene at one: the same
physics on that mesh. Values the scene gives per cell of its mesh (an imaged porosity, say)
pass to a refined mesh's children unchanged; a remeshed body has other cells and cannot take
them. A refined mesh and its cell values are files in lungmech's cache
(:mod:`lungmech.app.cache`), made once per content; the scene's own files are only read.

Collective: under MPI, call :func:`at` on all ranks.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from mpi4py import MPI

import numpy as np

from lungmech.app.cache import Cache, code_version, key
from lungmech.app.scene import BUILDERS, Scene, build_geometry, cell_data, file_sha256, physics
from lungmech.errors import ParameterError
from lungmech.fem.formulations import TaylorHood
from lungmech.lung.poromechanics import read_cell_values
from lungmech.mesh import files
from lungmech.mesh.builders import default_mesh_size
from lungmech.mesh.refine import refined
from lungmech.parallel import on_root

__all__ = ["Discretisation", "at", "mixed_allowed", "remeshed"]

DEGREES = (1, 2)


@dataclass(frozen=True, order=True)
class Discretisation:
    """A mesh ``level`` (0: the scene's; k > 0: refined k times; k < 0: remeshed at 2^|k| h)
    and an elements' ``degree``."""

    level: int = 0
    degree: int = 1
    mixed: bool = False

    def __post_init__(self) -> None:
        if isinstance(self.level, bool) or not isinstance(self.level, int):
            raise ParameterError(f"a mesh level is an integer (got {self.level!r})")
        if self.degree not in DEGREES:
            raise ParameterError(f"element degree must be one of {', '.join(map(str, DEGREES))} (got {self.degree!r})")
        if self.mixed and self.degree < 2:
            raise ParameterError(
                f"the mixed formulation is Taylor–Hood: its displacement degree is ≥ 2 (got {self.degree})"
            )

    @classmethod
    def of(cls, scene: Scene, level: int = 0) -> Discretisation:
        """The scene's own discretisation (its degree, its formulation's mixedness) at mesh ``level``."""
        return cls(level, scene.degree, scene.table.get("formulation", {}).get("type") == "mixed")

    @property
    def name(self) -> str:
        """E.g. "P1 h", "P1 h/4" (refined twice), "P2 h", "P1 2h" (remeshed coarser), "P2–P1 h"
        (Taylor–Hood)."""
        size = "h" if self.level == 0 else f"h/{2**self.level}" if self.level > 0 else f"{2**-self.level}h"
        elements = f"P{self.degree}–P{self.degree - 1}" if self.mixed else f"P{self.degree}"
        return f"{elements} {size}"

    @property
    def mesh_factor(self) -> float:
        """The mesh size relative to the scene's: 2^−level."""
        return 2.0**-self.level

    def content(self) -> dict:
        """What this discretisation is, for a cache key (and, as keywords, itself)."""
        return {"level": self.level, "degree": self.degree} | ({"mixed": True} if self.mixed else {})


def at(scene: Scene, discretisation: Discretisation, cache: Cache, comm: MPI.Comm = MPI.COMM_WORLD) -> Scene:
    """``scene`` at ``discretisation`` (see the module's doc). Its geometry never writes a mesh
    file of the scene's (a builder's ``msh_file`` is left out)."""
    geometry = {k: v for k, v in scene.geometry.items() if k != "msh_file"}
    scene = replace(scene, geometry=geometry, degree=discretisation.degree)
    if discretisation.mixed and scene.table.get("formulation", {}).get("type") != "mixed":
        mixed_allowed(scene)  # the displacement scene's Taylor–Hood version (a mixed one keeps its own)
        scene = replace(scene, formulation=TaylorHood())
    if discretisation.level > 0:
        return _refined(scene, discretisation.level, cache, comm)
    if discretisation.level < 0:
        return remeshed(scene, discretisation.mesh_factor)
    return scene


def mixed_allowed(scene: Scene) -> None:
    """Refuse, in one line, a scene that has no Taylor–Hood version: a formulation other than
    the displacement one (the lung's poromechanics, say), or a law without a volumetric split."""
    kind = scene.table.get("formulation", {}).get("type", "displacement")
    if kind != "displacement":
        raise ParameterError(f"formulation.type: the {kind} formulation has no Taylor–Hood (mixed) version")
    TaylorHood().check(scene.material, 2)


def _refined(scene: Scene, times: int, cache: Cache, comm: MPI.Comm) -> Scene:
    """The scene on its mesh refined ``times`` times: a mesh file and cell values in the cache."""
    cells = cell_data(scene.formulation)
    described = physics(scene)
    content = {
        "geometry": described["geometry"],
        "mesh_file": file_sha256(scene.geometry["file"]) if "file" in scene.geometry else None,
        "cells": {name: described["formulation"][name] for name in cells},
        "refinements": times,
        "code": code_version(("mesh",)),
    }

    def fill(folder: Path) -> None:
        fine = refined(build_geometry(scene.geometry, comm), times)
        files.write(fine.geometry, folder / "mesh.vtu")
        for name, path in cells.items():
            _save(folder / f"{name}.npy", fine.cell_values(read_cell_values(path, name)), comm)

    folder = cache.folder("levels", key(content), fill)
    formulation = replace(scene.formulation, **{name: str(folder / f"{name}.npy") for name in cells})
    return replace(scene, geometry={"file": str(folder / "mesh.vtu")}, formulation=formulation)


def remeshed(scene: Scene, factor: float) -> Scene:
    """The scene's body remeshed by its builder at ``factor`` times its mesh size; refused in
    one line where it cannot be (a mesh file, values per cell, a builder without a size)."""
    spec = dict(scene.geometry)
    if "file" in spec:
        raise ParameterError(
            f"geometry.file: the scene's mesh comes from a file ('{spec['file']}'), which lungmech cannot remesh: "
            "no coarser level is made (finer ones are, by refinement)"
        )
    if cells := cell_data(scene.formulation):
        raise ParameterError(
            f"formulation.{next(iter(cells))}: values given per cell of the scene's mesh do not fit a remeshed "
            "body: no coarser level is made (finer ones are, by refinement)"
        )
    name = spec.pop("builder")
    if "cells" in spec:
        counts = [int(n) for n in spec["cells"]]
        step = round(factor)
        if any(n % step for n in counts):
            raise ParameterError(
                f"geometry.cells: {tuple(counts)} cannot be divided by {step}: no mesh {step}× coarser is made"
            )
        spec["cells"] = tuple(n // step for n in counts)
    else:
        size = spec.get("mesh_size") or default_mesh_size(BUILDERS[name], spec)
        if size is None:
            raise ParameterError(f"geometry: the {name} builder has no mesh size to coarsen: no coarser level is made")
        spec["mesh_size"] = float(size) * factor
    return replace(scene, geometry={"builder": name, **spec})


def _save(path: Path, values: np.ndarray, comm: MPI.Comm) -> None:
    on_root(comm, lambda: np.save(path, values))
