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
  random z;
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
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix

from lungmech import jit
from lungmech.errors import ParameterError
from lungmech.fem.averages import averages
from lungmech.fem.model import Model
from lungmech.fem.parametric import UNITS
from lungmech.fem.quantities import Probe, assemble_owned
from lungmech.fem.sensitivity import ValueDerivatives
from lungmech.parallel.linalg import apply, gram
from lungmech.rom.basis import origin
from lungmech.rom.ecsw import AVERAGE
from lungmech.rom.whole import Arrays

if TYPE_CHECKING:  # (it imports this module)
    from lungmech.rom.hyper_reduced import HyperReducedSolver

__all__ = ["Cubic", "OnPoints", "ReducedOutputs", "Reference", "affine", "cubic", "imposed_directions"]


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


@dataclass(frozen=True)
class Cubic:
    """f(z) = c₀ + c₁·z + ½ zᵀC₂z + ⅙ C₃[z, z, z], C₂ and C₃ symmetric."""

    c0: float
    c1: np.ndarray
    c2: np.ndarray
    c3: np.ndarray

    def __call__(self, z: np.ndarray) -> float:
        return float(self.c0 + self.c1 @ z + 0.5 * z @ self.c2 @ z + np.einsum("ijk,i,j,k", self.c3, z, z, z) / 6)

    def gradient(self, z: np.ndarray) -> np.ndarray:
        """∂f/∂z = c₁ + C₂z + ½ C₃[·, z, z]."""
        return self.c1 + self.c2 @ z + 0.5 * np.einsum("ijk,j,k->i", self.c3, z, z)


def cubic(model: Model, functional: ufl.Form, start: np.ndarray, directions: np.ndarray, check: float = 1e-9) -> Cubic:
    """The functional f(start + Z z) (a 0-form of ``model.state``, a polynomial of degree ≤ 3 in
    it) as a :class:`Cubic` in z, from its derivatives: ``start`` a full local state array,
    ``directions`` Z the owned rows of the directions (columns). Collective; the model's state is
    kept. A functional that is not a cubic of the state (off by more than ``check`` relative at
    a random z) is an error."""
    state, comm = model.state, model.geometry.mesh.comm
    owned, size = directions.shape
    gradient = ufl.derivative(functional, state, ufl.TestFunction(model.space))
    compiled = jit.form(functional), jit.form(gradient)
    hessian = jit.form(ufl.derivative(gradient, state, ufl.TrialFunction(model.space)))
    scratch = fem.Function(model.space).x

    def at(z: np.ndarray) -> None:
        state.x.array[:] = start
        state.x.array[:owned] += directions @ z
        state.x.scatter_forward()

    def value() -> float:
        return comm.allreduce(fem.assemble_scalar(compiled[0]), op=MPI.SUM)

    def projected_hessian() -> np.ndarray:
        H = assemble_matrix(hessian)
        H.assemble()
        reduced = gram(directions, apply(H, directions, comm), comm)
        H.destroy()
        return reduced

    with model.kept_state():
        at(np.zeros(size))
        c0 = value()
        c1 = gram(directions, assemble_owned(compiled[1], scratch, owned)[:, None], comm)[:, 0]
        c2 = projected_hessian()
        c3 = np.empty((size, size, size))
        for i in range(size):
            at(np.eye(size)[i])
            c3[i] = projected_hessian() - c2
        result = Cubic(c0, c1, c2, c3)
        z = _test_point(directions, comm)
        at(z)
        exact = value()
    off = comm.allreduce(abs(result(z) - exact), op=MPI.MAX)  # one decision for all ranks
    if off > check * max(abs(exact), abs(c0), np.finfo(float).tiny):
        raise ParameterError(
            f"this functional is not a cubic polynomial of the state (off by {off:.2e} at a test "
            "point): it cannot be reduced exactly"
        )
    return result


def affine(
    model: Model, evaluate: Callable[[], np.ndarray], start: np.ndarray, directions: np.ndarray, check: float = 1e-9
) -> tuple[np.ndarray, np.ndarray]:
    """(f₀, F₁) with f(start + Z z) = f₀ + F₁ z for a vector functional ``evaluate()`` of the
    model's state that is affine in it (e.g. ∫ρ₀ x dX): k + 2 evaluations, the last a check at
    a random z (a functional that is not affine is an error). Collective; the state is kept."""
    state, comm = model.state, model.geometry.mesh.comm
    owned, size = directions.shape

    def at(z: np.ndarray) -> np.ndarray:
        state.x.array[:] = start
        state.x.array[:owned] += directions @ z
        state.x.scatter_forward()
        return np.asarray(evaluate(), dtype=float).reshape(-1)

    with model.kept_state():
        f0 = at(np.zeros(size))
        F1 = np.column_stack([at(unit) - f0 for unit in np.eye(size)]) if size else np.zeros((f0.size, 0))
        z = _test_point(directions, comm)
        off = np.abs(at(z) - (f0 + F1 @ z)).max(initial=0.0)
    if off > check * max(np.abs(f0).max(initial=0.0), np.finfo(float).tiny):
        raise ParameterError(f"this functional is not affine in the state (off by {off:.2e} at a test point)")
    return f0, F1


def _test_point(directions: np.ndarray, comm: MPI.Comm) -> np.ndarray:
    """A random z of moderate size, the same on every rank: each direction moves the body ~10 %."""
    largest = np.empty(directions.shape[1])
    comm.Allreduce(np.abs(directions).max(axis=0, initial=0.0), largest, op=MPI.MAX)
    return np.random.default_rng(0).uniform(-0.1, 0.1, directions.shape[1]) / np.where(largest > 0, largest, 1.0)


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
            found = cubic(model, ufl.det(model.F) * model.dx, start, directions)
            return np.array(found.c0), found.c1, found.c2, found.c3

        c0, c1, c2, c3 = solver.whole.get("volume", volume)
        self._volume = Cubic(float(c0), c1, c2, c3)

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
        :func:`~lungmech.fem.sensitivity.output_derivatives`: with dz/dμ = (dq/dμ, da/dμ), the
        volume's ∇f(z) · dz/dμ, the probes' P dz/dμ, the sampled energy's derivative and the loads'.
        Collective."""
        dz = np.vstack([dq, derivatives.amplitudes[self._constraints]])
        result: dict[str, object] = {
            "volume": self._volume.gradient(self.coordinates()) @ dz,
            "strain_energy": self.solver.sensitivities.energy(dq, derivatives),
        }
        if self._probes is not None:  # on an image u = w − ξ: du/dμ = dw/dμ − dξ/dμ
            moved = self._probes[1] @ dz
            result["probes"] = moved if self._reference_map is None else moved - self._reference_map.derivative()
        result["loads"] = {label: d.copy() for label, d in derivatives.loads.items()}
        return result

    def coordinates(self) -> np.ndarray:
        """z = (q, a): the solver's q and the imposed displacements' factors now."""
        return np.concatenate([self.solver.state, self.model.imposed_amplitudes()[self._constraints]])

    def __call__(self) -> dict[str, object]:
        z = self.coordinates()
        volume, sampled = self._volume(z), self.solver.functionals(self.solver.state)
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
