"""A scene's ``[parameters]``: named values μ, each on a target of the scene (a law constant, a
load's amplitude, an interface), with its range, scale, region and unit, read and checked into
:class:`~lungmech.fem.parameters.Parameter` objects; and the scene's tables with μ substituted."""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lungmech.app.table_checks import call, no_unknown_keys, typed
from lungmech.errors import LungmechError, ParameterError, SceneError
from lungmech.fem.parameters import Cells, HalfSpace, Parameter, Parameters

if TYPE_CHECKING:
    from lungmech.mesh.geometry import Geometry

__all__ = ["ImageLabel", "parameters", "substituted"]


# Units of the targets a parameter may name (the unit a user gives its values in).
_UNITS = {
    "E": "Pa",
    "mu": "Pa",
    "lmbda": "Pa",
    "bulk": "Pa",
    "c0": "Pa",
    "c1": "Pa",
    "c2": "Pa",
    "alpha": "Pa",
    "kappa": "Pa",
    "pore_barrier": "Pa",
    "nu": "1",
    "gamma": "1",
    "phi_s0": "1",
    "imaged_porosity": "1",
    "pore_exponent": "1",
    "c2_share": "1",
    "value": "Pa",
    "amplitude": "1",
    "pitch": "deg",
    "roll": "deg",
    "angle": "deg",
}
_PARAMETER_KEYS = ("target", "default", "range", "scale", "region", "outside")


def parameters(table: dict[str, Any], folder: Path) -> tuple[Parameter, ...]:
    """[parameters.NAME] tables: target, range, optional default (the scene's own value at the
    target), scale ("linear" or "log"), region and outside."""
    section = table.get("parameters", {})
    if not isinstance(section, dict):
        raise SceneError("parameters: expected tables [parameters.NAME]")
    built = []
    for name, entry in section.items():
        where = f"parameters.{name}"
        if not isinstance(entry, dict):
            raise SceneError(f"{where}: expected a table with target and range")
        no_unknown_keys(entry, _PARAMETER_KEYS, where)
        for required in ("target", "range"):
            if required not in entry:
                raise SceneError(f"{where}: missing key '{required}'")
        target = typed(entry["target"], str, f"{where}.target")
        if target.partition(".")[0] == "shape" and "shape_modes" not in table.get("geometry", {}):
            raise SceneError(
                f"{where}.target: {target} is a shape mode's coefficient: name the library's shape modes in "
                "[geometry] (shape_modes = \"modes.npz\", from 'lungmech shape-modes' on this mesh)"
            )
        scale = entry.get("scale", "linear")
        if scale not in ("linear", "log"):
            raise SceneError(f"{where}.scale: must be 'linear' or 'log' (got {scale!r})")
        default = entry["default"] if "default" in entry else _value_at(table, target, where)
        kind, _, key = target.partition(".")
        unit = {"interface": "m", "shape": "sd"}.get(kind, _UNITS.get(key.rpartition(".")[2], ""))
        built.append(
            call(
                Parameter,
                {
                    "name": name,
                    "target": target,
                    "default": default,
                    "range": entry["range"],
                    "log": scale == "log",
                    "unit": unit,
                    "region": _region(entry.get("region"), f"{where}.region", folder),
                    "outside": entry.get("outside"),
                },
                where,
            )
        )
    try:
        Parameters(built)
    except ParameterError as error:
        raise SceneError(f"parameters: {error}") from None
    return tuple(built)


def _region(spec: Any, where: str, folder: Path) -> Cells | HalfSpace | None:
    """A parameter's region: {tag = N} (cell tag), {image = "labels.nii.gz", label = N} (the cells
    whose midpoint lies in a voxel of that label) or {normal, position, width} (a half-space)."""
    if spec is None:
        return None
    if not isinstance(spec, dict):
        raise SceneError(
            f"{where}: expected {{tag = N}}, {{image = FILE, label = N}} or {{normal = [..], position = .., width = ..}}"
        )
    if "tag" in spec:
        no_unknown_keys(spec, ("tag",), where)
        return call(Cells, {"tag": spec["tag"], "label": f"tag {spec['tag']}"}, where)
    if "image" in spec:
        no_unknown_keys(spec, ("image", "label"), where)
        path = folder / typed(spec["image"], str, f"{where}.image")
        label = typed(spec.get("label"), int, f"{where}.label")
        if not path.is_file():
            raise SceneError(f"{where}.image: file '{path}' not found")
        return Cells(marker=ImageLabel(str(path), label), label=f"label {label} of {path.name}")
    no_unknown_keys(spec, ("normal", "position", "width"), where)
    return call(HalfSpace, spec, where)


