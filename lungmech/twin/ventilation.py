"""Regional ventilation as imaging reads it: the local volume change from end-expiration to
end-inspiration, fitted and observed.

On the lung imaged at end-expiration (the mesh), a motion w to end-inspiration changes each
cell's volume by the factor J = det(I + ∇w); J − 1 is the specific ventilation a CT of both
states shows. Not J against the unloaded reference, which no image shows.

* **fitted**: w is the model's motion at the estimate (a full-order solve, its field);
* **observed**: w is a registration of the imaged mesh onto the end-inspiration segmentation
  (:func:`lungmech.registration.sobolev.register`). Between two segmentations the motion
  inside the lung comes from the registration's regulariser, not from the lung: this is what a
  registration of segmentations reads, the picture to set beside the fitted one, not data the
  fit used (an intensity registration's field would be).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import dolfinx
import numpy as np
import ufl
from dolfinx import fem

from lungmech import jit
from lungmech.fem.parametric import ParametricModel
from lungmech.registration.image import Image
from lungmech.registration.sobolev import Options, register

__all__ = ["Ventilation", "ventilation", "volume_ratio"]


@dataclass(frozen=True)
class Ventilation:
    """J − 1 on each cell this rank owns of ``mesh`` (the lung imaged at end-expiration):
    ``fitted`` and ``observed`` (see the module's doc)."""

    mesh: dolfinx.mesh.Mesh
    fitted: np.ndarray
    observed: np.ndarray


def volume_ratio(w: fem.Function) -> np.ndarray:
    """J = det(I + ∇w) on each cell this rank owns of w's mesh (its value at the midpoint:
    constant on a P1 motion's tetrahedra)."""
    mesh = w.function_space.mesh
    cells = fem.functionspace(mesh, ("DG", 0))
    J = fem.Function(cells)
    F = ufl.Identity(mesh.geometry.dim) + ufl.grad(w)
    J.interpolate(jit.expression(ufl.det(F), cells.element.interpolation_points))
    owned = mesh.topology.index_map(mesh.topology.dim).size_local
    return J.x.array[cells.dofmap.list[:owned, 0]].copy()


def ventilation(
    model: ParametricModel, mu: Mapping[str, float], time: float, inspiration: Image, options: Options = Options()
) -> Ventilation:
    """The ventilation of the full ``model`` of an imaged lung at ``mu`` from its start to
    ``time``, beside the registration of its mesh onto the ``inspiration`` segmentation.
    Collective; the model's state is left at ``time``."""
    solution = model.solve(dict(mu), times=[model.stepping.start, time])
    model.fields(solution.states[-1], time)
    fitted = volume_ratio(model.model.motion()) - 1.0
    mesh = model.model.geometry.mesh
    observed = volume_ratio(register(mesh, inspiration, options).displacement) - 1.0
    return Ventilation(mesh, fitted, observed)
