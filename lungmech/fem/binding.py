"""How a model's parameters reach its forms: every value a parameter sets lives in a ``fem.Constant``.

:func:`material` turns a law (or a function of the parameter values that returns one) into the
law the forms use — each numeric constant a ``fem.Constant``, or c_out + χ (c_in − c_out) where
a parameter acts on a region — and returns how to assign new values. A law's constants are
found by rebuilding it at the new values (``law_at(keys)``, with ``keys`` the values of the
material targets by key: ``{"E": 2e3}`` for a parameter on ``material.E``) and reading its
numbers, so derived constants (μ and λ from E and ν) and the law's own checks come for free. The other targets
are :func:`formulation` constants, :func:`loads` (value, amplitude, posture) and
:func:`constraints` amplitudes; the model applies what they return.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
import ufl
from dolfinx import fem
from ufl.core.expr import Expr

from lungmech.errors import ParameterError
from lungmech.fem.loads import is_pressure
from lungmech.fem.materials import Material, numbers_of, with_values
from lungmech.fem.parameters import ANGLES, LOAD_ATTRIBUTES, HalfSpace, Parameter, Parameters

if TYPE_CHECKING:
    from lungmech.fem.constraints import Displacement
    from lungmech.fem.formulations import Formulation
    from lungmech.fem.loads import Load
    from lungmech.mesh.geometry import Geometry

LawAt = Callable[[Mapping[str, float]], Material]
Assign = Callable[[Mapping[str, float]], None]


def law_function(material: Material | LawAt, parameters: Parameters) -> LawAt:
    """``material`` as a function of its targets' values by key: itself if it is one, else the law
    with the constants those keys name replaced (``key`` a path of
    :func:`~lungmech.fem.materials.numbers_of`, or its last part when that is unambiguous)."""
    if callable(material) and not isinstance(material, Material):
        return material
    paths = list(numbers_of(material))
    targets = {p.key: _path(p, paths) for p in parameters if p.kind == "material"}
    return lambda keys: with_values(material, {targets[key]: v for key, v in keys.items()})


def _path(parameter: Parameter, paths: list[str]) -> str:
    matches = [path for path in paths if path == parameter.key or path.endswith("." + parameter.key)]
    if len(matches) != 1:
        found = "several: " + ", ".join(matches) if matches else "none"
        raise ParameterError(
            f"parameter '{parameter.name}': target {parameter.target} must name one constant of the law "
            f"({found}; the law has {', '.join(paths)})"
        )
    return matches[0]


def material(
    law_at: LawAt,
    parameters: Parameters,
    geometry: Geometry,
    interfaces: Mapping[str, fem.Constant],
    shape: Expr | None = None,
) -> tuple[Material, Assign]:
    """The law the forms use, and ``assign(values)`` that sets its constants for new values.
    ``shape``: the template map's displacement (regions by position move with it), or None."""
    mesh = geometry.mesh
    values = parameters.defaults
    base = law_at(outside_keys(parameters, values))
    finite = {path: v for path, v in numbers_of(base).items() if abs(v) != float("inf")}
    constants = {path: fem.Constant(mesh, v) for path, v in finite.items()}
    regions = _regions(parameters)
    fields = dict(constants)
    region_constants = []
    for region, members in regions.items():
        moved = _affected(law_at, parameters, members, finite)
        names = ", ".join(f"'{p.name}'" for p in members)
        if not moved:
            raise ParameterError(
                f"parameters {names} change no constant of the law on their region: they act on nothing"
            )
        if isinstance(region, HalfSpace):
            _holds_cells(region, geometry, parameters, names)
        chi = region.indicator(
            geometry, interfaces, None if shape is None else ufl.SpatialCoordinate(geometry.mesh) + shape
        )
        inside = {path: fem.Constant(mesh, finite[path]) for path in moved}
        for path, c in inside.items():
            fields[path] = fields[path] + chi * (c - constants[path])
        region_constants.append((members, inside))

    def assign(values: Mapping[str, float]) -> None:
        outside = outside_keys(parameters, values)
        _set(constants, law_at(outside), parameters)
        for members, inside in region_constants:
            _set(inside, law_at(outside | {p.key: values[p.name] for p in members}), parameters)

    assign(values)
    return with_values(base, fields), assign


