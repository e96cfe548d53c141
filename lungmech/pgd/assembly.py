"""The operators of a linear model's residual, from its own forms: at one point of its values,

    R(u; c) = (K₀ + Σ_e c_e K_e) u − (f₀ + Σ_e c_e f_e),

each K_e, f_e the difference of two assemblies (c_e = 1 and 0, the other varying values 0);
and along a **curve** — a value the residual is not affine in, moved by one parameter — as the
Chebyshev series of those operators in that parameter's unit coordinate σ
(:mod:`lungmech.pgd.chebyshev`): assembled at the Chebyshev–Lobatto points, 9, 17, 33 or 65 of
them, nested, until the series' last two coefficients fall below :data:`CURVE` of its largest
(measured on the residual of a random state), and kept to the last coefficient above it.
Values moved by several parameters, each its own (a population's shape coefficients), give
the series' tensor product, each parameter's points refined until its own tail is below.

:func:`check_affine` holds the result to the model's own residual at a random point and state,
so that a model outside these forms is refused, not approximated.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix

from lungmech import jit
from lungmech.errors import ParameterError
from lungmech.fem.model import Model
from lungmech.fem.quantities import assemble_owned
from lungmech.parallel.linalg import apply
from lungmech.parallel.owned import owned_size
from lungmech.pgd import chebyshev

__all__ = ["AFFINE", "CURVE", "Assembler", "Operators", "check_affine", "check_linear", "series"]

AFFINE = 1e-9  # the largest relative mismatch of the assembled residual and the operators'
CURVE = 1e-11  # a curve's series: its last two coefficients below this fraction of the largest, and kept above it
POINTS = (9, 17, 33, 65)  # the Chebyshev-Lobatto points a curve is assembled at, nested, fewest first
GRID = 1089  # the most points of several curves' tensor grid (33 × 33), each 2 + the varying values' assemblies
MEMORY = 2**33  # bytes of operators a rank may hold for a series: the grid's and the coefficients' (8 GiB)


@dataclass
class Operators:
    """K₀, f₀ and ``unit[e]`` = (K_e, f_e) for each varying value e (module docstring): at one
    point, or one coefficient of a curve's series."""

    K0: PETSc.Mat
    f0: np.ndarray
    unit: dict[int, tuple[PETSc.Mat, np.ndarray]]

    def residuals(self, u: np.ndarray, comm: MPI.Comm) -> np.ndarray:
        """K₀ u − f₀, then each K_e u − f_e: (1 + values) × owned entries."""
        pairs = [(self.K0, self.f0), *self.unit.values()]
        return np.array([apply(K, u[:, None], comm)[:, 0] - f for K, f in pairs])

    def destroy(self) -> None:
        self.K0.destroy()
        for K, _ in self.unit.values():
            K.destroy()


