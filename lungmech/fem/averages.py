"""A formulation's averages: means of cellwise scalars over the body, reported as outputs.

A formulation may name averages (``formulation.averages(model)``: the lung's fractions and mean
stresses), each an :class:`Average` of a scalar f of the state, a mean per unit reference volume
or per unit current volume:

.. math:: ⟨f⟩_X = \\frac{∫ f \\, dX}{∫ dX},   ⟨f⟩_x = \\frac{∫ f J \\, dX}{∫ J \\, dX} = \\frac{∫ f \\, dx}{∫ dx}.

Both are ratios of two integrals over the reference body. The full model evaluates them as they
stand (:func:`means`); a hyper-reduced model samples their numerators ∫ f w dX, w = 1 or J
(:mod:`lungmech.rom.ecsw`) and has their denominators exactly: the reference volume, and the
current volume's cubic (:mod:`lungmech.rom.outputs`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import ufl
from dolfinx import fem
from ufl.core.expr import Expr

from lungmech.fem.quantities import deformed_volume, integral

if TYPE_CHECKING:
    from lungmech.fem.model import Model

__all__ = ["Average", "averages", "means"]


@dataclass(frozen=True)
class Average:
    """The mean of the scalar ``integrand`` (in ``unit``) over the body, ``per`` unit reference
    volume (⟨f⟩_X = ∫ f dX / ∫ dX) or per unit current volume (⟨f⟩_x = ∫ f J dX / ∫ J dX)."""

    integrand: Expr
    unit: str
    per: Literal["reference", "current"] = "reference"

    def __post_init__(self) -> None:
        if self.per not in ("reference", "current"):
            raise ValueError(f"an average is per 'reference' or 'current' volume, not {self.per!r}")

    def weighted(self, model: Model) -> Expr:
        """The numerator's integrand over the reference body: f, or f J per current volume."""
        return self.integrand * ufl.det(model.F) if self.per == "current" else self.integrand


def averages(model: Model) -> dict[str, Average]:
    """The averages ``model``'s formulation names, by name ({} if it names none)."""
    named = getattr(model.formulation, "averages", None)
    return {} if named is None else dict(named(model))


def means(model: Model) -> dict[str, tuple[Callable[[], float], str]]:
    """Each of the formulation's averages as (its value on the model's state, its unit) by name.

    Compiled once (collective); the reference volume is integrated at each call, since an
    inverse problem moves the reference."""
    comm = model.geometry.mesh.comm
    named = averages(model)
    if not named:
        return {}
    reference = integral(fem.Constant(model.geometry.mesh, 1.0) * model.dx, comm)
    current = deformed_volume(model)
    result: dict[str, tuple[Callable[[], float], str]] = {}
    for name, average in named.items():
        numerator = integral(average.weighted(model) * model.dx, comm)
        volume = current if average.per == "current" else reference
        result[name] = (_ratio(numerator, volume), average.unit)
    return result


def _ratio(numerator: Callable[[], float], denominator: Callable[[], float]) -> Callable[[], float]:
    return lambda: numerator() / denominator()
