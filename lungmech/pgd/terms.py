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

A value the residual is not affine in — the position s of a stiffness jump, inside a tanh; a
population's shape coefficient aᵢ, in det G and G⁻¹ — moved by one parameter μⱼ (its **curve**)
is taken as it is: every operator above is assembled at Chebyshev–Lobatto points of μⱼ's axis
and written as a Chebyshev series in it (:mod:`lungmech.pgd.chebyshev`,
:mod:`lungmech.pgd.assembly`), so each term gains a factor Tₖ on axis j:

    K(c; μⱼ) = Σₖ Tₖ(σⱼ) (K₀ₖ + Σ_e c_e K_eₖ),   σⱼ the unit coordinate of μⱼ;

several parameters' curves give the series' tensor product, a factor T_{kⱼ} on each of their
axes (k a multi-index).
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
from dolfinx import fem

from lungmech.errors import ParameterError
from lungmech.fem.model import Model
from lungmech.parallel.linalg import apply
from lungmech.pgd import chebyshev
from lungmech.pgd.assembly import AFFINE, Assembler, check_affine, check_linear, series
from lungmech.pgd.axes import Axis

__all__ = [
    "Curve",
    "affine_in_state",
    "LoadTerm",
    "Term",
    "Terms",
    "constants",
    "kept",
    "separated_terms",
    "set_values",
    "values",
    "values_at",
]

RANK = 1e-13  # singular values of a two-parameter value below this fraction of the largest are round-off


@dataclass(frozen=True)
class Term:
    """One separated operator term: ``factors[j]`` its function of axis j at that axis's
    nodes, ``matrix`` its K_T, ``entry`` the value c_e it comes from (the index into
    :func:`values`; None for K₀, the fixed values'), ``degree`` the multi-index k of its
    Chebyshev factors T_{kⱼ} on the curves' axes, flattened in C order (0 without a curve).
    Terms of one entry and degree share its matrix."""

    factors: tuple[np.ndarray, ...]
    matrix: PETSc.Mat
    entry: int | None = None
    degree: int = 0


@dataclass(frozen=True)
class Curve:
    """The values ``entries`` (indices into :func:`values`) the residual is not affine in, all
    moved by axis ``axis``: the terms carry Tₖ(σ) on it, k < ``degrees``, from ``points``
    Chebyshev–Lobatto points of it (module docstring)."""

    axis: int
    entries: tuple[int, ...]
    degrees: int
    points: int


@dataclass(frozen=True)
class LoadTerm:
    """One separated load term: ``factors``, ``entry`` and ``degree`` as :class:`Term`'s,
    ``vector`` its f_S (owned entries, 0 where imposed). Terms of one entry and degree share
    its vector."""

    factors: tuple[np.ndarray, ...]
    vector: np.ndarray
    entry: int | None
    degree: int


@dataclass
class Terms:
    """R(u; μ) = Σ_T κ_T(μ) K_T u − Σ_S φ_S(μ) f_S over ``axes``: ``operator`` the K_T terms,
    ``load`` the f_S terms; ``free`` the owned entries not imposed (the modes live there);
    ``curves`` the values the terms interpolate, an axis each (none: the residual is affine in
    every value)."""

    axes: tuple[Axis, ...]
    operator: list[Term]
    load: list[LoadTerm]
    free: np.ndarray
    comm: MPI.Comm
    curves: tuple[Curve, ...] = ()

    @functools.cached_property
    def symmetric(self) -> bool:
        """Whether every K_T is symmetric, to round-off of the largest: the Galerkin problems are then too."""
        largest = max(_frobenius(t.matrix) for t in self.operator)
        return all(_asymmetry(t.matrix) <= 1e-12 * largest for t in self.operator)

    @functools.cached_property
    def operator_factors(self) -> list[np.ndarray]:
        """Each axis's operator factors side by side: terms × its nodes."""
        return [np.array([t.factors[j] for t in self.operator]) for j in range(len(self.axes))]

    @functools.cached_property
    def load_factors(self) -> list[np.ndarray]:
        """Each axis's load factors side by side: load terms × its nodes."""
        return [np.array([t.factors[j] for t in self.load]) for j in range(len(self.axes))]

    @functools.cached_property
    def loads(self) -> np.ndarray:
        """The f_S side by side: owned entries × load terms."""
        return np.column_stack([t.vector for t in self.load])

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