class Assembler:
    """Assembles ``model``'s Jacobian and residual with its ``constants`` set to given values
    (flattened, as :func:`lungmech.pgd.terms.values`); ``free`` the owned entries not imposed.
    ``linearised``: its residual is the model's linearisation at its rest state u₀ (a
    porosity, say), R(u₀; c) + K(u₀; c) u, and its operators are assembled there — the linear
    problem a nonlinear model's Newton–PGD takes as its preconditioner (:mod:`lungmech.pgd.newton`);
    or at the state ``at`` (local entries, ghosts too; an imaged body's image on its reference)."""

    def __init__(
        self,
        model: Model,
        constants: Sequence[fem.Constant],
        set_values: Callable,
        linearised: bool = False,
        at: np.ndarray | None = None,
    ) -> None:
        self.model, self.constants, self._set = model, list(constants), set_values
        self.linearised = linearised
        self.comm = model.geometry.mesh.comm
        self._jacobian, self._residual = jit.form(model.jacobian), jit.form(model.residual)
        self.owned = owned_size(model.space)
        self._work = fem.Function(model.space).x
        self.imposed = model.constrained_dofs()
        self.free = np.setdiff1d(np.arange(self.owned), self.imposed)
        self._rest = np.zeros(len(model.state.x.array))
        if linearised and at is not None:
            self._rest = at.copy()
        elif linearised:
            with model.kept_state():
                model.reset()
                self._rest = model.state.x.array.copy()

    def random_state(self, seed: int) -> np.ndarray:
        """A random u on the free entries (0 on the imposed), different on each rank."""
        u = np.zeros(self.owned)
        u[self.free] = np.random.default_rng(seed + self.comm.rank).standard_normal(len(self.free))
        return u

    def residual(self, values: np.ndarray, u: np.ndarray) -> np.ndarray:
        """R(u; c) on the free entries, the constants at ``values`` (``linearised``: R(u₀; c) +
        K(u₀; c) u)."""
        self._set(self.constants, values)
        self.model.state.x.array[:] = self._rest
        if not self.linearised:
            self.model.state.x.array[: self.owned] = u
        self.model.state.x.scatter_forward()
        found = assemble_owned(self._residual, self._work, self.owned)
        if self.linearised:
            K = self.jacobian()
            try:
                found += apply(K, u[:, None], self.comm)[:, 0]
            finally:
                K.destroy()
        return found[self.free]

    def norm(self, vector: np.ndarray) -> float:
        """The Euclidean norm of a distributed vector (owned entries)."""
        return float(np.sqrt(self.comm.allreduce(float(vector @ vector), op=MPI.SUM)))

    def operators(self, base: np.ndarray, varying: Sequence[int]) -> Operators:
        """K₀, f₀ at ``base`` (the varying values 0 there) and each varying value's K_e, f_e
        (at rest, linearised; else at u = 0)."""
        self.model.state.x.array[:] = self._rest
        self.model.state.x.scatter_forward()
        K0, f0 = self._at(base, 1.0)
        bare, _ = self._at(base, 0.0)
        unit = {}
        for e in varying:
            values = base.copy()
            values[e] = 1.0
            K, f = self._at(values, 0.0)
            K.axpy(-1.0, bare)
            unit[e] = (K, f - f0)
        bare.destroy()
        return Operators(K0, f0, unit)

    def jacobian(self) -> PETSc.Mat:
        """The Jacobian as the constants are now (the caller destroys it)."""
        K = assemble_matrix(self._jacobian, bcs=self.model.bcs)
        K.assemble()
        return K

    def _at(self, values: np.ndarray, diagonal: float) -> tuple[PETSc.Mat, np.ndarray]:
        self._set(self.constants, values)
        K = assemble_matrix(self._jacobian, bcs=self.model.bcs, diag=diagonal)
        K.assemble()
        f = -assemble_owned(self._residual, self._work, self.owned)
        f[self.imposed] = 0.0
        return K, f