def _holds_cells(region: HalfSpace, geometry: Geometry, parameters: Parameters, names: str) -> None:
    """Refuse a half-space that holds no cell at any position it can take (its own, or the ends
    and default of the interface parameter that moves it): its parameters would act nowhere.
    (A cell region without cells is refused by its indicator.)"""
    positions: tuple[float, ...]
    if isinstance(region.position, str):
        mover = parameters.named(region.position)
        positions = (mover.range[0], mover.default, mover.range[1])
    else:
        positions = (region.position,)
    if not any(region.cells_behind(geometry, s) for s in positions):
        n = ", ".join(f"{c:g}" for c in region.normal)
        at = " to ".join(dict.fromkeys(f"{s:g}" for s in (min(positions), max(positions))))
        raise ParameterError(
            f"parameters {names}: their half-space region (n·x < s, n = ({n}), s = {at} m) holds no cell of the "
            "mesh, so they would act nowhere: check its normal and position against the mesh's coordinates"
        )


def outside_keys(parameters: Parameters, values: Mapping[str, float]) -> dict[str, float]:
    """The material targets' values by key outside every region: a global parameter's value, else
    the value a regional parameter's target keeps outside its region."""
    material = [p for p in parameters if p.kind == "material"]
    keys = {p.key: p.outside if p.outside is not None else p.default for p in material if p.region is not None}
    return keys | {p.key: values[p.name] for p in material if p.region is None}


def _regions(parameters: Parameters) -> dict:
    groups: dict = {}
    for p in parameters:
        if p.region is not None:
            groups.setdefault(p.region, []).append(p)
    return groups


def _affected(law_at: LawAt, parameters: Parameters, members: list[Parameter], base: dict[str, float]) -> list[str]:
    """The law's constants that the region's parameters change (tried at both ends of their ranges)."""
    outside = outside_keys(parameters, parameters.defaults)
    moved = set()
    for end in (0, 1):
        law = law_at(outside | {p.key: p.range[end] for p in members})
        moved |= {path for path, v in numbers_of(law).items() if path in base and v != base[path]}
    return sorted(moved)


def _set(constants: Mapping[str, fem.Constant], law: Material, parameters: Parameters) -> None:
    numbers = numbers_of(law)
    for path, constant in constants.items():
        if path not in numbers or abs(numbers[path]) == float("inf"):
            names = ", ".join(p.name for p in parameters if p.kind == "material")
            raise ParameterError(
                f"parameters {names} change the form of the law (its constant {path}), not only its values"
            )
        constant.value = np.asarray(numbers[path])


def loads(
    base: Sequence[Load], parameters: Parameters
) -> Callable[[Mapping[str, float]], tuple[tuple[Load, ...], np.ndarray]]:
    """``at(values) -> (loads, amplitudes)``: the model's loads with the values and postures the
    ``loads.<name>.<attribute>`` parameters set, and a factor per load (its amplitude)."""
    named = {load.name: i for i, load in enumerate(base) if load.name}
    acting = [p for p in parameters if p.kind == "loads"]
    for p in acting:
        name, _, attribute = p.key.rpartition(".")
        if name not in named:
            known = ", ".join(named) or "none: give loads a name"
            raise ParameterError(f"parameter '{p.name}': no load named '{name}' (named loads: {known})")
        load = base[named[name]]
        if attribute not in LOAD_ATTRIBUTES:
            raise ParameterError(f"parameter '{p.name}': a load's target is one of {', '.join(LOAD_ATTRIBUTES)}")
        if attribute == "value" and not is_pressure(load):
            raise ParameterError(
                f"parameter '{p.name}': load '{name}' has a vector value or a formula; use {name}.amplitude"
            )
        if attribute in ANGLES and not hasattr(load, "acceleration"):
            raise ParameterError(f"parameter '{p.name}': only gravity has a posture ({attribute})")
        components = len(getattr(load, "acceleration", ()))
        if attribute in ANGLES and (attribute == "angle") != (components == 2):
            raise ParameterError(
                f"parameter '{p.name}': {attribute} turns a {'plane' if attribute == 'angle' else '3-D'} problem's "
                f"gravity, and load '{name}' has {components} components; "
                + ("use pitch and roll in 3-D" if attribute == "angle" else "use angle in a plane problem")
            )

    def at(values: Mapping[str, float]) -> tuple[tuple[Load, ...], np.ndarray]:
        current, amplitudes = list(base), np.ones(len(base))
        for p in acting:
            name, _, attribute = p.key.rpartition(".")
            i = named[name]
            if attribute == "value":
                current[i] = dataclasses.replace(current[i], value=values[p.name])
            elif attribute == "amplitude":
                amplitudes[i] = values[p.name]
        for i, load in enumerate(base):
            angles = {a: values[p.name] for p in acting for a in ANGLES if p.key == f"{load.name}.{a}"}
            if angles:
                assert hasattr(load, "acceleration")  # checked above: only gravity has a posture
                turn = (
                    in_plane(angles["angle"])
                    if "angle" in angles
                    else posture(angles.get("pitch", 0.0), angles.get("roll", 0.0))
                )
                turned = turn @ np.asarray(load.acceleration)
                current[i] = dataclasses.replace(current[i], acceleration=tuple(turned))
        return tuple(current), amplitudes

    return at


