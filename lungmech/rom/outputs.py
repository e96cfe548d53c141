"""A hyper-reduced model's outputs from reduced operators: no full field is formed online.

The state of a reduced model is affine in a few numbers,

.. math:: x = r + Z z,   Z = [V, D],   z = (q, a(t)),

q the reduced coordinates and a the imposed displacements' factors amplitude · ramp(t), D their
directions (each constraint's imposed values at factor 1) and r the start state with the
imposed dofs at 0. The outputs of :class:`~lungmech.fem.parametric.Outputs` follow:

* **probes** are linear in x: p(z) = p(r) + Σ z_i p(Z_i), exact;
* **the volume** ∫ det F dX is a cubic polynomial of x (F is affine in the state, det a cubic;
  a quadratic in 2-D), so exactly
  f(z) = c₀ + c₁·z + ½ zᵀC₂z + ⅙ C₃[z, z, z] with c₁ = Zᵀ∇f(r), C₂ = Zᵀ∇²f(r)Z and
  C₃[i] = Zᵀ(∇²f(r + Z_i) − ∇²f(r))Z: k + 2 assemblies offline (:func:`cubic`), checked at a
  random z (:mod:`lungmech.rom.exact`; over a shape map, in (z, a): :mod:`lungmech.rom.shaped`);
* **the strain energy** ∫ ψ dX is not polynomial: it is sampled as an ECSW functional
  (:attr:`lungmech.rom.ecsw.WeightedForms.functionals`) and summed on the reduced mesh;
* **the formulation's averages** (:mod:`lungmech.fem.averages`) are ratios: their numerators
  ∫ f w dX are sampled functionals alike, their denominators exact, the reference volume (a
  number of the whole body) or the current volume (the cubic above);
* **the loads** are the model's scalar load values (no field).

On an imaged body (:mod:`lungmech.rom.imaged`) u = w − ξ(μ): the probes above are those of the
motion w, and ξ at them, with the reference volume, comes from the reduced inverse motion
(:class:`Reference`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from mpi4py import MPI

import numpy as np
import ufl

from lungmech.fem.averages import averages
from lungmech.fem.model import Model
from lungmech.fem.parametric import UNITS
from lungmech.fem.quantities import Probe
from lungmech.fem.sensitivity import ValueDerivatives
from lungmech.rom import shaped
from lungmech.rom.basis import origin
from lungmech.rom.ecsw import AVERAGE
from lungmech.rom.exact import Cubic, cubic
from lungmech.rom.whole import Arrays

if TYPE_CHECKING:  # (it imports this module)
    from lungmech.rom.hyper_reduced import HyperReducedSolver

__all__ = ["OnPoints", "ReducedOutputs", "Reference", "imposed_directions"]


class Reference(Protocol):
    """An imaged body's reference at the current μ, as a reduced model has it."""

    def reference_volume(self) -> float:
        """∫ det(I + ∇ξ) dx (m³; m³/m in 2-D)."""
        ...

    def reference_map_at(self, probe: Callable[[], Probe]) -> OnPoints:
        """ξ at the points of ``probe()`` now, (points, 3) in m, as a function of the reduced
        state, and its derivative with respect to μ (``probe`` is called on the whole body only)."""
        ...


@dataclass(frozen=True)
class OnPoints:
    """A field at points, (points, 3), as it is now (``value()``) and its derivative with
    respect to μ at the last placement (``derivative()``, the parameters on a last axis)."""

    value: Callable[[], np.ndarray]
    derivative: Callable[[], np.ndarray]


