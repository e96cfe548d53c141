"""Imposed displacements (Dirichlet conditions) on named boundaries, with load ramps."""

from __future__ import annotations

import numbers
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from dolfinx import fem

from lungmech import checks
from lungmech.errors import ParameterError
from lungmech.fem.ramp import Ramp

if TYPE_CHECKING:
    from lungmech.fem.placement import Image
    from lungmech.mesh.geometry import Geometry

AXES = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True)
class Displacement:
    """u = ramp(t) · value on a boundary; only component ``component`` of u when it is given.

    ``value`` is a vector (or a scalar with ``component``), or a function of the reference
    coordinates x (shape (3, n)) returning the values at those points. ``name`` lets a parameter
    scale it (``constraints.<name>.amplitude``).
    """

    boundary: str
    value: Sequence[float] | float | Callable[[np.ndarray], np.ndarray] = 0.0
    component: int | str | None = None
    ramp: Ramp = field(default_factory=Ramp)
    name: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str):
            raise ParameterError(f"name must be a string (got {self.name!r})")
        if not isinstance(self.boundary, str) or not self.boundary:
            raise ParameterError(f"boundary must be a boundary name (got {self.boundary!r})")
        if not isinstance(self.ramp, Ramp):
            raise ParameterError(f"ramp must be a Ramp (got {self.ramp!r})")
        if not callable(self.value):
            scalar = isinstance(self.value, numbers.Real) and not isinstance(self.value, bool)
            value = checks.real("value", self.value) if scalar else checks.vector("value", self.value, (2, 3))
            object.__setattr__(self, "value", value)
        if isinstance(self.component, bool):
            raise ParameterError(f"component must be 0, 1, 2 or x, y, z (got {self.component!r})")
        if isinstance(self.component, str):
            if self.component not in AXES:
                raise ParameterError(f"component must be 0, 1, 2 or x, y, z (got {self.component!r})")
            object.__setattr__(self, "component", AXES[self.component])
        if self.component is not None and self.component not in (0, 1, 2):
            raise ParameterError(f"component must be 0, 1, 2 or x, y, z (got {self.component!r})")


def clamp(boundary: str) -> Displacement:
    """u = 0 on the boundary."""
    return Displacement(boundary, (0.0, 0.0, 0.0), ramp=Ramp.constant())


def symmetry(boundary: str, component: int | str) -> Displacement:
    """Zero normal displacement on a symmetry plane (the plane's normal is axis ``component``)."""
    return Displacement(boundary, 0.0, component, ramp=Ramp.constant())


@dataclass
class ImposedValue:
    """A built Dirichlet condition and how to set its value at time t: the base value times
    :meth:`factor`."""

    bc: fem.DirichletBC
    target: fem.Function
    base: np.ndarray  # the value at the entries ``where`` of target
    ramp: Ramp
    where: np.ndarray  # the entries of target the condition reads: its dofs (a surface's, not the mesh's)
    amplitude: float = 1.0  # a parameter's factor on the value
    image: Image | None = None  # the unknown is not u but the motion from an image, or its inverse map

    def factor(self, t: float) -> float:
        """The factor on the base value at time t: amplitude · ramp(t) for u; on an image at t₀,
        amplitude · (ramp(t) − ramp(t₀)) for the motion w = u(t) − u(t₀) and −amplitude ·
        ramp(t₀) for the inverse map ξ = −u(t₀), since the image is the state at t₀."""
        if self.image is None:
            return self.amplitude * self.ramp(t)
        if self.image.unknown == "motion":
            return self.amplitude * (self.ramp(t) - self.ramp(self.image.time))
        return -self.amplitude * self.ramp(self.image.time)

    def set_time(self, t: float) -> None:
        self.target.x.array[self.where] = self.factor(t) * self.base


def build(
    constraint: Displacement, space: fem.FunctionSpace, geometry: Geometry, image: Image | None = None
) -> ImposedValue:
    """The DirichletBC of ``constraint`` on the displacement (sub)space ``space`` (on an image,
    of the motion or the inverse map, see :meth:`ImposedValue.factor`)."""
    assert not isinstance(constraint.component, str)  # __post_init__ made an axis name its index
    gdim = geometry.mesh.geometry.dim
    if constraint.component is not None and constraint.component >= gdim:
        raise ParameterError(
            f"imposed displacement on '{constraint.boundary}': component {'xyz'[constraint.component]} "
            f"does not exist on a {gdim}-D mesh"
        )
    sub = space if constraint.component is None else space.sub(constraint.component)
    values = sub.collapse()[0] if sub.component() else sub
    facets = geometry.facets(constraint.boundary)
    fdim = geometry.mesh.topology.dim - 1
    base = fem.Function(values)
    base.interpolate(_as_callable(constraint, values.value_size))
    target = fem.Function(values)
    if sub.component():  # a subspace: dofs come in (sub, collapsed) pairs
        dofs = fem.locate_dofs_topological((sub, values), fdim, facets)
        bc = fem.dirichletbc(target, dofs, sub)
        where = np.asarray(dofs[1])
    else:
        dofs = fem.locate_dofs_topological(sub, fdim, facets)
        bc = fem.dirichletbc(target, dofs)
        bs = values.dofmap.index_map_bs
        where = (bs * np.asarray(dofs)[:, None] + np.arange(bs)).reshape(-1)
    return ImposedValue(bc, target, base.x.array[where].copy(), constraint.ramp, where, image=image)


def _as_callable(constraint: Displacement, size: int) -> Callable[[np.ndarray], np.ndarray]:
    if callable(constraint.value):
        return constraint.value
    value = np.atleast_1d(np.asarray(constraint.value, dtype=float))
    if value.size == 3 and size == 2 and value[2] == 0.0:
        value = value[:2]  # a vector without z-part (e.g. a clamp's zeros) is the in-plane one
    if value.size != size:
        what = "a scalar" if size == 1 else f"{size} components"
        raise ParameterError(f"imposed displacement on '{constraint.boundary}' needs {what} (got {list(value)})")
    return lambda x: np.tile(value[:, None], (1, x.shape[1]))
