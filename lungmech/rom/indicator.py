"""Error indicators of reduced answers: the length of the Newton correction at them.

Offline, :class:`ResidualIndicator` takes the full correction (O(mesh)); online,
:class:`EnrichedIndicator` takes it in the span of the basis and an enrichment W, the POD
directions next after the basis, from the reduced solver's own (sampled) residual and tangent,
so that every online answer carries its indicator without touching the full mesh.

At a reduced state x_r the full residual R(x_r) is what the reduced model leaves unbalanced. The
step a full Newton iteration would take from there, with the tangent K_μ at the start state x₀
(the state the basis is relative to: at rest, or a lung's imaged state) and the answer's
parameters μ, measured in the energy norm E of the errors (the second variation of the
stored energy at rest, default parameters),

    η(t) = ‖K_μ⁻¹ R(x_r(t))‖_E,

is the error x − x_r itself for a linear model (K = K_μ) and its first-order estimate for a
nonlinear one. An answer's indicator is

    η = max_t η(t) / max_t ‖x_r(t) − x₀(t)‖_E,

relative to the largest change along the load path as
:attr:`lungmech.rom.reductor.Errors.energy` is, so the two are compared number for number. Each
answer costs one MUMPS factorisation of K_μ, and each output time one residual assembly and one
back-substitution: O(mesh), the offline check of the greedy training
(:mod:`lungmech.rom.greedy`) and of a model's validation.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, cast

from petsc4py import PETSc

import numpy as np
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix, create_matrix

from lungmech import jit
from lungmech.fem.linear import factorised
from lungmech.fem.model import Model
from lungmech.fem.parametric import Solution
from lungmech.fem.quantities import assemble_owned
from lungmech.parallel.linalg import apply, gram, norms
from lungmech.rom.basis import Basis, inner_product, origin
from lungmech.rom.galerkin import ReducedSolver
from lungmech.rom.hyper_reduced import HyperReducedSolver
from lungmech.rom.whole import Whole

if TYPE_CHECKING:  # (it imports this module)
    from lungmech.rom.reduced import ReducedModel

__all__ = ["ENRICHMENT", "EnrichedIndicator", "ResidualIndicator", "enrichment"]

ENRICHMENT = 8  # at most: the online indicator's directions beyond the basis


def enrichment(basis: Basis, modes: Basis | None) -> np.ndarray:
    """The POD directions of ``modes`` next after ``basis`` (its leading vectors; at most
    :data:`ENRICHMENT`, owned rows), where the online indicator looks: none when ``modes`` is
    None or holds no more."""
    if modes is None or basis.size >= modes.size:
        return np.zeros((basis.vectors.shape[0], 0))
    return modes.vectors[:, basis.size : basis.size + ENRICHMENT].copy()


class ResidualIndicator:
    """η of reduced answers of ``model`` (collective; :meth:`destroy` frees the factorisation).

    K_μ has 1 on the diagonal of imposed dofs, where the residual is set to 0: a reduced state
    meets its imposed displacements exactly."""

    def __init__(self, model: Model) -> None:
        self.model = model
        self.comm = model.geometry.mesh.comm
        self._energy = inner_product(model, "energy")
        self._residual, self._jacobian = jit.form(model.residual), jit.form(model.jacobian)
        self._tangent = create_matrix(self._jacobian)
        self._solver = factorised(self._tangent)
        self._work = fem.Function(model.space).x  # ghosted: assembly adds into ghost rows
        self._correction, self._vector = cast(tuple[PETSc.Vec, PETSc.Vec], self._tangent.createVecs())  # (right, left)
        self._constrained = model.constrained_dofs()

    def factorise(self, start: np.ndarray) -> None:
        """K_μ: the tangent at the state ``start`` (a state array) and the model's current
        parameters, factorised."""
        model, K = self.model, self._tangent
        with model.kept_state():
            model.state.x.array[:] = start
            model.state.x.scatter_forward()
            for term in model.state_dependent:
                term.update()
            K.zeroEntries()
            assemble_matrix(K, self._jacobian, bcs=model.bcs, diag=1.0)  # type: ignore[arg-type, misc]  # the into-a-matrix overload (singledispatch) is not in the hints
            K.assemble()
        self._solver.setOperators(K)

    def at_state(self) -> float:
        """η(t) = ‖K_μ⁻¹ R‖_E at the model's current state, parameters and loads (its
        state-dependent load coefficients set from that state first), K_μ that of the last
        :meth:`factorise`."""
        for term in self.model.state_dependent:
            term.update()
        b = self._vector
        b.array[:] = assemble_owned(self._residual, self._work, len(b.array))
        b.array[self._constrained] = 0.0
        self._solver.solve(b, self._correction)
        return self._norm(self._correction.array)

    def __call__(self, reduced: ReducedModel, solution: Solution) -> float:
        """η of ``solution``, an answer of the reduced model ``reduced`` on this model:
        max_t η(t) / max_t ‖x_r(t) − x₀(t)‖_E. Leaves the model at the last output's state."""
        owned = reduced.basis.vectors.shape[0]
        start = reduced.start_at(solution.parameters)  # an imaged body's at μ
        self.model.set_parameters(solution.parameters)
        self.model.set_time(float(reduced.stepping.start))
        self.factorise(origin(self.model, start))
        worst, change = 0.0, 0.0
        for index in range(len(solution.times)):
            x_r = reduced.reconstruct(solution, index)  # and the parameters and time of that output
            worst = max(worst, self.at_state())
            change = max(change, self._norm(x_r - origin(self.model, start)[:owned]))
        return worst / change if change > 0 else worst

    def _norm(self, x: np.ndarray) -> float:
        """‖x‖_E of owned rows."""
        return float(norms(x[:, None], self._energy, self.comm)[0])

    def destroy(self) -> None:
        for item in (self._solver, self._tangent, self._energy, self._correction, self._vector):
            item.destroy()


