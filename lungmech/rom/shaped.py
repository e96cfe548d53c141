"""A reduced model's volumes over the body's shape: polynomials in (z, a) together.

On a template mesh with a shape map χ_a (:mod:`lungmech.fem.shape`, s = Σ aᵢ mᵢ, G = I + ∇s)
every volume a reduced model reports is that of the template moved by s plus the state's vector
field y (:mod:`lungmech.fem.placement`):

* the current volume, y = w the displacement from the mesh (u on a reference mesh, the motion
  on an image): ∫ det F dX = ∫ det(I + ∇w G⁻¹) det G dx̂ = ∫ det(I + ∇(w + s)) dx̂;
* an image's reference volume, y = ξ its inverse map: ∫ dX = ∫ det(I + ∇ξ G⁻¹) det G dx̂
  = ∫ det(I + ∇(ξ + s)) dx̂;
* the mesh's own body (the reference on a reference mesh, the image on an image), y = 0:
  ∫ det G dx̂ = ∫ det(I + ∇s) dx̂

(the first times the thickness stretch in 2-D). Each is a cubic in (y, a) together, whatever
the model's forms look like. With each mode lifted into the state's vector field (exact: modes
are of the mesh's degree, the displacement's degree at least that), s is one more direction of
the state, and :func:`~lungmech.rom.exact.cubic` gives the polynomial in z = (q, imposed factors,
a) from the template's volume functional ∫ det(I + ∇y) dx̂. Each is checked against the model's
own form at a random (z, a).
"""

from __future__ import annotations

from collections.abc import Callable

from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem

from lungmech.errors import ParameterError
from lungmech.fem.model import Model
from lungmech.fem.quantities import integral
from lungmech.parallel.owned import owned_size
from lungmech.rom.exact import Cubic, cubic

__all__ = ["lifted_modes", "mesh_volume", "volume"]


def lifted_modes(model: Model) -> np.ndarray:
    """The shape modes as states (owned rows, one column per mode): each mode in the state's
    vector field, every other field 0. Collective."""
    assert model.shape is not None
    lifted = np.empty((owned_size(model.space), len(model.shape.modes)))
    state = fem.Function(model.space)
    vector = state.sub(0) if model.multi_field else state
    for i, mode in enumerate(model.shape.modes):
        state.x.array[:] = 0.0
        vector.interpolate(mode)
        lifted[:, i] = state.x.array[: lifted.shape[0]]
    return lifted


def _template_volume(model: Model, stretched: bool) -> ufl.Form:
    """∫ det(I + ∇y) dx̂ of the state's vector field y on the template mesh (no shape map),
    times the thickness stretch in 2-D if ``stretched``."""
    y = ufl.split(model.state)[0] if model.multi_field else model.state
    J = ufl.det(ufl.Identity(len(y)) + ufl.grad(y))
    stretch = model.fields.get("thickness_stretch")
    if stretched and stretch is not None:
        J = J * stretch
    return J * ufl.dx(domain=model.geometry.mesh, metadata=model.dx.metadata())


def volume(model: Model, own: ufl.Form, start: np.ndarray, directions: np.ndarray, check: float = 1e-9) -> Cubic:
    """The volume ``own`` (a 0-form of the model: ∫ det F dX of a reference mesh's or an image's
    motion, ∫ 1 dX of an image's inverse problem) at the state r + Z z and the shape a, as a
    :class:`~lungmech.rom.exact.Cubic` in (z, a): ``start`` r (a full local state array),
    ``directions`` Z (owned rows). Checked against ``own`` at a random (z, a). Collective; the
    model's state and shape are kept."""
    if model.shape is None:
        raise ParameterError("the model has no shape map")
    found = cubic(model, _template_volume(model, stretched=True), start, np.hstack([directions, lifted_modes(model)]))
    _compare(model, found, integral(own, model.geometry.mesh.comm), start, directions, check)
    return found


def mesh_volume(model: Model, check: float = 1e-9) -> Cubic:
    """∫ det G dx̂, the volume of the mesh's body at the shape a (the reference on a reference
    mesh, the image on an image; m³, m³/m in 2-D), as a :class:`~lungmech.rom.exact.Cubic` in a.
    Collective."""
    if model.shape is None:
        raise ParameterError("the model has no shape map")
    zero, lifted = np.zeros_like(model.state.x.array), lifted_modes(model)
    found = cubic(model, _template_volume(model, stretched=False), zero, lifted)
    own = ufl.det(model.shape.gradient) * ufl.dx(domain=model.geometry.mesh, metadata=model.dx.metadata())
    _compare(model, found, integral(own, model.geometry.mesh.comm), zero, np.zeros((lifted.shape[0], 0)), check)
    return found


def _compare(
    model: Model,
    found: Cubic,
    own: Callable[[], float],
    start: np.ndarray,
    directions: np.ndarray,
    check: float,
) -> None:
    """``found`` against the model's own functional ``own()`` at a random (z, a): the state
    r + Z z (each direction moving a node by at most 1 cm) and the shape a ∈ [−0.5, 0.5]ᵏ."""
    assert model.shape is not None
    comm = model.geometry.mesh.comm
    rng = np.random.default_rng(1)
    owned, size = directions.shape
    largest = np.empty(size)
    comm.Allreduce(np.abs(directions).max(axis=0, initial=0.0), largest, op=MPI.MAX)
    z = rng.uniform(-0.01, 0.01, size) / np.where(largest > 0, largest, 1.0)
    a = rng.uniform(-0.5, 0.5, len(model.shape.modes))
    before = model.shape.values()
    with model.kept_state():
        model.state.x.array[:] = start
        model.state.x.array[:owned] += directions @ z
        model.state.x.scatter_forward()
        try:
            model.shape.set(a)
            exact = own()
        finally:
            model.shape.set(before)
    off = comm.allreduce(abs(found(np.concatenate([z, a])) - exact), op=MPI.MAX)
    if off > check * max(abs(exact), np.finfo(float).tiny):
        raise ParameterError(
            f"a volume over the shape is off by {off:.2e} at a test point: the shape modes are not in the "
            "state's space, or the state's vector field is not what moves the body"
        )
