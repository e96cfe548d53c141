"""The values a model's parameters set, in closed form, for a PGD model's answers without
setting the fem model's parameters (the bulk of an answer's time).

A value v(μ) — a law's constant, a load's value as applied — is written as a sum over the axes
it moves with, each term in a small basis of that parameter:

    v(μ) = v₀ + Σⱼ aⱼ · fⱼ(μⱼ),   fⱼ = (μⱼ) for a quantity, (cos μⱼ, sin μⱼ) for an angle (degrees),

fitted on each axis's nodes (the others at their defaults) and then **checked** at random points
of the whole box against the model's own assignment, each value to 1e-10 of its size over the
axes' nodes. Where that
check fails, a value may be a product of two parameters (gravity under pitch and roll: cos p
sin r): each pair of axes adds Bⱼₗ (Δfⱼ ⊗ Δfₗ), Δf = f(μ) − f(default), fitted on a 4 × 4
grid of the two axes (zero where either is at its default, so the single axes' fit stands),
and the whole is checked again. Where it still fails — a function outside the basis (a Lamé
constant of a Poisson ratio) — there is no closed form, and the caller sets the fem model's
parameters instead.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from lungmech.fem.model import Model
from lungmech.fem.parameters import ANGLES, Parameter
from lungmech.pgd.axes import Axis

__all__ = ["ClosedForm", "closed_form", "joined"]

CHECK = 1e-10  # the largest mismatch at the check's points, relative to the values' size


def _is_angle(parameter: Parameter) -> bool:
    """Whether ``parameter`` is an angle (degrees), whose basis is (cos μ, sin μ)."""
    return parameter.target.rsplit(".", 1)[-1] in ANGLES


def _basis(angle: bool, mu: float) -> list[float]:
    """fⱼ(μ): (μ) for a quantity, (cos μ, sin μ) for an ``angle`` in degrees."""
    if angle:
        radians = math.radians(mu)
        return [math.cos(radians), math.sin(radians)]
    return [mu]


@dataclass(frozen=True)
class ClosedForm:
    """v(μ) = ``base`` + Σⱼ ``coefficients[j]`` fⱼ(μⱼ) (values × basis size) + Σ over ``pairs``
    (j, l, Bⱼₗ) Bⱼₗ (Δfⱼ ⊗ Δfₗ) (values × the two bases' sizes' product), over ``axes``;
    ``origin[j]`` fⱼ at the default."""

    axes: tuple[Axis, ...]
    base: np.ndarray
    coefficients: tuple[np.ndarray, ...]
    origin: tuple[np.ndarray, ...] = ()
    pairs: tuple[tuple[int, int, np.ndarray], ...] = ()

    @functools.cached_property
    def _stacked(self) -> np.ndarray:
        """Every axis's coefficients side by side (values × all bases): one product a point."""
        return np.hstack(self.coefficients) if self.coefficients else np.zeros((len(self.base), 0))

    @functools.cached_property
    def _readers(self) -> tuple[tuple[str, bool], ...]:
        """Each axis's parameter name and whether it is an angle."""
        return tuple((axis.parameter.name, _is_angle(axis.parameter)) for axis in self.axes)

    @functools.cached_property
    def _slices(self) -> tuple[slice, ...]:
        """Each axis's basis in the stacked f."""
        ends = np.cumsum([0] + [2 if angle else 1 for _, angle in self._readers])
        return tuple(slice(int(a), int(b)) for a, b in zip(ends[:-1], ends[1:]))

    def __call__(self, mu: Mapping[str, float]) -> np.ndarray:
        f: list[float] = []
        for name, angle in self._readers:
            f += _basis(angle, float(mu[name]))
        stacked = np.array(f)
        found = self.base + self._stacked @ stacked
        for j, l, B in self.pairs:
            fj, fl = (stacked[self._slices[i]] - self.origin[i] for i in (j, l))
            found += B @ (fj[:, None] * fl).ravel()
        return found


def joined(forms: Sequence[ClosedForm]) -> tuple[ClosedForm, list[int]]:
    """One :class:`ClosedForm` whose values are ``forms``' stacked (one evaluation of the bases
    for them all: the bulk of a closed form's time is its call's), and where each form's values
    end in them. The forms share their axes; a pair one lacks is zero in its rows."""
    axes = forms[0].axes
    origin = next((form.origin for form in forms if form.origin), ())
    base = np.concatenate([form.base for form in forms])
    coefficients = tuple(np.vstack([form.coefficients[j] for form in forms]) for j in range(len(axes)))
    keys = sorted({(j, l) for form in forms for j, l, _ in form.pairs})
    pairs = []
    for j, l in keys:
        width = (2 if _is_angle(axes[j].parameter) else 1) * (2 if _is_angle(axes[l].parameter) else 1)
        own = [{(a, b): B for a, b, B in form.pairs}.get((j, l), np.zeros((len(form.base), width))) for form in forms]
        pairs.append((j, l, np.vstack(own)))
    ends = np.cumsum([len(form.base) for form in forms]).tolist()
    return ClosedForm(axes, base, coefficients, origin, tuple(pairs)), ends


