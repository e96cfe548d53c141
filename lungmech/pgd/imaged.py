"""An imaged body's reference in a PGD fitted to full solves: ξ(μ) beside the breath.

On an imaged body (:mod:`lungmech.fem.inverse_motion`) each full solve finds at μ the inverse
problem's state x_ξ(μ) — the unloaded reference X = x + ξ(μ) of the image, and the image's
other fields — and then the breath x(t; μ) from the image, w = 0 at t₀. A fitted PGD
(:mod:`lungmech.pgd.fitted`) fits both, each by its own separated terms:

    x(t; μ) ≈ x_rest + Q R (q(μ) ∘ τ(t)),   t ∈ {t₀, the output times},
    x_ξ(μ) ≈ x_ξ,rest + Q_ξ a(μ),           a(μ) = R_ξ q_ξ(μ),

the breath from t₀ on, where it is the image (w = 0) with x_ξ(μ)'s other fields
(:func:`image_states`). The outputs are exact functions of (z, a):

* the displacement from the reference at the probes, u = w − ξ: w's part linear in z
  (:class:`~lungmech.pgd.online.Online`), ξ's affine in a (:class:`Reference`);
* the reference volume ∫ det(I + ∇ξ) dx, a cubic in a (:func:`lungmech.rom.exact.cubic`);
* the volume from the image, ∫ det(I + ∇w) dx, a cubic in z alone, as every model's.

Over a population's shape map (an image of the template moved by s, :mod:`lungmech.rom.shaped`)
each volume is a cubic in its coordinates and the shape coefficients together, and the image's
own volume ∫ det(I + ∇s) dx̂ a cubic in the shape coefficients.

:func:`reference` makes the :class:`Reference` of a fitted ξ; :meth:`Reference.hand_over`
puts ξ(μ) into the breath's model for a full field.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from dolfinx import fem

from lungmech.fem.inverse_motion import Handover, InverseMotion, vector_entries
from lungmech.fem.model import Model
from lungmech.fem.parametric import FullOrderModel
from lungmech.fem.quantities import Probe, strain_energy
from lungmech.fem.start import StartReport
from lungmech.parallel.owned import owned_size
from lungmech.pgd.decomposition import Decomposition
from lungmech.rom import shaped
from lungmech.rom.exact import Cubic, affine, cubic
from lungmech.rom.load_paths import LoadPath

__all__ = ["Reference", "constant", "image_states", "reference", "start_energies"]


@dataclass(frozen=True)
class Reference:
    """ξ(μ) of an imaged body as a fitted ``decomposition`` of its inverse problem's state
    (modes: owned rows, relative to that model's rest state ``rest``, a full local array):
    ``probes`` ξ at the probe points, (p₀, P) with ξ = p₀ + P a (a row per point and component;
    m), ``volume`` the reference volume, a cubic in a (m³; m³/m in 2-D), ``imaged`` the
    image's volume and ``body`` what the body is called ("lung"). Over a shape map (``shape``
    coefficients), ``volume`` is a cubic in (a, the shape coefficients) and ``imaged`` in the
    shape coefficients; without, ``imaged`` is a constant."""

    decomposition: Decomposition
    rest: np.ndarray
    probes: tuple[np.ndarray, np.ndarray]
    volume: Cubic
    imaged: Cubic
    body: str = "body"
    shape: int = 0

    def at_probes(self, mu: Mapping[str, float]) -> np.ndarray:
        """ξ at the probe points (a row per point and component; m)."""
        p0, P = self.probes
        return p0 + P @ self.decomposition.factors(mu)

    def probe_derivatives(self, mu: Mapping[str, float]) -> np.ndarray:
        """dξ/dμ at the probe points (a row per point and component × parameters; m per unit)."""
        return self.probes[1] @ self.decomposition.factor_derivatives(mu)

    def start(self, mu: Mapping[str, float], shape: np.ndarray) -> StartReport:
        """What the start is at ``mu`` (and the ``shape`` coefficients it sets; none without a
        shape map): the image on its fitted reference, with both volumes (m³)."""
        factors = self.decomposition.factors(mu)
        details = {
            "imaged_volume": self.imaged(shape),
            "reference_volume": self.volume(np.concatenate([factors, shape]) if self.shape else factors),
        }
        return StartReport(
            "imaged", f"the imaged {self.body} (its unloaded reference from the PGD's fit of it)", 0, details
        )

    def hand_over(self, model: Model, mu: Mapping[str, float]) -> None:
        """ξ(μ) as ``model``'s reference map (a model of the image's motion; collective)."""
        state = fem.Function(model.space)  # the inverse problem's space, numbered alike (Handover checks)
        d = self.decomposition
        state.x.array[:] = self.rest
        state.x.array[: d.modes.shape[0]] += d.modes @ d.factors(mu)
        state.x.scatter_forward()
        vector = vector_entries(model)
        assert model.reference_map is not None  # (a model of an image's motion)
        model.set_reference_map(state.x.array[vector][: owned_size(model.reference_map.function_space)])

    def arrays(self) -> dict[str, np.ndarray]:
        """Its small arrays by name, for a model file (the modes and the rest state go by the
        mesh's canonical order)."""
        p0, P = self.probes
        names = ("c0", "c1", "c2", "c3")
        found = {"reduced": self.decomposition.reduced, "probes0": p0, "probes": P, "shape": np.array([self.shape])}
        found |= {f"volume/{name}": c for name, c in zip(names, self.volume.arrays())}
        return found | {f"imaged/{name}": c for name, c in zip(names, self.imaged.arrays())}


def image_states(full: FullOrderModel, solved: Sequence[LoadPath]) -> np.ndarray:
    """Each imaged path's start x₀(μ), the image (w = 0) with its inverse problem's other
    fields (owned rows, a column per path): what the hand-over makes of x_ξ(μ)."""
    owned = owned_size(full.model.space)
    vector = vector_entries(full.model)
    vector = vector[vector < owned]
    columns = []
    for path in solved:
        assert path.inverse is not None  # (an imaged body's path)
        x0 = path.inverse.copy()
        x0[vector] = 0.0
        columns.append(x0)
    return np.column_stack(columns)


def start_energies(full: FullOrderModel, solved: Sequence[LoadPath]) -> np.ndarray:
    """Each imaged path's strain energy at t₀ (J): the image on its reference ξ(μ), which a
    path's outputs (at the output times) leave out. Collective; the model is reset."""
    start = full.start
    assert isinstance(start, InverseMotion)  # (an imaged body's full model)
    model, inverse = full.model, start.inverse
    handover, energy, owned = Handover(model, inverse), strain_energy(model), owned_size(inverse.space)
    found = []
    for path in solved:
        assert path.inverse is not None
        inverse.state.x.array[:owned] = path.inverse
        inverse.state.x.scatter_forward()
        model.set_parameters(path.solution.parameters)
        handover.hand_over(inverse, model)
        model.set_time(full.stepping.start)
        found.append(energy())
    full.reset()
    return np.array(found)


def reference(full: FullOrderModel, decomposition: Decomposition, probe: Probe | None) -> Reference:
    """The :class:`Reference` of ``decomposition``, a fit of ``full``'s inverse problem's
    state from its rest state, with ξ at ``probe``'s points (located on the image). Collective;
    the inverse problem's state is kept."""
    start = full.start
    assert isinstance(start, InverseMotion)  # (an imaged body's full model)
    inverse = start.inverse
    with inverse.kept_state():
        inverse.reset()
        rest = inverse.state.x.array.copy()
    modes = decomposition.modes
    at_rest = fem.Constant(inverse.geometry.mesh, 1.0) * inverse.dx
    if inverse.shape is None:
        volume, imaged, shape = cubic(inverse, at_rest, rest, modes), constant(full.model.geometry.volume()), 0
    else:  # on a template: in (a, the shape coefficients)
        volume, imaged = shaped.volume(inverse, at_rest, rest, modes), shaped.mesh_volume(full.model)
        shape = len(inverse.shape.modes)
    if probe is not None:  # u = −ξ in the inverse problem
        p0, P = affine(inverse, lambda: -probe(inverse.displacement()), rest, modes)
    else:
        p0, P = np.zeros(0), np.zeros((0, modes.shape[1]))
    return Reference(decomposition, rest, (p0, P), volume, imaged, start.body, shape)


def constant(value: float) -> Cubic:
    """``value`` as a cubic in no coordinate."""
    return Cubic(float(value), np.zeros(0), np.zeros((0, 0)), np.zeros((0, 0, 0)))