def separated_terms(
    model: Model, axes: Sequence[Axis], linearised: bool = False, at: np.ndarray | None = None
) -> Terms:
    """The separated terms of ``model``'s residual at its current time over ``axes`` (one per
    parameter of the model, in its order) — or, ``linearised``, of its linearisation at rest
    R(0; c) + K(0; c) u, for a nonlinear model (a state-dependent load's coefficients θ held
    as they are), or at the state ``at`` (local entries, ghosts too) with the model's other
    coefficients as they are. Refused in one line where the model (or its linearisation) is not linear and
    affine in its values, where a parameter sets a field or moves three or more values
    together, or where an imposed displacement is not zero. Collective."""
    if [axis.parameter.name for axis in axes] != list(model.parameters.names):
        raise ParameterError(
            f"PGD: one axis per parameter of the model, in its order ({', '.join(model.parameters.names)})"
        )
    if model.state_dependent and not linearised:  # (a Newton–PGD takes it: build_nonlinear)
        raise ParameterError(
            "PGD: a load depends on the state (balanced gravity), so the residual is not affine in the state: "
            "its a priori PGD is the Newton–PGD's (lungmech.pgd.newton.build_nonlinear; lungmech pgd build makes it)"
        )
    for imposed in model.imposed:
        if np.any(imposed.base != 0.0):
            raise ParameterError("PGD: an imposed displacement is not zero; only zero ones are separated")
    held = constants(model)
    with kept(model, held):
        default = values_at(model, held, model.parameter_values)
        assembler = Assembler(model, held, set_values, linearised, at)
        check_linear(assembler, default)
        _no_field_moves(model, axes)
        along, moved = _sweeps(model, held, axes)
        curves = _curved(model, assembler, held, axes, default, along, moved)
        curved = [e for _, entries in curves for e in entries]
        entries = _factors(axes, along, moved, curved, _grids(model, held, axes))
        _check_separated(model, held, axes, default, entries, curved)
        varying = sorted({e for e, _ in entries})
        return _assembled(model, assembler, held, default, varying, entries, axes, curves)


def affine_in_state(model: Model) -> bool:
    """Whether ``model``'s residual is affine in its state (a linear model, the a priori
    greedy's; else the Newton–PGD's), checked as :func:`separated_terms` checks it; a load
    that depends on the state (balanced gravity) is not. Collective."""
    if model.state_dependent:
        return False
    held = constants(model)
    with kept(model, held):
        try:
            check_linear(Assembler(model, held, set_values), values_at(model, held, model.parameter_values))
        except ParameterError:
            return False
    return True


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