def closed_form(model: Model, axes: tuple[Axis, ...], read: Callable[[], np.ndarray]) -> ClosedForm | None:
    """The :class:`ClosedForm` of the values ``read()`` gives after ``model.set_parameters``
    (module docstring), or None where none holds. The model's parameters are left as they were."""
    kept = dict(model.parameter_values)
    defaults = model.parameters.defaults
    try:
        model.set_parameters(defaults)
        at_defaults = np.asarray(read(), dtype=float)
        if not at_defaults.size:  # no value (no shape map, no load-only value): nothing to fit or check
            return ClosedForm(
                tuple(axes), at_defaults, tuple(np.zeros((0, len(_basis(_is_angle(a.parameter), 0.0)))) for a in axes)
            )
        base, coefficients, sizes = at_defaults.copy(), [], np.abs(at_defaults)
        origin = tuple(np.array(_basis(_is_angle(a.parameter), defaults[a.parameter.name])) for a in axes)
        for axis, f0 in zip(axes, origin):
            parameter = axis.parameter
            rows, found = [], []
            for mu in axis.values:
                model.set_parameters(defaults | {parameter.name: float(mu)})
                rows.append(np.subtract(_basis(_is_angle(parameter), float(mu)), f0))
                found.append(np.asarray(read(), dtype=float) - at_defaults)
            sizes = np.maximum(
                sizes, np.abs(np.array(found) + at_defaults).max(axis=0)
            )  # (a shape's a: 0 at the defaults)
            a = np.linalg.lstsq(np.array(rows), np.array(found), rcond=None)[0].T  # values × basis
            base -= a @ f0
            coefficients.append(a)
        form = ClosedForm(tuple(axes), base, tuple(coefficients), origin)
        sizes = np.maximum(sizes, np.finfo(float).tiny)  # each value's size over the axes' nodes
        if _holds(model, form, read, sizes):
            return form
        form = replace(form, pairs=_pairs(model, form, read, sizes))
        return form if _holds(model, form, read, sizes) else None
    finally:
        model.set_parameters(kept)


def _pairs(
    model: Model, form: ClosedForm, read: Callable[[], np.ndarray], sizes: np.ndarray
) -> tuple[tuple[int, int, np.ndarray], ...]:
    """Each pair of axes' Bⱼₗ, fitted to what the single axes leave on a 4 × 4 grid of theirs
    (a pair whose values do not mix, below :data:`CHECK` of each value's size: none)."""
    defaults, axes, found = model.parameters.defaults, form.axes, []
    for j, l in itertools.combinations(range(len(axes)), 2):
        rows, left = [], []
        for a in _four(axes[j]):
            for b in _four(axes[l]):
                point = defaults | {axes[j].parameter.name: a, axes[l].parameter.name: b}
                model.set_parameters(point)
                left.append(np.asarray(read(), dtype=float) - form(point))
                fj, fl = (
                    np.array(_basis(_is_angle(axes[i].parameter), v)) - form.origin[i] for i, v in ((j, a), (l, b))
                )
                rows.append(np.outer(fj, fl).ravel())
        B = np.linalg.lstsq(np.array(rows), np.array(left), rcond=None)[0].T
        if np.any(np.abs(np.array(rows) @ B.T) > CHECK * sizes):  # what it adds on the grid
            found.append((j, l, B))
    return tuple(found)


def _four(axis: Axis) -> np.ndarray:
    """Four of an axis's nodes, its ends among them."""
    values = np.asarray(axis.values)
    return values[np.unique(np.linspace(0, len(values) - 1, 4).round().astype(int))]


def _holds(model: Model, form: ClosedForm, read: Callable[[], np.ndarray], sizes: np.ndarray) -> bool:
    """Whether ``form`` is the model's own assignment at 8 random points, each value to
    :data:`CHECK` of its size ``sizes``."""
    for point in model.parameters.sample(8, seed=23):
        model.set_parameters(point)
        found = np.asarray(read(), dtype=float)
        if np.any(
            np.abs(form(point) - found) > CHECK * np.maximum(sizes, np.abs(found))
        ):  # (a pair's product: 0 on the axes)
            return False
    return True
