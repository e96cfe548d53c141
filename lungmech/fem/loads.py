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
from typing import ClassVar, NamedTuple

import numpy as np
import ufl
from ufl.core.expr import Expr

from lungmech import checks
from lungmech.errors import ParameterError
from lungmech.fem.kinematics import current_area_normal
from lungmech.fem.ramp import Ramp


class StateDependentWork(NamedTuple):
    """A virtual work W(u, θ; v) whose coefficients θ are global functionals of the state, θ = Θ(u).

    ``update()`` sets θ = Θ(u) for the model's current state; ``linearise()`` returns, at that
    state, the columns ∂W/∂θ_j and dΘ_j/du (owned dofs of the model's space), so that the
    tangent of −W(u, Θ(u)) is the frozen-θ tangent plus −(∂W/∂θ)(dΘ/du), a low-rank term.
    """

    form: ufl.Form
    update: Callable[[], None]
    linearise: Callable[[], tuple[np.ndarray, np.ndarray]]


class Named:
    """A load's label for outputs and messages: its ``name``, or what it is and where it acts.

    Subclasses are frozen dataclasses with a ``name`` field and a ``kind`` (e.g. "traction").
    """

    kind: ClassVar[str]

    @property
    def label(self) -> str:
        where = getattr(self, "boundary", None)
        where = (where,) if isinstance(where, str) else where
        return self.name or (f"{self.kind} on {'+'.join(where)}" if where else self.kind)

    def _check(self, vector: bool) -> None:
        """Validate name, ramp and value (a number, or a vector of 2 or 3 numbers: the model
        checks it against the mesh's dimension), and the boundary."""
        if not isinstance(self.name, str):
            raise ParameterError(f"name must be a string (got {self.name!r})")
        if not isinstance(self.ramp, Ramp):
            raise ParameterError(f"ramp must be a Ramp (got {self.ramp!r})")
        value = checks.vector("value", self.value, (2, 3)) if vector else checks.real("value", self.value)
        object.__setattr__(self, "value", value)
        if hasattr(self, "boundary"):
            names = (self.boundary,) if isinstance(self.boundary, str) else self.boundary
            if (
                isinstance(names, str | bytes)
                or not isinstance(names, Sequence)
                or not names
                or not all(isinstance(n, str) and n for n in names)
            ):
                raise ParameterError(f"boundary must be a boundary name or a list of them (got {self.boundary!r})")
            object.__setattr__(self, "boundary", self.boundary if isinstance(self.boundary, str) else tuple(names))


@dataclass(frozen=True)
class BodyForce(Named):
    """Dead body force per unit reference volume (e.g. ρ₀ g)."""

    value: Sequence[float]
    ramp: Ramp = field(default_factory=Ramp)
    name: str = ""
    kind: ClassVar[str] = "body force"

    def __post_init__(self):
        self._check(vector=True)

    def potential(self, model, value: Expr) -> ufl.Form:
        return -ufl.dot(value, model.u) * ufl.dx(domain=model.geometry.mesh)


@dataclass(frozen=True)
class Traction(Named):
    """Dead traction per unit reference area on a named boundary."""

    boundary: str
    value: Sequence[float]
    ramp: Ramp = field(default_factory=Ramp)
    name: str = ""
    kind: ClassVar[str] = "traction"

    def __post_init__(self):
        self._check(vector=True)

    def potential(self, model, value: Expr) -> ufl.Form:
        return -ufl.dot(value, model.u) * model.geometry.ds(self.boundary)


@dataclass(frozen=True)
class FollowerPressure(Named):
    """Pressure on the deformed boundary, pushing against its outward normal: t = −p n da.

    Pulled back to the reference surface with Nanson's formula, n da = J F⁻ᵀ N dA. A positive
    value on the inner surface of a cavity inflates it; a negative one on the outer surface of a
    body (pleural suction) pulls it outwards.
    """

    boundary: str | tuple[str, ...]  # one boundary, or several under the same pressure
    value: float
    ramp: Ramp = field(default_factory=Ramp)
    name: str = ""
    kind: ClassVar[str] = "follower pressure"

    def __post_init__(self):
        self._check(vector=False)

    def virtual_work(self, model, v: Expr, value: Expr) -> ufl.Form:
        n_da = current_area_normal(model.F, ufl.FacetNormal(model.geometry.mesh))
        return -value * ufl.dot(n_da, v) * model.geometry.ds(self.boundary)


Load = BodyForce | Traction | FollowerPressure
