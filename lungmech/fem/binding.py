"""How a model's parameters reach its forms: every value a parameter sets lives in a ``fem.Constant``.

:func:`material` turns a law (or a function of the parameter values that returns one) into the
law the forms use — each numeric constant a ``fem.Constant``, or c_out + χ (c_in − c_out) where
a parameter acts on a region — and returns how to assign new values. A law's constants are
found by rebuilding it at the new values (``law_at(keys)``, with ``keys`` the values of the
material targets by key: ``{"E": 2e3}`` for a parameter on ``material.E``) and reading its
numbers, so derived constants (μ and λ from E and ν) and the law's own checks come for free. The other targets
(formulation constants, loads, imposed displacements, interfaces) are assigned by the model.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from dolfinx import fem

from lungmech.errors import ParameterError
from lungmech.fem.materials import Material, numbers_of, with_values
from lungmech.fem.parameters import Parameter, Parameters

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
    law_at: LawAt, parameters: Parameters, geometry, interfaces: Mapping[str, fem.Constant]
) -> tuple[Material, Assign]:
    """The law the forms use, and ``assign(values)`` that sets its constants for new values."""
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
        if not moved:
            continue
        chi = region.indicator(geometry, interfaces)
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
        constant.value = numbers[path]
