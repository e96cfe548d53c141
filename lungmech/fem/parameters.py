"""Named parameters μ of a model: what they act on, their ranges, and the box they span.

A :class:`Parameter` is a named scalar with a default, a range [low, high] and a sampling scale
(linear or log). Its ``target`` says what it acts on:

========================================  ====================================================
``material.<key>``                        a constant of the law (``mu``, ``c1``, ``E``, …)
``formulation.<field>``                   a constant of the formulation (``kappa``, ``phi_s0``, …)
``loads.<name>.value``                    the value of the scalar load named ``name`` (Pa)
``loads.<name>.amplitude``                a factor on that load's value (any load)
``loads.<name>.pitch`` / ``.roll``        the posture: gravity turned about x / y (degrees)
``loads.<name>.angle``                    a plane problem's gravity turned in its plane,
                                          counter-clockwise (degrees)
``constraints.<name>.amplitude``          a factor on an imposed displacement
``interface``                             the position (m) of a :class:`HalfSpace` region
``shape.mode_<i>``                        the coefficient aᵢ of the i-th shape mode (1, 2, …;
                                          :mod:`lungmech.fem.shape`): the body's shape
========================================  ====================================================

A material parameter may act on a :attr:`Parameter.region` only — a set of cells (:class:`Cells`:
a cell tag, or any marker such as the labels of an image) or a half-space with a smooth boundary
(:class:`HalfSpace`) whose position may itself be a parameter. In the region the law takes the
parameter's value, elsewhere the value ``outside``; the field is c(x) = c_out + χ(x) (c_in −
c_out), with χ the region's indicator, so that outputs stay differentiable in μ.

Every value reaches the forms through ``fem.Constant`` objects, so changing μ recompiles nothing
(:meth:`lungmech.fem.model.Model.set_parameters`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, overload

import numpy as np
import ufl

from lungmech import checks
from lungmech.errors import ParameterError

if TYPE_CHECKING:
    from lungmech.mesh.geometry import Geometry

__all__ = ["Cells", "HalfSpace", "Parameter", "Parameters", "Region"]

KINDS = ("material", "formulation", "loads", "constraints", "interface", "shape")
LOAD_ATTRIBUTES = ("value", "amplitude", "pitch", "roll", "angle")
ANGLES = ("pitch", "roll", "angle")  # the load attributes that turn gravity (degrees)


@dataclass(frozen=True)
class Cells:
    """A region made of whole cells: those tagged ``tag`` in the geometry's cell tags, or those
    a ``marker(geometry) -> bool array`` (one per local cell, ghosts included) selects — the
    labels of an image, say. ``label`` names it in messages."""

    tag: int | None = None
    marker: Callable | None = field(default=None, compare=False)
    label: str = ""

    def __post_init__(self) -> None:
        if (self.tag is None) == (self.marker is None):
            raise ParameterError("a cell region needs exactly one of a cell tag or a marker")
        if self.tag is not None:
            checks.integer("region tag", self.tag)

    def describe(self) -> dict:
        return {"cells": self.tag if self.tag is not None else self.label}

    def indicator(
        self, geometry: Geometry, constants: Mapping[str, object], position: ufl.core.expr.Expr | None = None
    ) -> ufl.core.expr.Expr:
        """χ as a DG0 field: 1 on the region's cells, 0 elsewhere (cells move with the mesh:
        ``position`` is not needed)."""
        from dolfinx import fem

        mesh = geometry.mesh
        space = fem.functionspace(mesh, ("DG", 0))
        chi = fem.Function(space, name=f"region {self.label or self.tag}")
        cells = mesh.topology.index_map(mesh.topology.dim)
        local = cells.size_local + cells.num_ghosts
        if self.marker is not None:
            inside = np.asarray(self.marker(geometry), dtype=bool)
            if inside.shape != (local,):
                raise ParameterError(f"region {self.label!r}: the marker gave {inside.shape} values for {local} cells")
        else:
            if geometry.cell_tags is None:
                raise ParameterError(f"region: cell tag {self.tag} asked for, but the mesh has no cell tags")
            inside = np.zeros(local, dtype=bool)
            inside[geometry.cell_tags.find(self.tag)] = True
        chi.x.array[np.asarray(space.dofmap.list)[:, 0]] = inside  # one DG0 dof per cell
        if not mesh.comm.allreduce(int(inside[: cells.size_local].sum())):
            raise ParameterError(f"region {self.label or self.tag}: no cell of the mesh lies in it")
        return chi


@dataclass(frozen=True)
class HalfSpace:
    """The cells behind a plane, with a smooth edge: χ(x) = ½(1 − tanh((n·x − s)/w)).

    ``normal`` n (normalised here), ``position`` s (m: a number, or the name of an
    ``interface`` parameter that moves the plane), ``width`` w (m) of the transition. χ ≈ 1
    where n·x < s, e.g. below a height s for n = (0, 0, 1).
    """

    normal: Sequence[float]
    position: float | str
    width: float

    def __post_init__(self) -> None:
        n = checks.vector("region normal", self.normal)
        if not np.linalg.norm(n) > 0:
            raise ParameterError("region normal must not be zero")
        object.__setattr__(self, "normal", tuple(float(c) for c in np.asarray(n) / np.linalg.norm(n)))
        if not isinstance(self.position, str):
            object.__setattr__(self, "position", float(checks.real("region position", self.position)))
        checks.real("region width", self.width, positive=True)

    def describe(self) -> dict:
        return {"normal": list(self.normal), "position": self.position, "width": self.width}

    def cells_behind(self, geometry: Geometry, position: float) -> int:
        """Collective: the number of cells whose midpoint lies behind the plane at ``position``
        (n·x < s, where χ > ½)."""
        mesh = geometry.mesh
        owned = mesh.topology.index_map(mesh.topology.dim).size_local
        midpoints = mesh.geometry.x[mesh.geometry.dofmaps[0][:owned]].mean(axis=1)
        n = np.zeros(3)
        n[: len(self.normal)] = self.normal
        return mesh.comm.allreduce(int(np.count_nonzero(midpoints @ n < position)))

    def indicator(
        self, geometry: Geometry, constants: Mapping[str, object], position: ufl.core.expr.Expr | None = None
    ) -> ufl.core.expr.Expr:
        """χ = ½(1 − tanh((n·x − s)/w)) at the mesh's points x, or at ``position`` (the body's
        points on a template mesh moved by its shape map)."""
        x = ufl.SpatialCoordinate(geometry.mesh) if position is None else position
        n = ufl.as_vector(self.normal)
        s = constants[self.position] if isinstance(self.position, str) else self.position
        return 0.5 * (1 - ufl.tanh((ufl.dot(n, x) - s) / self.width))


Region = Cells | HalfSpace


@dataclass(frozen=True)
class Parameter:
    """A named scalar μ: its ``target`` (see the module's table), ``default``, ``range`` =
    (low, high), sampling scale (``log``: samples spread evenly in log μ; needs low > 0), the
    ``unit`` it is given in, and for a material target an optional ``region`` with the value
    the target keeps ``outside`` it (default: the parameter's default)."""

    name: str
    target: str
    default: float
    range: tuple[float, float]
    log: bool = False
    unit: str = ""
    region: Region | None = None
    outside: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.isidentifier():
            raise ParameterError(f"parameter name must be a word of letters, digits and _ (got {self.name!r})")
        if not isinstance(self.target, str) or self.target.split(".")[0] not in KINDS:
            raise ParameterError(
                f"parameter '{self.name}': target must start with one of {', '.join(KINDS)} (got {self.target!r})"
            )
        if isinstance(self.range, str) or not isinstance(self.range, Sequence) or len(self.range) != 2:
            raise ParameterError(f"parameter '{self.name}': range must be [low, high] (got {self.range!r})")
        low = checks.real(f"parameter '{self.name}': range[0]", self.range[0])
        high = checks.real(f"parameter '{self.name}': range[1]", self.range[1])
        if not low < high:
            raise ParameterError(f"parameter '{self.name}': range must have low < high (got [{low:g}, {high:g}])")
        object.__setattr__(self, "range", (float(low), float(high)))
        checks.boolean(f"parameter '{self.name}': log", self.log)
        if self.log and not low > 0:
            raise ParameterError(
                f"parameter '{self.name}': a log scale needs a positive range (got [{low:g}, {high:g}])"
            )
        object.__setattr__(self, "default", float(checks.real(f"parameter '{self.name}': default", self.default)))
        self.check(self.default, "default")
        if self.region is not None and self.kind != "material":
            raise ParameterError(f"parameter '{self.name}': only material parameters act on a region")
        if self.outside is not None:
            object.__setattr__(self, "outside", float(checks.real(f"parameter '{self.name}': outside", self.outside)))

    @property
    def kind(self) -> str:
        """What it acts on: material, formulation, loads, constraints, interface or shape."""
        return self.target.split(".")[0]

    @property
    def key(self) -> str:
        """The target without its kind: ``c1`` of ``material.c1``, ``pleural.value`` of ``loads.pleural.value``."""
        return self.target.partition(".")[2]

    def check(self, value: float, what: str = "value") -> float:
        """``value`` if it lies in the range, else a ParameterError that gives the range."""
        low, high = self.range
        if not (isinstance(value, int | float | np.floating) and not isinstance(value, bool) and math.isfinite(value)):
            raise ParameterError(f"parameter '{self.name}': {what} must be a finite number (got {value!r})")
        if not low <= value <= high:
            unit = f" {self.unit}" if self.unit and self.unit != "1" else ""
            raise ParameterError(
                f"parameter '{self.name}' = {value:g}{unit} is outside its range [{low:g}, {high:g}]{unit}"
            )
        return float(value)

    def to_unit(self, value: float) -> float:
        """θ ∈ [0, 1] of ``value``: (μ − low)/(high − low), or in log μ on a log scale."""
        low, high = self.range
        if self.log:
            return (math.log(value) - math.log(low)) / (math.log(high) - math.log(low))
        return (value - low) / (high - low)

    def from_unit(self, u: float) -> float:
        """The value at θ = ``u`` (the inverse of :meth:`to_unit`), kept inside the range."""
        low, high = self.range
        if self.log:
            return float(min(max(math.exp(math.log(low) + u * (math.log(high) - math.log(low))), low), high))
        return float(min(max(low + u * (high - low), low), high))

    def unit_derivative(self, value: float) -> float:
        """∂μ/∂θ at ``value``: high − low, or μ ln(high/low) on a log scale."""
        low, high = self.range
        return value * math.log(high / low) if self.log else high - low

    def describe(self) -> dict:
        """Plain values: what the parameter is and acts on (part of a reduced model's fingerprint)."""
        described = {
            "name": self.name,
            "target": self.target,
            "default": self.default,
            "range": list(self.range),
            "log": self.log,
            "unit": self.unit,
        }
        if self.region is not None:
            described["region"] = self.region.describe()
            described["outside"] = self.outside if self.outside is not None else self.default
        return described


class Parameters(Sequence[Parameter]):
    """The parameters of a model, in order: the box they span, checks and space-filling samples."""

    def __init__(self, parameters: Sequence[Parameter] = ()) -> None:
        self._items = tuple(parameters)
        for p in self._items:
            if not isinstance(p, Parameter):
                raise ParameterError(f"parameters must be Parameter objects (got {p!r})")
        names = [p.name for p in self._items]
        if len(set(names)) != len(names):
            repeated = sorted({n for n in names if names.count(n) > 1})
            raise ParameterError(f"parameter names must differ (repeated: {', '.join(repeated)})")
        self._by_name = {p.name: p for p in self._items}
        moved = set()
        for p in self._items:
            position = getattr(p.region, "position", None)
            if isinstance(position, str):
                mover = self._by_name.get(position)
                if mover is None or mover.kind != "interface":
                    raise ParameterError(
                        f"parameter '{p.name}': its region's position names '{position}', which is not an "
                        "'interface' parameter of this model"
                    )
                moved.add(position)
        for p in self._items:
            if p.kind == "interface" and p.name not in moved:
                raise ParameterError(
                    f"parameter '{p.name}' moves an interface that no region's position names: it would act on "
                    f"nothing (give a region position = '{p.name}', or leave it out)"
                )
        for target in dict.fromkeys(p.target for p in self._items if p.kind != "interface"):
            _one_owner([p for p in self._items if p.target == target])

    @overload
    def __getitem__(self, index: int) -> Parameter: ...

    @overload
    def __getitem__(self, index: slice) -> tuple[Parameter, ...]: ...

    def __getitem__(self, index: int | slice) -> Parameter | tuple[Parameter, ...]:
        return self._items[index]

    def __len__(self) -> int:
        return len(self._items)

    def __iter__(self) -> Iterator[Parameter]:
        return iter(self._items)

    def __contains__(self, name: object) -> bool:
        return name in self._by_name

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._by_name)

    def named(self, name: str) -> Parameter:
        try:
            return self._by_name[name]
        except KeyError:
            known = ", ".join(self._by_name) or "none"
            raise ParameterError(f"unknown parameter '{name}' (this model's parameters: {known})") from None

    @property
    def defaults(self) -> dict[str, float]:
        return {p.name: p.default for p in self._items}

    def values(
        self, given: Mapping[str, float] | None = None, start: Mapping[str, float] | None = None
    ) -> dict[str, float]:
        """Every parameter's value: ``given`` ones checked against their ranges, the others from
        ``start`` (default: the defaults). Unknown names are refused."""
        given = dict(given or {})
        for name in given:
            self.named(name)
        base = self.defaults | dict(start or {})
        return {p.name: p.check(given[p.name]) if p.name in given else base[p.name] for p in self._items}

    def text(self, values: Mapping[str, float]) -> str:
        """``values`` for a person: "c1 = 250 Pa, breath = 1.2" (the defaults: "the defaults")."""
        parts = []
        for name, value in values.items():
            unit = self.named(name).unit
            parts.append(f"{name} = {value:.4g}" + (f" {unit}" if unit and unit != "1" else ""))
        return ", ".join(parts) if parts and values != self.defaults else "the defaults"

    def to_unit(self, values: Mapping[str, float]) -> np.ndarray:
        """Coordinates in the unit box [0, 1]^n (log parameters in log μ)."""
        return np.array([p.to_unit(values[p.name]) for p in self._items])

    def from_unit(self, unit: np.ndarray) -> dict[str, float]:
        """Values from coordinates in the unit box (the inverse of :meth:`to_unit`)."""
        return {p.name: p.from_unit(float(u)) for p, u in zip(self._items, np.asarray(unit, dtype=float))}

    def sample(self, count: int, seed: int = 0) -> list[dict[str, float]]:
        """``count`` points spread over the box: the first ``count`` of a scrambled Sobol' sequence
        of 2^m ≥ count points (``scipy.stats.qmc``), seeded so that the same call gives the same
        points; log parameters spread in log μ."""
        from scipy.stats import qmc

        checks.integer("sample count", count, minimum=1)
        if not self._items:
            return [{} for _ in range(count)]
        sobol = qmc.Sobol(d=len(self._items), scramble=True, seed=seed)
        points = sobol.random_base2(max(0, math.ceil(math.log2(count))))[:count]
        return [self.from_unit(u) for u in points]

    def describe(self) -> list[dict]:
        return [p.describe() for p in self._items]


def _one_owner(sharing: list[Parameter]) -> None:
    """Refuse parameters on one target that would not all act: two on it everywhere (the last
    would win), two on one region, or values outside the regions that disagree.

    By design a material target may have one global parameter and regional ones (a fibrotic
    zone's stiffness beside the lung's): the global one is then the value outside the regions,
    and a regional ``outside`` would be ignored, so it is refused. Without a global one, every
    regional parameter's outside value (its ``outside``, else its default) must be the same."""
    everywhere = [p for p in sharing if p.region is None]
    regional = [p for p in sharing if p.region is not None]
    target = sharing[0].target
    if len(everywhere) > 1:  # (only material parameters have regions)
        names = " and ".join(f"'{p.name}'" for p in everywhere)
        raise ParameterError(f"parameters {names} all set {target}: only the last would act; keep one")
    for i, p in enumerate(regional):
        if same := [q.name for q in regional[:i] if q.region == p.region]:
            raise ParameterError(f"parameters '{same[0]}' and '{p.name}' set {target} on the same region; keep one")
    if everywhere:
        if given := [p.name for p in regional if p.outside is not None]:
            raise ParameterError(
                f"parameter '{given[0]}': its value outside the region would be ignored: parameter "
                f"'{everywhere[0].name}' sets {target} there (leave out 'outside')"
            )
    elif len({p.outside if p.outside is not None else p.default for p in regional}) > 1:
        names = ", ".join(f"'{p.name}'" for p in regional)
        raise ParameterError(
            f"parameters {names} set {target} on regions, with different values outside them: give them "
            "the same 'outside', or a parameter of their own for the value outside"
        )
