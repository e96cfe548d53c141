"""The reductor: from a full-order model and training parameters to a reduced model.

:func:`reduce` solves the full model along its load path at every training point μ_j (a
seeded space-filling sample of the parameter box, see
:meth:`~lungmech.fem.parameters.Parameters.sample`), keeps every accepted step as a snapshot of
x − x₀, and makes their POD basis in the chosen inner product; the reduced model projects the
full model's forms on it. :func:`errors` measures a reduced model against the full one, point by
point: the error in the energy norm of the state and the error of the outputs.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from lungmech.errors import ParameterError
from lungmech.fem.parametric import FullOrderModel, Solution
from lungmech.fem.start import one_state
from lungmech.parallel.linalg import norms
from lungmech.rom.basis import origin
from lungmech.rom.pod import pod, snapshots
from lungmech.rom.reduced import ReducedModel

__all__ = ["Errors", "errors", "reduce"]


def reduce(
    full: FullOrderModel,
    training: Sequence[Mapping[str, float]],
    size: int = 20,
    inner: str = "energy",
    timings: dict[str, float] | None = None,
) -> ReducedModel:
    """The reduced model of ``full`` on the POD basis of its load paths at the ``training`` points.

    ``size`` caps the basis (POD keeps fewer when the snapshots have fewer directions above its
    noise level). ``inner`` is the POD's inner product: "energy" (the second variation of the
    stored energy at rest), "mass" or "l2". ``timings``, if given, receives the seconds spent on
    snapshots and POD. Collective.
    """
    if not training:
        raise ParameterError("reduce: give at least one training parameter point")
    model = full.model
    start = one_state(full.start, model)
    tic = time.perf_counter()
    data = snapshots(model, full.stepping, solver=full.solver, start=start, parameters=training)
    seconds = {"snapshots": time.perf_counter() - tic}
    tic = time.perf_counter()
    points = [model.parameters.values(point) for point in training]
    basis = pod(model, data, inner=inner, size=size, source={"training": points})
    seconds["pod"] = time.perf_counter() - tic
    if timings is not None:
        timings.update(seconds)
    probes = full.outputs.probe_points
    return ReducedModel(model, basis, full.stepping, full.solver.options, start, probes, points)


@dataclass(frozen=True)
class Errors:
    """A reduced solution against the full one, worst over the output times.

    ``energy``: max ‖x − x_r‖_E / max ‖x − x₀‖_E over the output times, E the energy inner product
    at rest: the state's error relative to the largest change along the load path (a state back at
    rest has no relative error of its own). ``volume``: |V − V_r| / V. ``volume_change``: |V − V_r| / |V − V₀|
    (relative to the volume the load path moved). ``strain_energy``: relative error.
    """

    energy: float
    volume: float
    volume_change: float
    strain_energy: float


def errors(reduced: ReducedModel, full: Solution, approximate: Solution) -> Errors:
    """How far ``approximate`` (of ``reduced``) lies from ``full`` (of the full model, same μ)."""
    if not np.allclose(full.times, approximate.times):
        raise ParameterError("errors: the two solutions have different output times")
    model = reduced.model
    comm = model.geometry.mesh.comm
    W = reduced.energy_product  # assembled once per reduced model
    owned = reduced.basis.vectors.shape[0]
    error, change = 0.0, 0.0
    for index in range(len(full.times)):
        x = full.states[index]
        x_r = reduced.reconstruct(approximate, index)
        x_0 = origin(model, reduced.start)[:owned]  # the start with this time's imposed values
        difference = np.column_stack([x - x_r, x - x_0])
        lengths = norms(difference, W, comm)
        error, change = max(error, lengths[0]), max(change, lengths[1])
    V, V_r = full.outputs["volume"], approximate.outputs["volume"]
    V_0 = reduced.start_volume
    E, E_r = full.outputs["strain_energy"], approximate.outputs["strain_energy"]
    return Errors(
        energy=float(error / change) if change > 0 else float(error),
        volume=float(np.max(np.abs(V - V_r) / np.abs(V))),
        volume_change=float(np.max(np.abs(V - V_r)) / max(np.max(np.abs(V - V_0)), 1e-300)),
        strain_energy=float(np.max(np.abs(E - E_r)) / max(np.max(np.abs(E)), 1e-300)),
    )
