"""External loads as potentials (conservative) or virtual works (follower loads).

A load is a frozen description: a value, where it acts, and a :class:`Ramp`. The model gives it
the current value as a UFL ``Constant`` (``ramp(t) · value``), so a load step recompiles nothing.
Conservative loads define ``potential(model, value)`` (the energy of the load, −work); follower
loads define ``virtual_work(model, v, value)``; a load may define both (its virtual work may be
a :class:`StateDependentWork`). Both read the model's kinematics (u, F,
the formulation's fields, its dx), so a load may act on any field, not only on u.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import ufl
from ufl.core.expr import Expr

from lungmech.ramp import Ramp


class StateDependentWork(NamedTuple):
    """A virtual work whose coefficients θ are global functionals of the state, θ = G(u).

    ``evaluate()`` returns G(u) for the current state without touching the form;
    ``assign(θ)`` sets the coefficients the form uses. The solver freezes θ during a Newton
    solve and iterates θ ← G(u(θ)) (accelerated) until it settles.
    """

    form: ufl.Form
    evaluate: Callable[[], np.ndarray]
    assign: Callable[[np.ndarray], None]


@dataclass(frozen=True)
class BodyForce:
    """Dead body force per unit reference volume (e.g. ρ₀ g)."""

    value: Sequence[float]
    ramp: Ramp = field(default_factory=Ramp)

    def potential(self, model, value: Expr) -> ufl.Form:
        return -ufl.dot(value, model.u) * ufl.dx(domain=model.geometry.mesh)


@dataclass(frozen=True)
class Traction:
    """Dead traction per unit reference area on a named boundary."""

    boundary: str
    value: Sequence[float]
    ramp: Ramp = field(default_factory=Ramp)

    def potential(self, model, value: Expr) -> ufl.Form:
        return -ufl.dot(value, model.u) * model.geometry.ds(self.boundary)


@dataclass(frozen=True)
class FollowerPressure:
    """Pressure on the deformed boundary, pushing against its outward normal: t = −p n da.

    Pulled back to the reference surface with Nanson's formula, n da = J F⁻ᵀ N dA. A positive
    value on the inner surface of a cavity inflates it; a negative one on the outer surface of a
    body (pleural suction) pulls it outwards.
    """

    boundary: str | tuple[str, ...]  # one boundary, or several under the same pressure
    value: float
    ramp: Ramp = field(default_factory=Ramp)

    def __post_init__(self):
        if not isinstance(self.boundary, str):
            object.__setattr__(self, "boundary", tuple(self.boundary))

    def virtual_work(self, model, v: Expr, value: Expr) -> ufl.Form:
        F = model.F
        N = ufl.FacetNormal(model.geometry.mesh)
        return -value * ufl.dot(ufl.det(F) * ufl.inv(F).T * N, v) * model.geometry.ds(self.boundary)


Load = BodyForce | Traction | FollowerPressure
