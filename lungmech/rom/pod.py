"""Proper orthogonal decomposition of full-order snapshots (method of snapshots)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from lungmech.errors import ParameterError
from lungmech.fem.model import Model
from lungmech.fem.parametric import FullOrderModel
from lungmech.fem.solver import NewtonOptions, NewtonSolver, Stepping
from lungmech.parallel import linalg
from lungmech.parallel.layout import layout
from lungmech.parallel.owned import owned_size
from lungmech.rom.basis import Basis, inner_product, positive, reference_state, zero_imposed
from lungmech.rom.load_paths import collected


def snapshots(
    model: Model,
    stepping: Stepping,
    scales: Sequence[float | Sequence[float]] = (1.0,),
    options: NewtonOptions | None = None,
    solver: NewtonSolver | None = None,
    start: np.ndarray | None = None,
    parameters: Sequence[Mapping[str, float]] = ({},),
) -> np.ndarray:
    """Full-order states minus the start state, at every accepted step of one run per parameter
    point and scale: :meth:`FullOrderModel.solve <lungmech.fem.parametric.FullOrderModel.solve>`
    from ``start`` (a state array, an equilibrium at the default parameters; default: unloaded),
    whose approach to the point's parameters gives snapshots too. A scale multiplies the loads'
    change since the start (a number: all loads; a sequence: one factor per load), so the training
    set spans parameters and load amplitudes as well as the load history. Returns the owned rows,
    shape (owned dofs, snapshots); the model is left at the start state, at its default
    parameters.
    """
    if not scales or not parameters:
        raise ParameterError("snapshots: give at least one load scale and one parameter point")
    start = reference_state(model) if start is None else start.copy()
    full = FullOrderModel(model, stepping, options, start=start, solver=solver)
    return collected(full, [(point, scale) for point in parameters for scale in scales])


def pod(
    model: Model,
    data: np.ndarray,
    inner: str = "mass",
    size: int | None = None,
    energy: float | None = None,
    source: dict | None = None,
) -> Basis:
    """The POD basis of the snapshot columns ``data``, orthonormal in ``inner``.

    Method of snapshots: C = Sᵀ W S = Q Σ² Qᵀ, modes S Q Σ⁻¹. Directions below 1e-7 of the
    largest singular value are numerical noise of C and are dropped; ``size`` or ``energy``
    (fraction of Σσ² to keep) truncates further. ``values`` are the singular values.
    """
    comm = model.geometry.mesh.comm
    if data.ndim != 2 or data.shape[0] != owned_size(model.space):
        raise ParameterError("pod: snapshots must be (owned dofs of the model, number of snapshots)")
    data = zero_imposed(model, data.copy())
    W = inner_product(model, inner)
    try:
        with positive(inner):
            decomposition = linalg.pod(data, W, comm)
    finally:
        if W is not None:
            W.destroy()
    if not decomposition.values.size:
        raise ParameterError("pod: the snapshots are all zero (did the loads act?)")
    source = (source or {}) | {"snapshots": data.shape[1], "singular_values": decomposition.spectrum.tolist()}
    basis = Basis(decomposition.modes, decomposition.values, "pod", inner, layout(model.space).fingerprint, source)
    if size is not None or energy is not None:
        basis = basis.truncate(size=size if size is None else min(size, basis.size), energy=energy)
    return basis
