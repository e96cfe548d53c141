"""A linear model's residual as a sum of separated terms, read from its own forms and its own
parameter assignment.

At a fixed time a linear model's residual is affine in its state u and in the values c its
parameters set (the ``fem.Constant`` entries of its forms: a law's moduli, a load's value or
direction):

    R(u; c) = K(c) u − f(c),   K(c) = K₀ + Σ_e c_e K_e,   f(c) = f₀ + Σ_e c_e f_e,

so each K_e, f_e is a difference of two assemblies of the model's own Jacobian and residual (at
c_e = 1 and at 0, the other varying entries 0): nothing is written by hand. A value c_e(μ)
moved by one parameter μⱼ is a function of it alone, read at the nodes of that axis; one moved
by two (a gravity component under pitch and roll) is the sum of products its values on the
two axes' node grid give by SVD (to round-off). The separated residual is then

    R(u; μ) = Σ_T κ_T(μ) K_T u − Σ_S φ_S(μ) f_S,   κ_T(μ) = Πⱼ κ_Tʲ(μⱼ),

each factor known at its axis's nodes (:mod:`lungmech.pgd.axes`), which is all the PGD's
integrals over the box need. Affinity is checked, not assumed: at a random point of the box
and a random state the assembled residual must equal the terms' to 1e-9 of its size.
Imposed displacements must be zero (the modes vanish there); K₀ carries 1 on their diagonal.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
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
from lungmech.pgd.axes import Axis

__all__ = ["LoadTerm", "Term", "Terms", "constants", "kept", "separated_terms", "set_values", "values", "values_at"]

AFFINE = 1e-9  # the largest relative mismatch of the assembled residual and the terms'
RANK = 1e-13  # singular values of a two-parameter value below this fraction of the largest are round-off


@dataclass(frozen=True)
class Term:
    """One separated operator term: ``factors[j]`` its function of axis j at that axis's
    nodes, ``matrix`` its K_T, ``entry`` the value c_e it comes from (the index into
    :func:`values`; None for K₀, the fixed values'). Terms of one entry share its matrix."""

    factors: tuple[np.ndarray, ...]
    matrix: PETSc.Mat
    entry: int | None = None


@dataclass(frozen=True)
class LoadTerm:
    """One separated load term: ``factors`` as :class:`Term`'s, ``vector`` its f_S (owned
    entries, 0 where imposed)."""

    factors: tuple[np.ndarray, ...]
    vector: np.ndarray


@dataclass
class Terms:
    """R(u; μ) = Σ_T κ_T(μ) K_T u − Σ_S φ_S(μ) f_S over ``axes``: ``operator`` the K_T terms,
    ``load`` the f_S terms; ``free`` the owned entries not imposed (the modes live there)."""

    axes: tuple[Axis, ...]
    operator: list[Term]
    load: list[LoadTerm]
    free: np.ndarray
    comm: MPI.Comm

    def residual(self, u: np.ndarray, mu_nodes: Sequence[int]) -> np.ndarray:
        """R(u) at the box point whose j-th coordinate is axis j's node ``mu_nodes[j]`` (owned
        entries; for checks)."""
        r = np.zeros_like(u)
        for term in self.operator:
            r += (
                np.prod([f[i] for f, i in zip(term.factors, mu_nodes)])
                * apply(term.matrix, u[:, None], self.comm)[:, 0]
            )
        for load in self.load:
            r -= np.prod([f[i] for f, i in zip(load.factors, mu_nodes)]) * load.vector
        return r

    def destroy(self) -> None:
        for term in self.operator:
            term.matrix.destroy()


def separated_terms(model: Model, axes: Sequence[Axis]) -> Terms:
    """The separated terms of ``model``'s residual at its current time over ``axes`` (one per
    parameter of the model, in its order). Refused in one line where the model is not linear
    and affine in its values, where a parameter sets a field or moves three or more values
    together, or where an imposed displacement is not zero. Collective."""
    if [axis.parameter.name for axis in axes] != list(model.parameters.names):
        raise ParameterError(
            f"PGD: one axis per parameter of the model, in its order ({', '.join(model.parameters.names)})"
        )
    if model.state_dependent:
        raise ParameterError("PGD: a load depends on the state (balanced gravity): the residual is not affine in it")
    for imposed in model.imposed:
        if np.any(imposed.base != 0.0):
            raise ParameterError("PGD: an imposed displacement is not zero; only zero ones are separated")
    held = constants(model)
    with kept(model, held):
        default = values_at(model, held, model.parameter_values)
        _no_field_moves(model, axes)
        entries = _factors(model, held, axes, default)
        _check_separated(model, held, axes, default, entries)
        varying = sorted({e for e, _ in entries})
        return _assembled(model, held, default, varying, entries, axes)


def constants(model: Model) -> list[fem.Constant]:
    """The Constants of the model's residual and Jacobian, in one order: the values c."""
    return list(dict.fromkeys([*model.residual.constants(), *model.jacobian.constants()]))


def values(model: Model) -> np.ndarray:
    """The values c the model's parameters set now: every entry of :func:`constants`, flattened
    and concatenated (a term's ``entry`` indexes it)."""
    held = constants(model)
    return np.concatenate([np.ravel(c.value) for c in held]) if held else np.zeros(0)


@contextlib.contextmanager
def kept(model: Model, constants: list[fem.Constant]) -> Iterator[None]:
    """The model's parameters, constants and state as they were, after the block."""
    values = dict(model.parameter_values)
    saved = [np.array(c.value, copy=True) for c in constants]
    try:
        with model.kept_state():
            yield
    finally:
        model.set_parameters(values)
        for c, value in zip(constants, saved):
            c.value = value


def values_at(model: Model, constants: list[fem.Constant], at: dict[str, float]) -> np.ndarray:
    """Every constant's entries, flattened and concatenated, with the parameters at ``at``."""
    model.set_parameters(at)
    return np.concatenate([np.ravel(c.value) for c in constants]) if constants else np.zeros(0)


def set_values(constants: list[fem.Constant], flat: np.ndarray) -> None:
    """The constants' entries from the flattened ``flat``."""
    start = 0
    for c in constants:
        size = np.size(c.value)
        c.value = flat[start : start + size].reshape(np.shape(c.value))
        start += size


def _no_field_moves(model: Model, axes: Sequence[Axis]) -> None:
    """Refuse a parameter that sets a field (a region's stiffness, a shape map): its values are
    not separated here."""
    functions = [f for f in model.residual.coefficients() if f is not model.state]
    before = [f.x.array.copy() for f in functions]
    for axis in axes:
        for mu in axis.values[[0, -1]]:
            model.set_parameters({axis.parameter.name: float(mu)})
            for f, array in zip(functions, before):
                if not np.array_equal(f.x.array, array):
                    raise ParameterError(
                        f"PGD: parameter {axis.parameter.name!r} sets the field {f.name!r}; fields are not separated"
                    )
        model.set_parameters({axis.parameter.name: model.parameters.defaults[axis.parameter.name]})


def _factors(
    model: Model, constants: list[fem.Constant], axes: Sequence[Axis], default: np.ndarray
) -> list[tuple[int, tuple[np.ndarray, ...]]]:
    """(entry, its factors on every axis) for each varying entry's separated part: one part for
    an entry moved by one parameter, one per singular value for two."""
    defaults = model.parameters.defaults
    along = []  # the entries' values at each axis's nodes, the others at their defaults
    moved = []  # whether each entry moves along each axis, through the defaults or two random points
    for axis in axes:
        name = axis.parameter.name
        bases = [defaults, *model.parameters.sample(2, seed=3)]
        sweeps = [
            np.array([values_at(model, constants, base | {name: float(mu)}) for mu in axis.values]) for base in bases
        ]
        along.append(sweeps[0])
        moved.append(np.any([_varies(sweep) for sweep in sweeps], axis=0))
    ones = [np.ones(len(axis.nodes)) for axis in axes]
    grids: dict[tuple[int, int], np.ndarray] = {}  # every value on two axes' node grid, made once a pair
    parts = []
    for e in range(len(default)):
        by = [j for j in range(len(axes)) if moved[j][e]]
        if len(by) > 2:
            names = ", ".join(axes[j].parameter.name for j in by)
            raise ParameterError(
                f"PGD: one value moves with {len(by)} parameters together ({names}); at most two are separated"
            )
        if len(by) == 1:
            (j,) = by
            parts.append((e, tuple(along[j][:, e] if i == j else ones[i] for i in range(len(axes)))))
        elif len(by) == 2:
            j, k = by
            if (j, k) not in grids:
                pair = axes[j].parameter.name, axes[k].parameter.name
                grids[j, k] = np.array(
                    [
                        [
                            values_at(model, constants, defaults | dict(zip(pair, (float(a), float(b)))))
                            for b in axes[k].values
                        ]
                        for a in axes[j].values
                    ]
                )
            left, sigma, right = np.linalg.svd(grids[j, k][:, :, e], full_matrices=False)
            for r in np.flatnonzero(sigma > RANK * sigma[0]):
                factors = list(ones)
                factors[j], factors[k] = sigma[r] * left[:, r], right[r]
                parts.append((e, tuple(factors)))
    return parts


def _varies(sweep: np.ndarray) -> np.ndarray:
    """Which entries change along a sweep (rows: its points), beyond round-off."""
    return np.ptp(sweep, axis=0) > 1e-12 * np.abs(sweep).max(axis=0)


def _check_separated(
    model: Model, constants: list[fem.Constant], axes: Sequence[Axis], default: np.ndarray, parts: list
) -> None:
    """The separated values against the model's own at random points of the axes' node grid."""
    rng = np.random.default_rng(5)
    varying = {e for e, _ in parts}
    for _ in range(4):
        index = [int(rng.integers(len(axis.nodes))) for axis in axes]
        values = values_at(model, constants, {a.parameter.name: float(a.values[i]) for a, i in zip(axes, index)})
        expected = default.copy()
        expected[list(varying)] = 0.0
        for e, factors in parts:
            expected[e] += np.prod([f[i] for f, i in zip(factors, index)])
        if np.abs(values - expected).max() > 1e-10 * max(np.abs(values).max(), 1e-300):
            raise ParameterError("PGD: the parameters' values are not separated on the axes' nodes (a lungmech error)")


def _assembled(
    model: Model,
    constants: list[fem.Constant],
    default: np.ndarray,
    varying: list[int],
    parts: list[tuple[int, tuple[np.ndarray, ...]]],
    axes: Sequence[Axis],
) -> Terms:
    """K₀, f₀ (the fixed entries at their values, the varying at 0) and each part's K_e, f_e."""
    jacobian, residual = jit.form(model.jacobian), jit.form(model.residual)
    owned = owned_size(model.space)
    work = fem.Function(model.space).x
    imposed = model.constrained_dofs()
    free = np.setdiff1d(np.arange(owned), imposed)
    model.state.x.array[:] = 0.0
    model.state.x.scatter_forward()

    def at(values: np.ndarray, diagonal: float) -> tuple[PETSc.Mat, np.ndarray]:
        set_values(constants, values)
        K = assemble_matrix(jacobian, bcs=model.bcs, diag=diagonal)
        K.assemble()
        f = -assemble_owned(residual, work, owned)
        f[imposed] = 0.0
        return K, f

    base = default.copy()
    base[varying] = 0.0
    K0, f0 = at(base, 1.0)
    bare, _ = at(base, 0.0)
    ones = tuple(np.ones(len(axis.nodes)) for axis in axes)
    operator, load = [Term(ones, K0)], [LoadTerm(ones, f0)]
    unit: dict[int, tuple[PETSc.Mat, np.ndarray]] = {}
    for e in varying:
        values = base.copy()
        values[e] = 1.0
        K, f = at(values, 0.0)
        K.axpy(-1.0, bare)
        unit[e] = (K, f - f0)
    bare.destroy()
    _check_affine(model, constants, free, K0, f0, unit)
    largest = max([_frobenius(K0), *(_frobenius(K) for K, _ in unit.values())])
    loudest = max([_norm(f0, model), *(_norm(f, model) for _, f in unit.values())])
    used = set()
    for e, factors in parts:
        K, f = unit[e]
        if _frobenius(K) > 1e-13 * largest:
            operator.append(Term(factors, K, e))
            used.add(e)
        if _norm(f, model) > 1e-13 * loudest:
            load.append(LoadTerm(factors, f))
    for e, (K, _) in unit.items():
        if e not in used:
            K.destroy()
    return Terms(tuple(axes), operator, load, free, model.geometry.mesh.comm)


def _frobenius(matrix: PETSc.Mat) -> float:
    return float(matrix.norm(PETSc.NormType.FROBENIUS))  # type: ignore[arg-type]  # petsc4py's stub: a tuple for NORM_1_AND_2 only


def _norm(vector: np.ndarray, model: Model) -> float:
    return float(np.sqrt(model.geometry.mesh.comm.allreduce(float(vector @ vector), op=MPI.SUM)))


def _check_affine(
    model: Model,
    constants: list[fem.Constant],
    free: np.ndarray,
    K0: PETSc.Mat,
    f0: np.ndarray,
    unit: dict[int, tuple[PETSc.Mat, np.ndarray]],
) -> None:
    """The residual the model assembles at a random point and state against the affine formula
    (K₀ + Σ c_e K_e) u − (f₀ + Σ c_e f_e) of the unit assemblies, on the free rows (u is 0 on
    the imposed ones): a nonlinear R(u), or one not affine in c, differs."""
    comm = model.geometry.mesh.comm
    values = values_at(model, constants, model.parameters.sample(1, seed=7)[0])
    owned = owned_size(model.space)
    rng = np.random.default_rng(11 + comm.rank)
    u = np.zeros(owned)
    u[free] = rng.standard_normal(len(free))
    model.state.x.array[:owned] = u
    model.state.x.scatter_forward()
    found = assemble_owned(jit.form(model.residual), fem.Function(model.space).x, owned)[free]
    expected = apply(K0, u[:, None], comm)[:, 0] - f0
    for e, (K, f) in unit.items():
        expected += values[e] * (apply(K, u[:, None], comm)[:, 0] - f)
    expected = expected[free]
    size = np.sqrt(comm.allreduce(float(expected @ expected), op=MPI.SUM))
    mismatch = np.sqrt(comm.allreduce(float((found - expected) @ (found - expected)), op=MPI.SUM))
    if not mismatch <= AFFINE * size:
        how = f"mismatch {mismatch / size:.1e} of its size" if np.isfinite(mismatch) else "not a finite number"
        raise ParameterError(
            f"PGD: the residual is not affine in the state and the parameters' values ({how} at a random point): "
            "this PGD separates linear models"
        )
