"""How far a reduced model's answer lies from the full model's, at the same μ and output times.

The state's error is measured in the energy norm of the model at rest (one norm for the whole
parameter box), relative to the largest change along the load path; the volume's relative to
the volume and to the volume change; the strain energy's relative to its largest value.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lungmech.errors import ParameterError
from lungmech.fem.parametric import Solution
from lungmech.parallel.linalg import apply, gram, norms
from lungmech.rom.basis import origin
from lungmech.rom.reduced import ReducedModel

__all__ = ["Errors", "errors"]


@dataclass(frozen=True)
class Errors:
    """A reduced solution against the full one, worst over the output times.

    ``energy``: max ‖x − x_r‖_E / max ‖x − x₀‖_E over the output times, E the energy inner product
    at rest: the state's error relative to the largest change along the load path (a state back at
    rest has no relative error of its own). ``volume``: |V − V_r| / V. ``volume_change``: |V − V_r| / |V − V₀|
    (relative to the volume the load path moved). ``strain_energy``: relative error.
    ``projection``: the best the basis V can do, max ‖(x − x₀) − P(x − x₀)‖_E / max ‖x − x₀‖_E,
    P = V (VᵀEV)⁻¹ VᵀE the E-orthogonal projection on V (``energy`` ≥ it, up to the solver's
    tolerance: a Galerkin answer is not the projection).
    """

    energy: float
    volume: float
    volume_change: float
    strain_energy: float
    projection: float


def errors(reduced: ReducedModel, full: Solution, approximate: Solution) -> Errors:
    """How far ``approximate`` (of ``reduced``) lies from ``full`` (of the full model, same μ)."""
    if not np.allclose(full.times, approximate.times):
        raise ParameterError("errors: the two solutions have different output times")
    if reduced.full_size is not None:
        raise ParameterError(
            "errors: this reduced model lives on its sampled cells alone and has no full state to compare; "
            "load it with its fields (lungmech.app.reduce.load(path, fields=True))"
        )
    model = reduced.model
    comm = model.geometry.mesh.comm
    W = reduced.energy_product  # assembled once per reduced model
    V = reduced.basis.vectors
    WV = apply(W, V, comm)
    gram_V = gram(V, WV, comm)
    error, change, best = 0.0, 0.0, 0.0
    start = reduced.start_at(approximate.parameters)  # an imaged body's at μ
    for index in range(len(full.times)):
        x = full.states[index]
        x_r = reduced.reconstruct(approximate, index)
        x_0 = origin(model, start)[: V.shape[0]]  # the start with this time's imposed values
        change_here = x - x_0
        projected = V @ np.linalg.solve(gram_V, gram(WV, change_here[:, None], comm)[:, 0])
        difference = np.column_stack([x - x_r, change_here, change_here - projected])
        lengths = norms(difference, W, comm)
        error, change, best = max(error, lengths[0]), max(change, lengths[1]), max(best, lengths[2])
    V, V_r = full.outputs["volume"], approximate.outputs["volume"]
    V_0 = reduced.start_volume
    E, E_r = full.outputs["strain_energy"], approximate.outputs["strain_energy"]
    return Errors(
        energy=float(error / change) if change > 0 else float(error),
        projection=float(best / change) if change > 0 else float(best),
        volume=float(np.max(np.abs(V - V_r) / np.abs(V))),
        volume_change=float(np.max(np.abs(V - V_r)) / max(np.max(np.abs(V - V_0)), 1e-300)),
        strain_energy=float(np.max(np.abs(E - E_r)) / max(np.max(np.abs(E)), 1e-300)),
    )
