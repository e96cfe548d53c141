"""The values a model's parameters set, in closed form, for a PGD model's answers without
setting the fem model's parameters (the bulk of an answer's time).

A value v(μ) — a law's constant, a load's value as applied — is written as a sum over the axes
it moves with, each term in a small basis of that parameter:

    v(μ) = v₀ + Σⱼ aⱼ · fⱼ(μⱼ),   fⱼ = (μⱼ) for a quantity, (cos μⱼ, sin μⱼ) for an angle (degrees),

fitted on each axis's nodes (the others at their defaults) and then **checked** at random points
of the whole box against the model's own assignment, to 1e-10 of the values' size. Where the
check fails — a value of a product of two parameters (gravity under pitch and roll), or of a
function outside the basis (a Lamé constant of a Poisson ratio) — there is no closed form, and
the caller sets the fem model's parameters instead.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from lungmech.fem.model import Model
from lungmech.fem.parameters import ANGLES, Parameter
from lungmech.pgd.axes import Axis

__all__ = ["ClosedForm", "closed_form"]

CHECK = 1e-10  # the largest mismatch at the check's points, relative to the values' size


def _basis(parameter: Parameter, mu: float) -> list[float]:
    """fⱼ(μ): (μ) for a quantity, (cos μ, sin μ) for an angle in degrees."""
    if parameter.target.rsplit(".", 1)[-1] in ANGLES:
        angle = math.radians(mu)
        return [math.cos(angle), math.sin(angle)]
    return [mu]


@dataclass(frozen=True)
class ClosedForm:
    """v(μ) = ``base`` + Σⱼ ``coefficients[j]`` fⱼ(μⱼ) (values × basis size), over ``axes``."""

    axes: tuple[Axis, ...]
    base: np.ndarray
    coefficients: tuple[np.ndarray, ...]

    @functools.cached_property
    def _stacked(self) -> np.ndarray:
        """Every axis's coefficients side by side (values × all bases): one product a point."""
        return np.hstack(self.coefficients) if self.coefficients else np.zeros((len(self.base), 0))

    def __call__(self, mu: Mapping[str, float]) -> np.ndarray:
        f = [value for axis in self.axes for value in _basis(axis.parameter, float(mu[axis.parameter.name]))]
        return self.base + self._stacked @ np.array(f)


def closed_form(model: Model, axes: tuple[Axis, ...], read: Callable[[], np.ndarray]) -> ClosedForm | None:
    """The :class:`ClosedForm` of the values ``read()`` gives after ``model.set_parameters``
    (module docstring), or None where none holds. The model's parameters are left as they were."""
    kept = dict(model.parameter_values)
    defaults = model.parameters.defaults
    try:
        model.set_parameters(defaults)
        at_defaults = np.asarray(read(), dtype=float)
        base, coefficients = at_defaults.copy(), []
        for axis in axes:
            parameter = axis.parameter
            rows, found = [], []
            for mu in axis.values:
                model.set_parameters(defaults | {parameter.name: float(mu)})
                rows.append(np.subtract(_basis(parameter, float(mu)), _basis(parameter, defaults[parameter.name])))
                found.append(np.asarray(read(), dtype=float) - at_defaults)
            a = np.linalg.lstsq(np.array(rows), np.array(found), rcond=None)[0].T  # values × basis
            base -= a @ _basis(parameter, defaults[parameter.name])
            coefficients.append(a)
        form = ClosedForm(tuple(axes), base, tuple(coefficients))
        size = max(float(np.abs(at_defaults).max(initial=0.0)), np.finfo(float).tiny)
        for point in model.parameters.sample(8, seed=23):
            model.set_parameters(point)
            if np.abs(form(point) - np.asarray(read(), dtype=float)).max(initial=0.0) > CHECK * size:
                return None
        return form
    finally:
        model.set_parameters(kept)
