"""External loads as potentials (conservative) or virtual works (follower loads).

A load is a frozen description: a value, where it acts, and a :class:`Ramp`. The model gives it
the current value as a UFL ``Constant`` (``ramp(t) · value``), so a load step recompiles nothing.
Tractions, body forces and pressures may also be formulas of the reference position and the time
(:mod:`lungmech.fem.expressions`), e.g. ``Traction("top", (0.0, "-1e3 * x * sin(pi * t)"))``;
the Constant then holds ramp(t) alone.
Conservative loads define ``potential(model, value)`` (the energy of the load, −work); follower
loads define ``virtual_work(model, v, value)``; a load may define both (its virtual work may be
a :class:`StateDependentWork`). Both read the model's kinematics (u, F,
the formulation's fields, its dx), so a load may act on any field, not only on u.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import Field, dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple, Protocol, cast

from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import mesh as dmesh
from ufl.core.expr import Expr

from lungmech import checks, jit
from lungmech.errors import ParameterError
from lungmech.fem import expressions
from lungmech.fem.kinematics import current_area_normal
from lungmech.fem.ramp import Ramp

if TYPE_CHECKING:
    from lungmech.fem.model import Model

LoadValue = float | str | Sequence[float | str]  # a number or a vector, each part maybe a formula


class Load(Protocol):
    """What a model uses of a load (:class:`lungmech.fem.model.Model`): its value (a number or a
    vector, any part of it a formula), what the model's Constant holds at ramp 1 (``magnitude``),
    its ramp, its name (parameters target it by name) and its label for outputs and messages.

    A load is a dataclass (a parameter on its value or posture replaces that field), and defines
    ``potential(model, value)``, ``virtual_work(model, v, value)`` or both (see the module): the
    model asks which with ``hasattr``. The loads here and the lung's
    (:class:`lungmech.lung.poromechanics.AlveolarPressure`, :class:`lungmech.lung.gravity.Gravity`)
    are :class:`Named` ones.
    """

    __dataclass_fields__: ClassVar[dict[str, Field[Any]]]

    @property
    def name(self) -> str: ...

    @property
    def value(self) -> LoadValue: ...

    @property
    def ramp(self) -> Ramp: ...

    @property
    def label(self) -> str: ...

    @property
    def magnitude(self) -> np.ndarray: ...


class _Described(Load, Protocol):
    """A :class:`Named` load: a :class:`Load` that says what it is (``kind``)."""

    kind: ClassVar[str]


class StateDependentWork(NamedTuple):
    """A virtual work W(u, θ; v) whose coefficients θ are global functionals of the state, θ = Θ(u).

    ``update()`` sets θ = Θ(u) for the model's current state; ``linearise()`` returns, at that
    state, the columns ∂W/∂θ_j and dΘ_j/du (owned dofs of the model's space), so that the
    tangent of −W(u, Θ(u)) is the frozen-θ tangent plus −(∂W/∂θ)(dΘ/du), a low-rank term.

    ``integrals`` names the integrals Θ is computed from
    (:class:`lungmech.fem.state_dependent.Integral`), and ``bind(integration)`` gives an object
    with the same ``update()`` and ``linearise()``, and ``rounding()`` (the size of θ's rounding
    errors), with every integral and column evaluated by ``integration``
    (:class:`lungmech.fem.state_dependent.Integration`): a hyper-reduced model evaluates them from
    its reduced coordinates and its sample instead of the whole mesh.
    """

    form: ufl.Form
    update: Callable[[], None]
    linearise: Callable[[], tuple[np.ndarray, np.ndarray]]
    integrals: dict = {}
    bind: Callable | None = None


class Named:
    """A load's label for outputs and messages: its ``name``, or what it is and where it acts.

    Subclasses are frozen dataclasses with a ``name`` field and a ``kind`` (e.g. "traction").
    """

    kind: ClassVar[str]

    @property
    def label(self: _Described) -> str:
        where = getattr(self, "boundary", None)
        where = (where,) if isinstance(where, str) else where
        return self.name or (f"{self.kind} on {'+'.join(where)}" if where else self.kind)

    def _check(self: _Described, vector: bool, formulas: bool = False) -> None:
        """Validate name, ramp and value (a number, or a vector of 2 or 3 numbers: the model
        checks it against the mesh's dimension; with ``formulas``, any of them may be a formula
        of x, y, z, t), and the boundary."""
        if not isinstance(self.name, str):
            raise ParameterError(f"name must be a string (got {self.name!r})")
        if not isinstance(self.ramp, Ramp):
            raise ParameterError(f"ramp must be a Ramp (got {self.ramp!r})")
        value: LoadValue
        if formulas and _has_formula(self.value):
            value = _formulas(self.value, vector)
        else:
            value = checks.vector("value", self.value, (2, 3)) if vector else checks.real("value", self.value)
        object.__setattr__(self, "value", value)
        if hasattr(self, "boundary"):
            names = checks.names("boundary", self.boundary)
            object.__setattr__(self, "boundary", self.boundary if isinstance(self.boundary, str) else names)

    @property
    def magnitude(self: _Described) -> np.ndarray:
        """What the model's Constant holds at ramp 1: the value, or 1 for a formula."""
        return np.ones(()) if _has_formula(self.value) else np.asarray(self.value, dtype=float)

    def current(self: _Described, model: Model, value: Expr) -> Expr:
        """The load at the model's time as UFL: ``value`` (the model's Constant, ramp(t) ×
        magnitude), times the formulas of the reference position and t where there are any."""
        if not _has_formula(self.value):
            return value
        position, time = model.position, model.time_constant

        def component(item: float | str, i: int | None) -> Expr | float:
            where = f"load '{self.label}': value" + ("" if i is None else f"[{i}]")
            return expressions.to_ufl(item, where, position, time) if isinstance(item, str) else item

        if isinstance(self.value, str):
            return value * component(self.value, None)
        vector = cast(Sequence[float | str], self.value)  # not a number: it has a formula
        return value * ufl.as_vector([component(item, i) for i, item in enumerate(vector)])

    def undefined(self: _Described, model: Model, times: Sequence[float]) -> str:
        """Collective: "" if the load's formulas are finite where it acts at ``times`` (s), else
        which formula is not and where: nan or inf there makes the residual so, and Newton's
        failure would look like an inverted element. Checked at the midpoints of its cells, or
        of its boundary's facets (owned), where quadrature samples it."""
        if not _has_formula(self.value):
            return ""
        mesh = model.geometry.mesh
        dim = mesh.topology.dim - (1 if hasattr(self, "boundary") else 0)
        if hasattr(self, "boundary"):
            names = (self.boundary,) if isinstance(self.boundary, str) else self.boundary
            entities = np.concatenate([model.geometry.facets(n) for n in names])
            entities = entities[entities < mesh.topology.index_map(dim).size_local]
        else:
            entities = np.arange(mesh.topology.index_map(dim).size_local, dtype=np.int32)
        points = dmesh.compute_midpoints(mesh, dim, entities.astype(np.int32))[:, : mesh.geometry.dim]
        vector = cast(Sequence[float | str], self.value)  # not a number: it has a formula
        items = [(None, self.value)] if isinstance(self.value, str) else list(enumerate(vector))
        found = ""
        for t in times:
            for i, item in items:
                if not isinstance(item, str) or found:
                    continue
                where = "value" + ("" if i is None else f"[{i}]")
                values = expressions.evaluate(item, f"load '{self.label}': {where}", points, t)
                bad = np.flatnonzero(~np.isfinite(values))
                if bad.size:
                    at = ", ".join(f"{c:.4g}" for c in points[bad[0]])
                    found = (
                        f"load '{self.label}': {where} = {item!r} is {values[bad[0]]} at x = ({at}) m, t = {t:.6g} s"
                    )
        reports = [f for f in mesh.comm.allgather(found) if f]
        if not reports:
            return ""
        return f"{reports[0]}: a load's formula must be finite wherever and whenever the load acts"


def is_pressure(load: Load) -> bool:
    """Whether a load's value is one number (a pressure, Pa): not a vector, not a formula."""
    return np.ndim(load.value) == 0 and not isinstance(load.value, str)


def _has_formula(value: object) -> bool:
    return isinstance(value, str) or (isinstance(value, tuple | list) and any(isinstance(v, str) for v in value))


def _formulas(value: object, vector: bool) -> str | tuple[float | str, ...]:
    """A value with formulas, checked: each one parses (the names against the mesh come later)."""
    if not vector:
        if not isinstance(value, str):
            raise ParameterError(f"value must be a number or a formula (got {value!r})")
        expressions.check(value, "value")
        return value
    if not isinstance(value, tuple | list) or len(value) not in (2, 3):
        raise ParameterError(f"value must be 2 or 3 numbers or formulas (got {value!r})")
    for i, item in enumerate(value):
        if isinstance(item, str):
            expressions.check(item, f"value[{i}]")
        else:
            checks.real(f"value[{i}]", item)
    return tuple(item if isinstance(item, str) else float(item) for item in value)


@dataclass(frozen=True)
class BodyForce(Named):
    """Dead body force per unit reference volume (e.g. ρ₀ g)."""

    value: Sequence[float | str]
    ramp: Ramp = field(default_factory=Ramp)
    name: str = ""
    kind: ClassVar[str] = "body force"

    def __post_init__(self) -> None:
        self._check(vector=True, formulas=True)

    def potential(self, model: Model, value: Expr) -> ufl.Form:
        dX = model.kinematics.reference_volume(ufl.dx(domain=model.geometry.mesh))
        return -ufl.dot(self.current(model, value), model.u) * dX


@dataclass(frozen=True)
class Traction(Named):
    """Dead traction per unit reference area on a named boundary (Pa; numbers, or formulas of
    the reference position and the time)."""

    boundary: str
    value: Sequence[float | str]
    ramp: Ramp = field(default_factory=Ramp)
    name: str = ""
    kind: ClassVar[str] = "traction"

    def __post_init__(self) -> None:
        self._check(vector=True, formulas=True)

    def potential(self, model: Model, value: Expr) -> ufl.Form:
        dA = model.kinematics.reference_area(model.geometry.ds(self.boundary))
        return -ufl.dot(self.current(model, value), model.u) * dA


@dataclass(frozen=True)
class Force(Named):
    """A total force on a named boundary (N; N per metre of thickness in 2-D), spread as a dead
    traction over its reference area A: t = f/A, A measured when the model is built."""

    boundary: str
    value: Sequence[float]
    ramp: Ramp = field(default_factory=Ramp)
    name: str = ""
    kind: ClassVar[str] = "force"

    def __post_init__(self) -> None:
        self._check(vector=True)

    def potential(self, model: Model, value: Expr) -> ufl.Form:
        from dolfinx import fem

        ds = model.geometry.ds(self.boundary)
        mesh = model.geometry.mesh
        area = mesh.comm.allreduce(fem.assemble_scalar(jit.form(1.0 * ds)), op=MPI.SUM)  # the mesh's
        per_area = fem.Constant(mesh, 1.0 / area)  # not a literal: another mesh compiles nothing
        return -per_area * ufl.dot(value, model.u) * model.kinematics.reference_area(ds)


@dataclass(frozen=True)
class NormalPressure(Named):
    """Dead pressure on a named boundary, along its reference outward normal: t = −p N (Pa;
    a number or a formula). Unlike a :class:`FollowerPressure` it does not turn with the
    surface: it derives from the potential ∫ p N·u dA."""

    boundary: str | tuple[str, ...]
    value: float | str
    ramp: Ramp = field(default_factory=Ramp)
    name: str = ""
    kind: ClassVar[str] = "normal pressure"

    def __post_init__(self) -> None:
        self._check(vector=False, formulas=True)

    def potential(self, model: Model, value: Expr) -> ufl.Form:
        N_dA = model.area_normal  # per mesh area
        return self.current(model, value) * ufl.dot(N_dA, model.u) * model.geometry.ds(self.boundary)


@dataclass(frozen=True)
class FollowerPressure(Named):
    """Pressure on the deformed boundary, pushing against its outward normal: t = −p n da.

    Pulled back to the reference surface with Nanson's formula, n da = J F⁻ᵀ N dA. A positive
    value on the inner surface of a cavity inflates it; a negative one on the outer surface of a
    body (pleural suction) pulls it outwards.
    """

    boundary: str | tuple[str, ...]  # one boundary, or several under the same pressure
    value: float | str
    ramp: Ramp = field(default_factory=Ramp)
    name: str = ""
    kind: ClassVar[str] = "follower pressure"

    def __post_init__(self) -> None:
        self._check(vector=False, formulas=True)

    def virtual_work(self, model: Model, v: Expr, value: Expr) -> ufl.Form:
        n_da = current_area_normal(model.F, model.area_normal)
        return -self.current(model, value) * ufl.dot(n_da, v) * model.geometry.ds(self.boundary)