def series(
    assembler: Assembler,
    base_at: Callable[[tuple[float, ...]], np.ndarray],
    varying: Sequence[int],
    names: Sequence[str],
) -> tuple[list[Operators], tuple[int, ...], tuple[int, ...]]:
    """The operators' Chebyshev coefficients along the curves of the parameters ``names``
    (module docstring; several: their tensor product, :mod:`lungmech.pgd.chebyshev`),
    ``base_at(σ)`` the values at the curves' unit coordinates σ (the varying ones 0): the
    coefficients in C order of their multi-indices, each parameter's number of coefficients
    kept and of points assembled. A parameter's points are refined while its series' tail
    (the largest over the others' coefficients) is above :data:`CURVE`. Refused in one line
    where 65 points do not resolve a parameter (a jump narrower than its range can follow), or
    where the grid would pass :data:`GRID` points or hold more than :data:`MEMORY` bytes of
    operators on a rank (the grid's, and as many coefficients at most)."""
    u = assembler.random_state(seed=19)
    at: dict[tuple[float, ...], Operators] = {}
    levels = [0] * len(names)
    try:
        while True:
            grids = [chebyshev.lobatto(POINTS[level]) for level in levels]
            shape = tuple(len(grid) for grid in grids)
            keys = [tuple(float(s) for s in point) for point in itertools.product(*grids)]
            _affordable(assembler, names, shape, at, 2 + len(varying))
            for key in keys:
                if key not in at:
                    at[key] = assembler.operators(base_at(key), varying)
            samples = np.array([at[key].residuals(u, assembler.comm) for key in keys])
            samples = samples.reshape(*shape, 1 + len(varying), u.size)  # (u.size: 0 on a rank owning no dof)
            for axis in range(len(shape)):
                samples = chebyshev.coefficients(samples, axis)
            sizes = np.sqrt(assembler.comm.allreduce(np.sum(samples**2, axis=-1), op=MPI.SUM))  # grid × groups
            profiles = [_profile(sizes, axis) for axis in range(len(shape))]  # coefficients × groups, a parameter
            tails = [max(chebyshev.tail(column) for column in profile.T) for profile in profiles]
            unresolved = [axis for axis, tail in enumerate(tails) if tail > CURVE]
            if not unresolved:
                kept = tuple(_kept(profile) for profile in profiles)
                grid = np.empty(shape, dtype=object)
                for index, key in zip(np.ndindex(*shape), keys):
                    grid[index] = at[key]
                return _combined(grid, kept), kept, shape
            for axis in unresolved:
                if levels[axis] + 1 == len(POINTS):
                    raise ParameterError(
                        f"PGD: the residual is not a smooth enough function of parameter {names[axis]!r} "
                        f"({POINTS[-1]} Chebyshev points leave {tails[axis]:.1e} of it): "
                        "widen the jump it moves or narrow its range"
                    )
                levels[axis] += 1
    finally:
        for operators in at.values():
            operators.destroy()


def _affordable(assembler: Assembler, names: Sequence[str], shape: tuple[int, ...], at: dict, matrices: int) -> None:
    """Refuse, in one line, a grid of ``shape`` past :data:`GRID` points, or whose operators
    (``matrices`` a point, as many again for the coefficients at most) would pass
    :data:`MEMORY` bytes on some rank, measured on an operator already made (or one made
    now)."""
    points = math.prod(shape)
    how = f"({' × '.join(map(str, shape))} points)"
    if points > GRID:
        raise ParameterError(
            f"PGD: the residual's dependence on {', '.join(names)} needs more than {GRID} assemblies {how}: "
            "narrow their ranges, or give fewer of them"
        )
    one = next(iter(at.values())).K0 if at else assembler.jacobian()
    nonzeros = one.getInfo()["nz_allocated"]
    if not at:
        one.destroy()
    needed = assembler.comm.allreduce(2 * points * matrices * nonzeros * 12, op=MPI.MAX)  # (a value, a column index)
    if needed > MEMORY:
        raise ParameterError(
            f"PGD: the operators' series in {', '.join(names)} {how} would hold {needed / 2**30:.1f} GiB on a rank "
            f"(at most {MEMORY / 2**30:.0f}): narrow their ranges, run on more ranks or a coarser mesh, "
            "or give --samples for a PGD fitted to full solves"
        )


def _profile(sizes: np.ndarray, axis: int) -> np.ndarray:
    """The coefficients' sizes along one parameter's ``axis``, the largest over the others'
    (``sizes``: grid × groups): coefficients × groups."""
    others = tuple(i for i in range(sizes.ndim - 1) if i != axis)
    return np.max(sizes, axis=others) if others else sizes


def _kept(profile: np.ndarray) -> int:
    """The number of coefficients up to the last whose size is above :data:`CURVE` of its
    group's largest (``profile``: coefficients × groups)."""
    largest = profile.max(axis=0)
    return 1 + int(np.max(np.flatnonzero(np.any(profile > CURVE * largest, axis=1)), initial=0))