def _sweeps(
    model: Model, constants: list[fem.Constant], axes: Sequence[Axis]
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Every value at each axis's nodes, the other parameters at their defaults (nodes × values,
    one array an axis), and which values each axis moves: through the defaults or two random
    points."""
    defaults = model.parameters.defaults
    along, moved = [], []
    for axis in axes:
        name = axis.parameter.name
        bases = [defaults, *model.parameters.sample(2, seed=3)]
        sweeps = [
            np.array([values_at(model, constants, base | {name: float(mu)}) for mu in axis.values]) for base in bases
        ]
        along.append(sweeps[0])
        moved.append(np.any([_varies(sweep) for sweep in sweeps], axis=0))
    return along, moved


def _curved(
    model: Model,
    assembler: Assembler,
    constants: list[fem.Constant],
    axes: Sequence[Axis],
    default: np.ndarray,
    along: list[np.ndarray],
    moved: list[np.ndarray],
) -> list[tuple[int, tuple[int, ...]]]:
    """(an axis, its values) for each axis moving values the residual is not affine in, each
    alone, at a random state and point: R at 0.3 of a value's range against 0.7 R(low) +
    0.3 R(high). Refused in one line where two parameters move one such value."""
    u = assembler.random_state(seed=17)
    generic = values_at(model, constants, model.parameters.sample(1, seed=13)[0])  # (at the defaults a jump may be 0)
    curved: dict[int, list[int]] = {}
    for e in range(len(default)):
        by = [j for j in range(len(axes)) if moved[j][e]]
        if not by:
            continue
        low, high = float(along[by[0]][:, e].min()), float(along[by[0]][:, e].max())

        a, b, t = (
            assembler.residual(np.where(np.arange(len(default)) == e, value, generic), u)
            for value in (low, high, low + 0.3 * (high - low))
        )
        size = max(assembler.norm(a), assembler.norm(b))
        if assembler.norm(t - (0.7 * a + 0.3 * b)) <= AFFINE * size:
            continue
        if len(by) > 1:
            names = ", ".join(axes[j].parameter.name for j in by)
            raise ParameterError(
                f"PGD: the residual is not affine in a value that {names} move together; one parameter's is separated"
            )
        curved.setdefault(by[0], []).append(e)
    return [(j, tuple(curved[j])) for j in sorted(curved)]


def _factors(
    axes: Sequence[Axis],
    along: list[np.ndarray],
    moved: list[np.ndarray],
    curved: Sequence[int],
    two: Callable[[int, int], np.ndarray],
) -> list[tuple[int, tuple[np.ndarray, ...]]]:
    """(entry, its factors on every axis) for each varying value's separated part, the
    ``curved`` ones aside: one part for a value moved by one parameter, one per singular value
    of its values on the two axes' node grid (``two(j, k)``: nodes × nodes × values) for two."""
    ones = [np.ones(len(axis.nodes)) for axis in axes]
    parts = []
    for e in range(len(moved[0]) if moved else 0):
        if e in curved:
            continue
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
            left, sigma, right = np.linalg.svd(two(j, k)[:, :, e], full_matrices=False)
            for r in np.flatnonzero(sigma > RANK * sigma[0]):
                factors = list(ones)
                factors[j], factors[k] = sigma[r] * left[:, r], right[r]
                parts.append((e, tuple(factors)))
    return parts


def _grids(model: Model, constants: list[fem.Constant], axes: Sequence[Axis]) -> Callable[[int, int], np.ndarray]:
    """``two(j, k)``: every value on axes j and k's node grid, the others at their defaults
    (made once a pair)."""
    defaults = model.parameters.defaults

    @functools.cache
    def two(j: int, k: int) -> np.ndarray:
        pair = axes[j].parameter.name, axes[k].parameter.name
        return np.array(
            [
                [values_at(model, constants, defaults | dict(zip(pair, (float(a), float(b))))) for b in axes[k].values]
                for a in axes[j].values
            ]
        )

    return two


def _varies(sweep: np.ndarray) -> np.ndarray:
    """Which entries change along a sweep (rows: its points), beyond round-off."""
    return np.ptp(sweep, axis=0) > 1e-12 * np.abs(sweep).max(axis=0)


def _check_separated(
    model: Model,
    constants: list[fem.Constant],
    axes: Sequence[Axis],
    default: np.ndarray,
    parts: list,
    curved: Sequence[int],
) -> None:
    """The separated values against the model's own at random points of the axes' node grid
    (the curved ones are the assemblies', not separated)."""
    rng = np.random.default_rng(5)
    varying = {e for e, _ in parts}
    for _ in range(4):
        index = [int(rng.integers(len(axis.nodes))) for axis in axes]
        values = values_at(model, constants, {a.parameter.name: float(a.values[i]) for a, i in zip(axes, index)})
        expected = default.copy()
        expected[list(varying)] = 0.0
        expected[list(curved)] = values[list(curved)]
        for e, factors in parts:
            expected[e] += np.prod([f[i] for f, i in zip(factors, index)])
        if np.abs(values - expected).max() > 1e-10 * max(np.abs(values).max(), 1e-300):
            raise ParameterError("PGD: the parameters' values are not separated on the axes' nodes (a lungmech error)")


