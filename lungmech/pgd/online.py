"""The outputs of a PGD model's state u = u_rest + Q z as exact functions of the modes'
coefficients z, made once offline (:class:`Online`):

* the volume ∫ det F dX, a cubic of z (:func:`lungmech.rom.exact.cubic`); over a population's
  shape map, a cubic of (z, a) together, a the shape coefficients (:mod:`lungmech.rom.shaped`);
* the probes' displacements, linear in z;
* the strain energy ½ zᵀ A(μ) z of a linear model, A(μ) = Σₖ wₖ(μ) (A₀ₖ + Σₑ cₑ(μ) Aₑₖ): Aₑₖ = Qᵀ Kₑₖ Q
  the terms' operators projected, cₑ(μ) the values the model's parameters set and wₖ the
  Chebyshev polynomials of the curves' parameters, their products over several (one 1 without a
  curve, :mod:`lungmech.pgd.terms`); checked against the model's own ∫ψ dX at a random point;
* a linear model's error indicator at every μ (:mod:`lungmech.pgd.indicator`'s η, without an
  assembly): the residual R = Σₖ wₖ [(K₀ₖ + Σₑ cₑ Kₑₖ) Q z − (f₀ₖ + Σₑ cₑ fₑₖ)] is Σ θ_b v_b, θ
  the products wₖ cₑ zᵢ and wₖ cₑ, v_b the columns Kₑₖ Q and −fₑₖ, so that
  ‖R‖²_{W⁻¹} = θᵀ G θ with G = Vᵀ W⁻¹ V made once offline, and η = √(θᵀ G θ) / ‖z‖ (the
  modes W-orthonormal). The small residual of a converged PGD is a difference of large
  squares there: θᵀ G θ resolves it down to about 10⁻¹⁵ |θ|ᵀ|G||θ| (W⁻¹'s own round-off, its
  solves not symmetric to the last digit, is of that order), and η is reported no lower than
  that floor, never 0. G is kept up to :data:`RESIDUAL_SIZE` columns and
  :data:`RESIDUAL_MEMORY` of work; beyond, an answer carries the estimate made at a sample of
  the box.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import cast

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import ufl

from lungmech.errors import ParameterError
from lungmech.fem.linear import factorised
from lungmech.fem.model import Model
from lungmech.fem.quantities import Probe, strain_energy
from lungmech.parallel.linalg import apply, gram
from lungmech.pgd import chebyshev
from lungmech.pgd import terms as separated
from lungmech.rom import shaped
from lungmech.rom.exact import Cubic, affine, cubic

__all__ = ["Online", "online"]

ENERGY_CHECK = 1e-9  # the quadratic form's strain energy against the model's own, relative
INDEPENDENT = 1e-14  # the projected operators' singular values below this fraction of the largest are round-off
RESIDUAL_SIZE = 600  # the residual's Gram matrix up to this many columns (2.9 MB; its product a point ≤ 0.1 ms)
RESIDUAL_MEMORY = 2**28  # bytes a rank may hold for V and W⁻¹ V while G is made (owned rows × columns × 16)
RESOLVED = 1e-15  # θᵀ G θ below this fraction of |θ|ᵀ|G||θ| is round-off


@dataclass(frozen=True)
class Online:
    """The outputs of u = Q z as functions of z: ``volume`` (m³), ``probes`` (m: a row per
    point and component, × m), ``energy`` (J: for each multi-index k of the curves' series, A₀ₖ
    then each entry's Aₑₖ; degrees × (1 + entries) × m × m) for the values ``entries`` (indices
    into :func:`lungmech.pgd.terms.values`), ``curves`` the axes of the series and ``degrees``
    each one's number of coefficients (:class:`lungmech.pgd.terms.Curve`; none: one degree);
    ``shape``: the number of shape coefficients a after z among the volume's coordinates (0: no
    shape map); ``residual`` the residual's Gram matrix G (module docstring; 0 × 0: none kept)."""

    volume: Cubic
    probes: np.ndarray
    energy: np.ndarray
    entries: np.ndarray
    curves: tuple[int, ...] = ()
    degrees: tuple[int, ...] = ()
    shape: int = 0
    residual: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def arrays(self) -> dict[str, np.ndarray]:
        """Its arrays by name, for a model file."""
        c0, c1, c2, c3 = self.volume.arrays()
        return {"volume/c0": c0, "volume/c1": c1, "volume/c2": c2, "volume/c3": c3} | {
            "probes": self.probes,
            "energy": self.energy,
            "entries": self.entries,
            "curve": np.array(self.curves or (-1,)),
            "curve_degrees": np.array(self.degrees, dtype=int),
            "shape": np.array([self.shape]),
            "residual": self.residual,
        }

    @classmethod
    def of(cls, arrays: Mapping[str, np.ndarray]) -> Online:
        """The :class:`Online` of its :meth:`arrays` (a file without a curve: one degree; with one
        curve and no degrees, that curve's all; without a shape: none)."""
        volume = Cubic.of(tuple(arrays[f"volume/{name}"] for name in ("c0", "c1", "c2", "c3")))
        energy = arrays["energy"]
        energy = energy if energy.ndim == 4 else energy[None]
        curves = tuple(int(a) for a in arrays.get("curve", ()) if a >= 0)
        degrees = tuple(int(n) for n in arrays.get("curve_degrees", (len(energy),) if curves else ()))
        shape = int(arrays["shape"][0]) if "shape" in arrays else 0
        entries = arrays["entries"].astype(int)
        residual = arrays["residual"] if "residual" in arrays else np.zeros((0, 0))
        return cls(volume, arrays["probes"], energy, entries, curves, degrees, shape, residual)

    def indicator(self, c: np.ndarray, weights: np.ndarray, z: np.ndarray) -> float | None:
        """η at the state Q z with the values ``c`` of :attr:`entries` and the curve's
        ``weights`` (module docstring); None where no Gram matrix is kept."""
        if not self.residual.size:
            return None
        value, degree, moded, modes, G, scales = self._residual_kept
        theta = np.concatenate([[1.0], c])[value] * weights[degree]  # θ on the kept columns: wₖ cₑ zᵢ,
        theta[moded] *= z[modes]  # or wₖ cₑ for a load's
        floor = RESOLVED * float(np.abs(theta) @ scales) ** 2  # |θ|ᵀ|G||θ| ≤ (Σ |θ_b| √G_bb)²
        size = math.sqrt(float(z @ z))
        return math.sqrt(max(float(theta @ G @ theta), floor)) / size if size > 0 else math.inf

    @functools.cached_property
    def _residual_kept(self) -> tuple[np.ndarray, ...]:
        """The Gram matrix's columns that are not 0 (a value's absent block): each one's value
        (0: the constant part, e + 1: entry e) and degree, the kept columns of a mode and that
        mode (the others are the loads'), G on them and √G_bb."""
        m, n = self.energy.shape[-1], 1 + len(self.entries)
        count = self.energy.shape[0] * self.energy.shape[1]
        kept = np.flatnonzero(np.abs(self.residual).max(axis=0) > 0)
        loads = kept >= count * m
        blocks = np.where(loads, kept - count * m, kept // m)
        moded = np.flatnonzero(~loads)
        G = self.residual[np.ix_(kept, kept)]
        return blocks % n, blocks // n, moded, kept[moded] % m, G, np.sqrt(np.maximum(np.diag(G), 0.0))

    def volume_at(self, z: np.ndarray, a: np.ndarray) -> float:
        """The volume at the state Q z and the shape a (m³)."""
        return self.volume(np.concatenate([z, a]) if self.shape else z)

    def rest_volume(self, a: np.ndarray) -> float:
        """The volume at rest (z = 0) at the shape a (m³): the volume's cubic on a alone."""
        return self._at_rest(a) if self.shape else self.volume.c0

    @functools.cached_property
    def _at_rest(self) -> Cubic:
        """The volume's cubic restricted to the shape coefficients a (its last :attr:`shape`
        coordinates)."""
        m, volume = len(self.volume.c1) - self.shape, self.volume
        return Cubic(volume.c0, volume.c1[m:], volume.c2[m:, m:], volume.c3[m:, m:, m:])

    def volume_derivatives(self, z: np.ndarray, a: np.ndarray, dz: np.ndarray, da: np.ndarray) -> np.ndarray:
        """d(volume)/dμ from dz/dμ (m × parameters) and da/dμ (shape × parameters)."""
        if not self.shape:
            return self.volume.gradient(z) @ dz
        gradient = self.volume.gradient(np.concatenate([z, a]))
        return gradient[: len(z)] @ dz + gradient[len(z) :] @ da

    def weights(self, units: np.ndarray, along: int | None = None) -> np.ndarray:
        """Π T_{kⱼ} over the curves' axes j at the point of unit coordinates ``units``, one per
        multi-index k (:func:`lungmech.pgd.chebyshev.tensor`), or its derivative in the unit
        coordinate of axis ``along`` (0 off the curves)."""
        if along is not None and along not in self.curves:
            return np.zeros(len(self.energy))
        at = None if along is None else self.curves.index(along)
        return chebyshev.tensor([units[j] for j in self.curves], self.degrees, at)

    def operator(self, c: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """A(c) = Σₖ wₖ (A₀ₖ + Σₑ cₑ Aₑₖ) (m × m), ``c`` the values of :attr:`entries`, ``weights``
        wₖ from :meth:`weights`: mixed in the operators' few independent combinations
        (:attr:`_combinations`)."""
        m = self.energy.shape[-1]
        mixed = np.outer(weights, np.concatenate([[1.0], c])).ravel()
        into, combinations = self._combinations
        return ((mixed @ into) @ combinations).reshape(m, m)

    def energy_and_volume(self, c: np.ndarray, weights: np.ndarray, z: np.ndarray) -> tuple[float, np.ndarray | None]:
        """(zᵀ A(c) z, the volume's powers (c₀, c₁·z, ½ C₂[z, z], ⅙ C₃[z, z, z])), so that the
        volume at the state s z is Σᵢ sⁱ powersᵢ (a linear model's state at any time a multiple
        of that at the path's end), without A (:meth:`operator`): one product of the pairs
        zⱼzₖ, j ≤ k, with the operators' independent combinations Cⱼ (zᵀ A z = Σⱼ βⱼ zᵀCⱼz) and
        the volume's C₃ and C₂ on the same pairs, stacked. Over a shape map the powers are None:
        the volume is a cubic of (z, a), a fixed along the path (:meth:`volume_at`)."""
        into, stacked, (j, k) = self._stacked
        found = stacked @ (z[j] * z[k])
        mixed = (weights @ into).reshape(len(c) + 1, -1)  # (1 + entries) × combinations: Σₖ wₖ, then the values
        n = mixed.shape[1]
        energy = float((mixed[0] + c @ mixed[1:]) @ found[:n])
        if self.shape:
            return energy, None
        volume = self.volume
        return energy, np.array([volume.c0, volume.c1 @ z, 0.5 * found[-1], (found[n:-1] @ z) / 6])

    @functools.cached_property
    def _stacked(self) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """The combinations Cⱼ on the pairs j ≤ k, an off-diagonal pair's twice, then (without a
        shape map) the volume's C₃ and C₂ there (``Cubic.on_pairs``): (into, degrees × (values ·
        combinations); (combinations [+ m + 1]) × pairs; the pairs)."""
        into, combinations = self._combinations
        m = self.energy.shape[-1]
        j, k = np.triu_indices(m) if self.shape else self.volume.pairs
        rows = [combinations.reshape(-1, m, m)[:, j, k] * np.where(j < k, 2.0, 1.0)]
        if not self.shape:
            second, third = self.volume.on_pairs
            rows += [third.T, second[None]]
        # row-major, so the product reads its rows contiguously: stacked from a transpose it
        # came out column-major, and a 50-mode answer's product took 15.5 µs, not 12
        return into.reshape(self.energy.shape[0], -1), np.ascontiguousarray(np.vstack(rows)), (j, k)

    @functools.cached_property
    def _combinations(self) -> tuple[np.ndarray, np.ndarray]:
        """The operators Aₑₖ (degrees · (1 + entries) of them) as combinations of fewer, an SVD's
        directions above :data:`INDEPENDENT` of the largest: (into, combinations) with the
        stacked operators = into @ combinations (the moving jump's 80 on 44 modes: 29)."""
        k, e, m, _ = self.energy.shape
        stacked = self.energy.reshape(k * e, m * m)
        if not stacked.size:
            return np.zeros((k * e, 0)), np.zeros((0, m * m))
        U, S, Vt = np.linalg.svd(stacked, full_matrices=False)
        kept = S > INDEPENDENT * S[0] if S[0] > 0 else np.zeros(len(S), bool)
        return U[:, kept] * S[kept], Vt[kept]


def online(
    model: Model, problem: separated.Terms | None, modes: np.ndarray, probe: Probe | None, W: PETSc.Mat | None = None
) -> Online:
    """The :class:`Online` outputs of ``model``'s states Q z (``modes`` Q, owned rows,
    orthonormal in the energy product ``W``) from the rest state, with the terms' operators of
    ``problem`` (None: a nonlinear model, whose strain energy is no quadratic form; a fitted
    PGD fits it, :mod:`lungmech.pgd.fitted`) and, given ``W``, the residual's Gram matrix; the
    strain energy's form checked against the model's own at a random point. Collective; the
    model's state and parameters are kept."""
    comm = model.geometry.mesh.comm
    m = modes.shape[1]
    with model.kept_state():
        model.reset()
        rest = model.state.x.array.copy()
    if model.shape is not None:  # in (z, a)
        volume = shaped.volume(model, ufl.det(model.F) * model.dx, rest, modes)
    else:
        volume = cubic(model, ufl.det(model.F) * model.dx, rest, modes)
    if probe is not None:
        _, probes = affine(model, lambda: probe(model.displacement()), rest, modes)
    else:
        probes = np.zeros((0, m))
    if problem is None:
        shape = 0 if model.shape is None else len(model.shape.modes)
        return Online(volume, probes, np.zeros((0, 1, m, m)), np.zeros(0, dtype=int), shape=shape)
    degrees = math.prod(curve.degrees for curve in problem.curves)  # (the multi-indices' count)
    matrices = {(t.degree, t.entry): t.matrix for t in problem.operator}  # a term dropped as 0: a zero block
    moved = [t.entry for t in problem.operator if t.entry is not None]
    moved += [t.entry for t in problem.load if t.entry is not None]
    entries = np.array(sorted(set(moved)), dtype=int)  # (a load's alone: a zero block of the energy)
    energy = np.zeros((degrees, 1 + len(entries), m, m))
    for k in range(degrees):
        for i, e in enumerate([None, *entries]):
            if (k, e) in matrices:
                energy[k, i] = gram(modes, apply(matrices[k, e], modes, comm), comm)
    residual = np.zeros((0, 0)) if W is None else _residual_gram(problem, modes, W, entries, degrees)
    curves = tuple(curve.axis for curve in problem.curves), tuple(curve.degrees for curve in problem.curves)
    found = Online(
        volume, probes, energy, entries, *curves, 0 if model.shape is None else len(model.shape.modes), residual
    )
    _check_energy(model, found, modes)
    return found


def _residual_gram(
    problem: separated.Terms, modes: np.ndarray, W: PETSc.Mat, entries: np.ndarray, degrees: int
) -> np.ndarray:
    """G = Vᵀ W⁻¹ V over the free rows (module docstring): for each degree k and value (None,
    then ``entries``) the block of columns Kₑₖ Q, then one column −fₑₖ each; 0 × 0 beyond
    :data:`RESIDUAL_SIZE` columns or :data:`RESIDUAL_MEMORY`. Collective: one factorisation of W."""
    m, blocks, comm = modes.shape[1], degrees * (1 + len(entries)), problem.comm
    n = blocks * (m + 1)
    if n > RESIDUAL_SIZE or comm.allreduce(16 * modes.shape[0] * n, op=MPI.MAX) > RESIDUAL_MEMORY:
        return np.zeros((0, 0))
    at = {e: 1 + i for i, e in enumerate(entries.tolist())} | {None: 0}
    V = np.zeros((modes.shape[0], blocks * (m + 1)))
    for (k, e), matrix in {(t.degree, t.entry): t.matrix for t in problem.operator}.items():
        b = k * (1 + len(entries)) + at[e]
        V[:, b * m : (b + 1) * m] = apply(matrix, modes, comm)
    for (k, e), vector in {(t.degree, t.entry): t.vector for t in problem.load}.items():
        V[:, blocks * m + k * (1 + len(entries)) + at[e]] = -vector
    V[np.setdiff1d(np.arange(V.shape[0]), problem.free)] = 0.0  # the imposed rows: the modes hold 0 there
    solver = factorised(W)
    x, rhs = cast(tuple[PETSc.Vec, PETSc.Vec], W.createVecs())
    Z = np.empty_like(V)
    try:
        for j in range(V.shape[1]):
            rhs.array[:] = V[:, j]
            solver.solve(rhs, x)
            Z[:, j] = x.array
    finally:
        for thing in (solver, x, rhs):
            thing.destroy()
    return comm.allreduce(V.T @ Z, op=MPI.SUM)


def _check_energy(model: Model, found: Online, modes: np.ndarray) -> None:
    """½ zᵀ A(c) z against the model's own ∫ψ dX at a random point of the box and a random z."""
    values = dict(model.parameter_values)
    rng = np.random.default_rng(13)
    z = rng.uniform(-1.0, 1.0, modes.shape[1])
    z = model.geometry.mesh.comm.bcast(z)
    try:
        with model.kept_state():
            point = model.parameters.sample(1, seed=17)[0]
            model.set_parameters(point)
            model.reset()
            model.state.x.array[: modes.shape[0]] += modes @ z
            model.state.x.scatter_forward()
            exact = strain_energy(model)()
            units = np.array([p.to_unit(point[p.name]) for p in model.parameters])
            reduced = 0.5 * z @ found.operator(separated.values(model)[found.entries], found.weights(units)) @ z
    finally:
        model.set_parameters(values)
    if not abs(reduced - exact) <= ENERGY_CHECK * max(abs(exact), np.finfo(float).tiny):
        raise ParameterError(
            f"PGD: the strain energy is not the quadratic form of the model's Jacobian (off by "
            f"{abs(reduced - exact) / max(abs(exact), np.finfo(float).tiny):.1e}, relative): a load depends on the state"
        )