def constraints(base: Sequence[Displacement], parameters: Parameters) -> Callable[[Mapping[str, float]], np.ndarray]:
    """``amplitudes(values)``: a factor per imposed displacement, set by ``constraints.<name>.amplitude``."""
    named = {c.name: i for i, c in enumerate(base) if c.name}
    acting = [p for p in parameters if p.kind == "constraints"]
    for p in acting:
        name, _, attribute = p.key.rpartition(".")
        if name not in named or attribute != "amplitude":
            known = ", ".join(named) or "none: give constraints a name"
            raise ParameterError(
                f"parameter '{p.name}': target must be constraints.<name>.amplitude (named constraints: {known})"
            )

    def amplitudes(values: Mapping[str, float]) -> np.ndarray:
        factors = np.ones(len(base))
        for p in acting:
            factors[named[p.key.rpartition(".")[0]]] = values[p.name]
        return factors

    return amplitudes


def posture(pitch: float, roll: float) -> np.ndarray:
    """The rotation R = R_y(roll) R_x(pitch) that turns gravity from the scene's posture (angles in
    degrees; x: the patient's right, y: anterior, z: superior). From upright, g = (0, 0, −g):
    pitch = −90° gives g along −y (supine, lying on the back), +90° prone; roll = +90° gives g along
    −x (lying on the left side), −90° on the right side."""
    a, b = np.radians(pitch), np.radians(roll)
    about_x = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    about_y = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    return about_y @ about_x


def in_plane(angle: float) -> np.ndarray:
    """The rotation of a plane problem's gravity by ``angle`` degrees, counter-clockwise about
    the out-of-plane axis: g = (0, −g) turns to g (sin θ, −cos θ)."""
    a = np.radians(angle)
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


def formulation(unbound: Formulation, bound: Formulation, parameters: Parameters) -> Assign:
    """How formulation parameters set the bound formulation's constants (checked by rebuilding the
    formulation at the new values, so its own checks apply)."""
    acting = {p.name: p.key for p in parameters if p.kind == "formulation"}
    for name, key in acting.items():
        target = getattr(bound, key, None)
        if isinstance(target, int | float) and target == 0:
            raise ParameterError(
                f"parameter '{name}': formulation.{key} is 0 in the scene, which leaves its term out of the forms; "
                "give it a positive value there to make it a parameter"
            )
        if not isinstance(target, fem.Constant | fem.Function) or isinstance(getattr(unbound, key), str | Callable):
            raise ParameterError(
                f"parameter '{name}': formulation.{key} is not a number of the {type(unbound).__name__} formulation "
                "(a constant given per cell by a file or a function cannot be one parameter)"
            )

    def assign(values: Mapping[str, float]) -> None:
        if not acting:
            return
        dataclasses.replace(unbound, **{key: values[name] for name, key in acting.items()})  # its checks
        for name, key in acting.items():
            target = getattr(bound, key)
            if isinstance(target, fem.Function):
                target.x.array[:] = values[name]
            else:
                target.value = values[name]

    return assign