@dataclass(frozen=True)
class ImageLabel:
    """The cells whose midpoint lies in a voxel of ``label`` in a label image (a segmentation of
    lobes or zones): a :class:`~lungmech.fem.parameters.Cells` marker."""

    path: str
    label: int

    def __call__(self, geometry: Geometry) -> np.ndarray:
        from lungmech.registration import image as images

        try:
            zone = images.read(self.path, label=self.label)
        except LungmechError as error:
            raise SceneError(f"region image: {error}") from None
        mesh = geometry.mesh
        cells = mesh.topology.index_map(mesh.topology.dim)
        nodes = mesh.geometry.dofmaps[0][: cells.size_local + cells.num_ghosts]
        voxels = np.rint(zone.index(mesh.geometry.x[nodes].mean(axis=1))).astype(int)
        inside = np.all((voxels >= 0) & (voxels < zone.shape), axis=1)
        marked = np.zeros(len(voxels), dtype=bool)
        marked[inside] = zone.mask[tuple(voxels[inside].T)]
        return marked


def _value_at(table: dict[str, Any], target: str, where: str) -> object:
    """The scene's own value at a parameter's target: its default when none is given (a load's
    value as written, a number or not: :class:`~lungmech.fem.parameters.Parameter` checks it)."""
    kind, _, key = target.partition(".")
    name, _, attribute = key.rpartition(".")
    if kind == "loads" and attribute in ("amplitude", "pitch", "roll", "angle"):
        return 1.0 if attribute == "amplitude" else 0.0
    if kind == "constraints" and attribute == "amplitude":
        return 1.0
    if kind == "shape":  # the library's mean shape
        return 0.0
    if kind == "loads" and attribute == "value":
        for entry in table.get("loads", []):
            if isinstance(entry, dict) and entry.get("name") == name:
                return entry.get("value")
    if kind in ("material", "formulation"):
        value = _lookup(table.get(kind, {}), key)
        if isinstance(value, int | float) and not isinstance(value, bool):
            return value
        if value is None:  # a misspelt key more often than a missing default
            section = table.get(kind, {})
            known = ", ".join(k for k, v in section.items() if isinstance(v, int | float | list)) or "none"
            raise SceneError(f"{where}.target: the scene has no {target} ([{kind}] keys: {known})")
    if kind == "loads" and attribute == "value":
        named = [e["name"] for e in table.get("loads", []) if isinstance(e, dict) and e.get("name")]
        if name not in named:
            raise SceneError(f"{where}.target: no load named '{name}' (named loads: {', '.join(named) or 'none'})")
    raise SceneError(f"{where}: give a default (the scene has no number at {target})")


def _lookup(table: Any, path: str) -> Any:
    for part in path.replace("[", ".").replace("]", "").split("."):
        if isinstance(table, dict):
            table = table.get(part)
        elif isinstance(table, list) and part.isdigit() and int(part) < len(table):
            table = table[int(part)]
        else:
            return None
    return table


def substituted(table: dict[str, Any], keys: Mapping[str, float], where: str) -> dict[str, Any]:
    """A copy of ``table`` with the values at the dotted ``keys`` (``c1``, ``terms[1].c1``) replaced."""
    table = copy.deepcopy(table)
    for path, value in keys.items():
        parts = path.replace("[", ".").replace("]", "").split(".")
        node = table
        for part in parts[:-1]:
            node = node[int(part)] if isinstance(node, list) else node[part]
        node[parts[-1]] = value
    return table