def imposed_directions(model: Model, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """r, D and the constraints they cover, with origin(model, reference) = r + D a for a the
    factors of those constraints (:meth:`~lungmech.fem.model.Model.imposed_amplitudes`): r the
    reference with every imposed dof at 0, D (full local arrays, columns) what each constraint
    imposes at factor 1 where it has the last word (conditions are set in order). Constraints
    that impose 0 (clamps, symmetry) are left out. Collective; the imposed values are kept."""
    imposed = model.imposed
    saved = [i.target.x.array.copy() for i in imposed]

    def at(factors: np.ndarray) -> np.ndarray:
        for i, factor in zip(imposed, factors):
            i.target.x.array[i.where] = factor * i.base
        return origin(model, reference)

    try:
        count = len(imposed)
        r = at(np.zeros(count))
        directions = [at(np.eye(count)[c]) - r for c in range(count)]
    finally:
        for i, values in zip(imposed, saved):
            i.target.x.array[:] = values
    comm = model.geometry.mesh.comm
    kept = np.array([c for c in range(len(imposed)) if comm.allreduce(bool(np.any(directions[c])), op=MPI.LOR)], int)
    D = np.column_stack([directions[c] for c in kept]) if kept.size else np.zeros((len(r), 0))
    return r, D, kept


class ReducedOutputs:
    """The outputs of :class:`~lungmech.fem.parametric.Outputs` of a hyper-reduced solver's
    state (its q, the model's time), from reduced operators (collective; offline: O(k) full
    assemblies, through the solver's :attr:`whole`, which keeps them, or gives them back on a
    body of sampled cells: :mod:`lungmech.rom.whole`). ``solver`` is a
    :class:`~lungmech.rom.hyper_reduced.HyperReducedSolver`; ``probes`` points or a
    :class:`~lungmech.fem.quantities.Probe` (material points) located already; ``reference``
    an imaged body's reference at μ (:class:`Reference`)."""

    def __init__(
        self,
        solver: HyperReducedSolver,
        probes: Sequence[Sequence[float]] | Probe = (),
        reference: Reference | None = None,
    ) -> None:
        model = self.model = solver.model
        self.solver, self.reference = solver, reference
        # the averages whose numerators the sample has cells for (not a file of an older build)
        self._averages = {name: a for name, a in averages(model).items() if AVERAGE + name in solver.sample.cells}
        # the whole body's, on a body of sampled cells; an imaged body's at μ
        self._reference_volume = model.geometry.volume if reference is None else reference.reference_volume
        self.units = dict(UNITS) | {f"averages/{name}": a.unit for name, a in self._averages.items()}
        owned = solver.basis.vectors.shape[0]
        start, imposed, self._constraints = solver.whole.imposed()
        directions = np.hstack([solver.basis.vectors, imposed[:owned]])

        def volume() -> Arrays:
            if model.shape is None:
                return cubic(model, ufl.det(model.F) * model.dx, start, directions).arrays()
            return shaped.volume(model, ufl.det(model.F) * model.dx, start, directions).arrays()  # in (z, a)

        self._volume = Cubic.of(solver.whole.get("volume", volume))
        if model.shape is not None and reference is None:  # ∫ det G dx̂, a cubic in a
            at_rest = Cubic.of(solver.whole.get("reference_volume", lambda: shaped.mesh_volume(model).arrays()))
            self._reference_volume = lambda: at_rest(self._shape())

        def located() -> Arrays:
            probe = (
                probes if isinstance(probes, Probe) else (Probe(model.geometry.mesh, probes) if len(probes) else None)
            )
            if probe is None:
                return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, directions.shape[1]))

            def displacement_at(x: np.ndarray) -> np.ndarray:
                model.state.x.array[:] = x
                model.state.x.scatter_forward()
                return probe(model.motion())  # w of an image (ξ at the probes is the Reference's)

            with model.kept_state():
                at_start = displacement_at(start)
                each = []
                for column in directions.T:
                    x = np.zeros_like(start)
                    x[:owned] = column
                    each.append(displacement_at(x))
            return np.asarray(probe.points, dtype=float), at_start, np.stack(each, axis=-1)

        points, at_start, each = solver.whole.get("probes", located)
        self.probe_points = tuple(tuple(float(c) for c in p) for p in points)
        self._probes = (at_start, each) if len(points) else None  # p(r), and p(Z_i) on the last axis
        self._reference_map: OnPoints | None = None  # ξ at the probes
        if reference is not None and len(points):  # located on the whole body only
            self._reference_map = reference.reference_map_at(
                lambda: probes if isinstance(probes, Probe) else Probe(model.geometry.mesh, probes)
            )

    def derivatives(self, dq: np.ndarray, derivatives: ValueDerivatives) -> dict[str, object]:
        """d(outputs)/dμ from dq/dμ (k, parameters) and the model's value derivatives
        (:class:`~lungmech.fem.sensitivity.ValueDerivatives`), in the structure of
        :func:`~lungmech.fem.sensitivity.output_derivatives`: with dz/dμ = (dq/dμ, dc/dμ), the
        volume's ∇f(z, a) · d(z, a)/dμ, the probes' P dz/dμ, the sampled energy's derivative and the loads'.
        Collective."""
        dz = np.vstack([dq, derivatives.amplitudes[self._constraints]])
        on_shape = np.vstack([dz, self._shape_derivatives(derivatives)])  # the volume's (z, a)
        result: dict[str, object] = {
            "volume": self._volume.gradient(self._with_shape(self.coordinates())) @ on_shape,
            "strain_energy": self.solver.sensitivities.energy(dq, derivatives),
        }
        if self._probes is not None:  # on an image u = w − ξ: du/dμ = dw/dμ − dξ/dμ
            moved = self._probes[1] @ dz
            result["probes"] = moved if self._reference_map is None else moved - self._reference_map.derivative()
        result["loads"] = {label: d.copy() for label, d in derivatives.loads.items()}
        return result

    def coordinates(self) -> np.ndarray:
        """z = (q, c): the solver's q and the imposed displacements' factors c now."""
        return np.concatenate([self.solver.state, self.model.imposed_amplitudes()[self._constraints]])

    def _with_shape(self, z: np.ndarray) -> np.ndarray:
        """(z, a): the volume's variables, a the shape coefficients now (none without a shape map)."""
        return np.concatenate([z, self._shape()])

    def _shape(self) -> np.ndarray:
        """The shape coefficients a now (none without a shape map)."""
        return np.zeros(0) if self.model.shape is None else self.model.shape.values()

    def _shape_derivatives(self, derivatives: ValueDerivatives) -> np.ndarray:
        """da/dμ (modes, parameters): each coefficient's row from the values' derivatives."""
        count = len(derivatives.names)
        if self.model.shape is None:
            return np.zeros((0, count))
        return np.array([derivatives.constants.get(c, np.zeros(count)) for c in self.model.shape.coefficients])

    def __call__(self) -> dict[str, object]:
        z = self.coordinates()
        volume, sampled = self._volume(self._with_shape(z)), self.solver.functionals(self.solver.state)
        values: dict[str, object] = {"volume": volume, "strain_energy": sampled["strain_energy"]}
        if self._probes is not None:
            moved = self._probes[0] + self._probes[1] @ z
            values["probes"] = moved if self._reference_map is None else moved - self._reference_map.value()
        values["loads"] = self.model.scalar_loads()
        if self._averages:
            per = {"reference": self._reference_volume(), "current": volume}
            values["averages"] = {
                name: sampled[AVERAGE + name] / per[average.per] for name, average in self._averages.items()
            }
        return values