def _combined(grid: np.ndarray, kept: tuple[int, ...]) -> list[Operators]:
    """The coefficients A_k = Σ_p Π_i C_{k_i p_i} (operators at grid point p), k < ``kept``, in C
    order: one parameter's axis after the other (the grid's ``Operators``, an object array, are
    the caller's; the partial sums between axes are made and destroyed here)."""
    current = grid
    for axis, count in enumerate(kept):
        C = chebyshev.coefficients(np.eye(current.shape[axis]))[:count]  # Cₖₚ
        moved = np.moveaxis(current, axis, 0)
        found = np.empty((count, *moved.shape[1:]), dtype=object)
        try:
            for index in np.ndindex(*moved.shape[1:]):
                column = list(moved[(slice(None), *index)])
                for k, row in enumerate(C):
                    found[(k, *index)] = _mixed(column, row)
        except BaseException:
            for operators in found.ravel():
                if operators is not None:
                    operators.destroy()
            raise
        finally:
            if current is not grid:
                for operators in current.ravel():
                    operators.destroy()
        current = np.moveaxis(found, 0, axis)
    return list(current.ravel())


def _mixed(samples: list[Operators], row: np.ndarray) -> Operators:
    """Σₚ rowₚ samplesₚ (every operator and vector)."""

    def matrix(matrices: list[PETSc.Mat]) -> PETSc.Mat:
        A = matrices[0].copy()
        A.scale(row[0])
        for c, K in zip(row[1:], matrices[1:]):
            A.axpy(c, K, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)  # type: ignore[arg-type]  # one form's assemblies: one pattern; the stubs say int
        return A

    unit = {
        e: (matrix([s.unit[e][0] for s in samples]), sum(c * s.unit[e][1] for c, s in zip(row, samples)))
        for e in samples[0].unit
    }
    f0 = sum(c * s.f0 for c, s in zip(row, samples))
    return Operators(matrix([s.K0 for s in samples]), np.asarray(f0), unit)


def check_affine(assembler: Assembler, values: np.ndarray, weights: np.ndarray, found: list[Operators]) -> None:
    """The residual the model assembles at the constants' ``values`` and a random state against
    Σₖ wₖ [(K₀ₖ + Σ c_e K_eₖ) u − (f₀ₖ + Σ c_e f_eₖ)] (``weights`` wₖ: the curve's Tₖ at the
    point, or one 1 without a curve), on the free rows: a nonlinear R(u), or one not affine in
    the values, differs."""
    u = assembler.random_state(seed=11)
    found_residual = assembler.residual(values, u)
    expected = np.zeros(assembler.owned)
    for w, operators in zip(weights, found):
        c = np.array([1.0, *(values[e] for e in operators.unit)])
        expected += w * (c @ operators.residuals(u, assembler.comm))
    expected = expected[assembler.free]
    _refuse_beyond(
        assembler.norm(found_residual - expected),
        assembler.norm(expected),
        "the separated terms' (its values not affine in the parameters, nor a smooth series of them)",
    )


def check_linear(assembler: Assembler, values: np.ndarray) -> None:
    """R(2u) − 2R(u) + R(0) = 0 at a random state u, the constants at ``values``: a residual
    not affine in the state (a nonlinear law, a follower load) refused in one line before the
    terms' assemblies (a ``linearised`` one is affine)."""
    if assembler.linearised:
        return
    u = assembler.random_state(seed=23)
    zero, once, twice = (assembler.residual(values, scale * u) for scale in (0.0, 1.0, 2.0))
    _refuse_beyond(
        assembler.norm(twice - 2.0 * once + zero),
        assembler.norm(twice - zero),
        "affine in the state: this PGD separates linear models; give --samples for a PGD fitted to full solves",
    )


def _refuse_beyond(mismatch: float, size: float, what: str) -> None:
    """Refuse, in one line, a residual off by more than :data:`AFFINE` of its ``size``: it is
    not ``what``."""
    if not mismatch <= AFFINE * size:
        how = f"mismatch {mismatch / size:.1e} of its size at a random point" if np.isfinite(mismatch) else "not finite"
        raise ParameterError(f"PGD: the residual ({how}) is not {what}")