def _assembled(
    model: Model,
    assembler: Assembler,
    constants: list[fem.Constant],
    default: np.ndarray,
    varying: list[int],
    parts: list[tuple[int, tuple[np.ndarray, ...]]],
    axes: Sequence[Axis],
    curves: list[tuple[int, tuple[int, ...]]],
) -> Terms:
    """K₀, f₀ (the fixed values at theirs, the varying at 0) and each part's K_e, f_e — along
    the curves, their Chebyshev series, each coefficient k a term with T_{kⱼ} on each curve's
    axis j — checked against the model's own residual."""
    base = default.copy()
    base[varying] = 0.0
    point = model.parameters.sample(1, seed=7)[0]
    on = [j for j, _ in curves]  # the curves' axes
    parameters = [axes[j].parameter for j in on]
    degrees: tuple[int, ...] = ()
    points: tuple[int, ...] = ()
    if not curves:
        found = [assembler.operators(base, varying)]
    else:
        curved = [e for _, entries in curves for e in entries]
        defaults = model.parameters.defaults

        def base_at(sigmas: tuple[float, ...]) -> np.ndarray:
            at = base.copy()
            where = defaults | {p.name: p.from_unit(sigma) for p, sigma in zip(parameters, sigmas)}
            at[curved] = values_at(model, constants, where)[curved]
            return at

        found, degrees, points = series(assembler, base_at, varying, [p.name for p in parameters])
    weights = chebyshev.tensor([p.to_unit(point[p.name]) for p in parameters], degrees)
    try:
        check_affine(assembler, values_at(model, constants, point), weights, found)
    except BaseException:
        for operators in found:
            operators.destroy()
        raise

    def along(factors: tuple[np.ndarray, ...], k: int) -> tuple[np.ndarray, ...]:
        """A part's factors with T_{kⱼ} on each curve's axis j (k flattened)."""
        multi = dict(zip(on, np.unravel_index(k, degrees))) if curves else {}
        return tuple(
            f * chebyshev.polynomials(axes[i].nodes, int(multi[i]) + 1)[:, -1] if i in multi else f
            for i, f in enumerate(factors)
        )

    ones = tuple(np.ones(len(axis.nodes)) for axis in axes)
    largest = max(_frobenius(K) for ops in found for K in (ops.K0, *(K for K, _ in ops.unit.values())))
    loudest = max(assembler.norm(f) for ops in found for f in (ops.f0, *(f for _, f in ops.unit.values())))
    operator, load, used = [], [], set()
    for k, ops in enumerate(found):
        if k == 0 or _frobenius(ops.K0) > 1e-13 * largest:  # K₀₀ always: it holds the imposed rows' 1
            operator.append(Term(along(ones, k), ops.K0, None, k))
            used.add(id(ops.K0))
        if k == 0 or assembler.norm(ops.f0) > 1e-13 * loudest:
            load.append(LoadTerm(along(ones, k), ops.f0, None, k))
        for e, factors in parts:
            K, f = ops.unit[e]
            if _frobenius(K) > 1e-13 * largest:
                operator.append(Term(along(factors, k), K, e, k))
                used.add(id(K))
            if assembler.norm(f) > 1e-13 * loudest:
                load.append(LoadTerm(along(factors, k), f, e, k))
    for ops in found:
        for K in (ops.K0, *(K for K, _ in ops.unit.values())):
            if id(K) not in used:
                K.destroy()
    made = tuple(Curve(j, entries, n, P) for (j, entries), n, P in zip(curves, degrees, points))
    return Terms(tuple(axes), operator, load, assembler.free, model.geometry.mesh.comm, made)


def _asymmetry(matrix: PETSc.Mat) -> float:
    """‖K − Kᵀ‖ (Frobenius; PETSc's isSymmetric with a tolerance misses a difference of
    assemblies' round-off)."""
    difference = matrix.copy()
    difference.axpy(-1.0, matrix.transpose(PETSc.Mat()))
    found = _frobenius(difference)
    difference.destroy()
    return found


def _frobenius(matrix: PETSc.Mat) -> float:
    return float(matrix.norm(PETSc.NormType.FROBENIUS))  # type: ignore[arg-type]  # petsc4py's stub: a tuple for NORM_1_AND_2 only