class EnrichedIndicator:
    """The online error indicator: the Newton correction in the enriched space U = [V W], the
    basis and its enrichment W,

        δ(t) = (Uᵀ K U)⁻¹ Uᵀ R(x_r(t)),   η̂(t) = ‖U δ‖_E = √(δᵀ G_U δ),

    with Uᵀ R and Uᵀ K U from the reduced solver (``enriched_terms()``: sampled on the reduced
    mesh for a hyper-reduced model), against the change ‖V q(t)‖_E = √(qᵀ G_V q). An answer's
    indicator is max_t η̂(t) / max_t ‖V q(t)‖_E, relative as :class:`ResidualIndicator`'s.

    Where the reduced solve converged, Vᵀ R = 0 and δ is the enriched Galerkin model's
    correction to it: the error along W, and the shift it implies along V. Where the state was
    not solved for — an imaged body's start, the image at its reduced reference ξ_r(μ)
    (:mod:`lungmech.rom.imaged`) — Vᵀ R ≠ 0 too: R there is the inverse problem's own residual
    R_ξ(ξ_r), and δ the breath's release from the image, ≈ −(ξ − ξ_r) in the small-strain
    limit (R depends on w − ξ), so the reference's error is covered as well. It sees the error
    only in U, so it estimates it from below, as well as the training's next directions
    describe it. G_U = Uᵀ E U is assembled once here (O(mesh), with the model; through
    ``whole``, :mod:`lungmech.rom.whole`, when given: kept, or given back on a body of sampled
    cells); each evaluation costs one sampled residual and tangent."""

    def __init__(self, model: Model, basis: np.ndarray, enrichment: np.ndarray, whole: Whole | None = None) -> None:
        def grams() -> tuple[np.ndarray]:
            comm = model.geometry.mesh.comm
            energy = inner_product(model, "energy")
            U = np.hstack([basis, enrichment])
            try:
                return (gram(U, apply(energy, U, comm), comm),)
            finally:
                energy.destroy()

        (self._gram,) = grams() if whole is None else whole.get("indicator", grams)
        self._size = basis.shape[1]

    @property
    def size(self) -> int:
        """The number of enrichment directions."""
        return self._gram.shape[0] - self._size

    def at(self, solver: ReducedSolver | HyperReducedSolver) -> tuple[float, float]:
        """(η̂(t), ‖V q‖_E) at the reduced ``solver``'s current state (collective)."""
        q, residual, tangent = solver.enriched_terms()
        change = _norm(q, self._gram[: self._size, : self._size])
        try:
            step = np.linalg.solve(tangent, residual)
        except np.linalg.LinAlgError:
            return np.inf, change
        return _norm(step, self._gram), change


def relative(pairs: list[tuple[float, float]]) -> float:
    """max_t η̂(t) / max_t ‖V q(t)‖_E of (η̂(t), change(t)) pairs along a path."""
    worst = max((eta for eta, _ in pairs), default=0.0)
    change = max((c for _, c in pairs), default=0.0)
    return worst / change if change > 0 else worst


def _norm(x: np.ndarray, gram_matrix: np.ndarray) -> float:
    return float(np.sqrt(abs(x @ gram_matrix @ x)))
