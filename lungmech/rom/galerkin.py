"""Reduced Galerkin solves: the full model's residual projected on a basis, Newton in k unknowns.

The state is x = x₀ + V q, where x₀ is the unloaded state with the imposed displacements and V
vanishes on imposed dofs. Newton solves Vᵀ R(x₀ + V q) = 0 with the reduced tangent Vᵀ K V
(K V is one PETSc MatMatMult with the distributed dense basis) and a backtracking line search
on the reduced residual. Without hyper-reduction each iteration still assembles the full
residual and tangent, which dominates the online cost; the k × k solve is negligible.

A :class:`ReducedSolver` has the interface of :class:`lungmech.fem.solver.NewtonSolver`, so the
same load stepping (:func:`lungmech.fem.solver.solve`), outputs and state-dependent loads work.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix, create_matrix

from lungmech import jit
from lungmech.errors import ParameterError
from lungmech.fem.convergence import Fields
from lungmech.fem.dynamics import ImplicitEuler
from lungmech.fem.limits import Inversion, displacement_gradient
from lungmech.fem.model import Model
from lungmech.fem.quantities import assemble_owned
from lungmech.fem.solver import NOT_CONVERGED, NewtonOptions, NewtonResult, StepsModelState
from lungmech.fem.state_dependent import StateDependent
from lungmech.parallel.layout import layout
from lungmech.parallel.linalg import apply, gram
from lungmech.rom.basis import Basis, dual, origin, reference_state


class ReducedSolver(StepsModelState):  # the model holds x₀ + V q after every evaluation
    """Newton on Vᵀ R(x₀ + V q) = 0 for one model and one basis; forms are compiled once.

    ``start`` is the state the basis is relative to (x₀ without the imposed displacements;
    default: the unloaded state), e.g. the imaged end-expiration state of a lung.
    ``residual`` and ``jacobian`` replace the model's own forms, as for NewtonSolver.
    ``enrichment`` (owned rows): directions beyond the basis, whose residual and tangent
    :meth:`enriched_terms` gives (the online error indicator's).
    """

    def __init__(
        self,
        model: Model,
        basis: Basis,
        options: NewtonOptions | None = None,
        residual: ufl.Form | None = None,
        jacobian: ufl.Form | None = None,
        start: np.ndarray | None = None,
        enrichment: np.ndarray | None = None,
    ) -> None:
        check_basis(model, basis)
        self.model, self.basis = model, basis
        self.options = options or NewtonOptions()
        self.comm = model.geometry.mesh.comm
        self.owned = basis.vectors.shape[0]
        self.V = np.ascontiguousarray(basis.vectors)
        self.W = None if enrichment is None else np.ascontiguousarray(enrichment)
        self.dual = dual(model, basis)
        self.reference = reference_state(model) if start is None else np.array(start, dtype=float)
        self._residual = jit.form(model.residual if residual is None else residual)
        self._jacobian = jit.form(model.jacobian if jacobian is None else jacobian)
        self._vector = fem.Function(model.space).x
        self._matrix = create_matrix(self._jacobian)
        self._fields = Fields(model)
        self.inversion = Inversion(model)
        displacement_gradient(model)  # compiled now, for the first step: later solves compile nothing
        self.state_dependent = StateDependent(model)
        self.coordinates = np.zeros(basis.size)
        self.description = f"reduced Galerkin: {basis.kind} basis of {basis.size} vectors"
        self.iterations_total = 0

    def set_start(self, start: np.ndarray) -> None:
        """The basis relative to ``start`` (a full local state array) from now on, and the model
        at it, q = 0: where a start found anew at every μ puts it (an imaged body's,
        :mod:`lungmech.rom.imaged`)."""
        self.reference = np.array(start, dtype=float)
        self.coordinates = np.zeros(self.basis.size)
        self.reconstruct(self.coordinates)

    def start_path(self) -> None:
        """A new load path begins (each reduced solve scales its own residual)."""

    def solve(self, start: np.ndarray | None = None) -> NewtonResult:
        """One reduced Newton solve from (the projection of) the current state, or of ``start``
        (a prediction; each reduced solve scales its own residual)."""
        if start is not None:
            self.set_state(start)
        return self._newton()

    def linear_step(self) -> None:
        """One reduced Newton step from the current state at the current loads (no line search)."""
        q = self.project()
        r = self.reduced_residual(q)
        try:
            step = np.linalg.solve(self.reduced_jacobian(), -r)
        except np.linalg.LinAlgError:  # a singular reduced tangent: as the full solver says it
            raise PETSc.Error(NOT_CONVERGED) from None
        self.reconstruct(q + step)

    def project(self) -> np.ndarray:
        """Coordinates q of the model's current state: (W V)ᵀ (x − x₀)."""
        x = self.model.state.x.array[: self.owned] - origin(self.model, self.reference)[: self.owned]
        return gram(self.dual, x[:, None], self.comm)[:, 0]

    def reconstruct(self, q: np.ndarray) -> None:
        """Set the model's state to x₀ + V q."""
        state = self.model.state.x
        state.array[:] = origin(self.model, self.reference)
        state.array[: self.owned] += self.V @ q
        state.scatter_forward()

    def reduced_residual(self, q: np.ndarray) -> np.ndarray:
        """Vᵀ R(x₀ + V q) (sets the model's state)."""
        return gram(self.V, self._residual_at(q)[:, None], self.comm)[:, 0]

    def _residual_at(self, q: np.ndarray) -> np.ndarray:
        """R(x₀ + V q), owned rows (sets the model's state)."""
        self.reconstruct(q)
        self.state_dependent.update()  # θ = Θ(x₀ + V q): balanced exactly at every iterate
        return assemble_owned(self._residual, self._vector, self.owned)

    def _tangent(self) -> PETSc.Mat:
        """K at the model's current state (the solver's matrix, overwritten)."""
        A = self._matrix
        A.zeroEntries()
        assemble_matrix(A, self._jacobian)  # type: ignore[arg-type]  # the into-a-matrix overload (singledispatch) is not in the hints
        A.assemble()
        return A

    def enriched_terms(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, Uᵀ R, Uᵀ K U) at x₀ + V q, q that of the model's state, U = [V W] the basis and
        its enrichment W: the residual and tangent of the enriched space (collective)."""
        q = self.project()
        assert self.W is not None, "enriched terms need an enrichment"
        residual, U = self._residual_at(q), np.hstack([self.V, self.W])
        return q, gram(U, residual[:, None], self.comm)[:, 0], gram(U, apply(self._tangent(), U, self.comm), self.comm)

    def reduced_jacobian(self) -> np.ndarray:
        """Vᵀ (K + U Wᵀ) V at the model's current state, U Wᵀ the tangent of state-dependent load
        coefficients (:mod:`lungmech.fem.state_dependent`)."""
        reduced = gram(self.V, apply(self._tangent(), self.V, self.comm), self.comm)
        if self.state_dependent:
            U, W = self.state_dependent.low_rank()
            reduced += gram(self.V, U, self.comm) @ gram(W, self.V, self.comm)
        return reduced

    def _newton(self) -> NewtonResult:
        q, converged, iterations, residuals, reason = newton(self, self.project(), self.options)
        self.iterations_total += iterations
        converged = converged and bool(np.all(np.isfinite(self.model.state.x.array)))
        if converged and (wrong := self.inversion()):
            converged, reason = False, f"{reason} to {wrong}"
        if converged:
            self.coordinates = q
        return NewtonResult(converged, iterations, tuple(residuals), reason)

    def floor(self) -> float:
        """‖|V|ᵀ ε|K|s‖: the round-off floor of Vᵀ R (see :mod:`lungmech.fem.convergence`)."""
        rounding = self._fields.rounding(self._matrix, self.model.state.x.petsc_vec)
        floor = float(
            np.linalg.norm(gram(np.abs(self.V), rounding.getArray(readonly=True)[: self.owned, None], self.comm))
        )
        rounding.destroy()
        return floor

    @property
    def residual_form(self) -> fem.Form:
        """The compiled residual form of the full model."""
        return self._residual

    @property
    def jacobian_form(self) -> fem.Form:
        """The compiled Jacobian form of the full model."""
        return self._jacobian

    def destroy(self) -> None:
        self._matrix.destroy()


def reduced_solver(basis: Basis, options: NewtonOptions | None = None) -> Callable[[ImplicitEuler], ReducedSolver]:
    """A factory of reduced Galerkin solvers on ``basis`` for the forms of a time-stepping scheme
    (:class:`lungmech.fem.dynamics.ImplicitEuler`): ``solver_factory`` of ``integrate``."""
    return lambda scheme: ReducedSolver(
        scheme.model, basis, options, residual=scheme.residual, jacobian=scheme.jacobian
    )


def check_basis(model: Model, basis: Basis) -> None:
    """A basis of another mesh or space is an error (collective)."""
    fingerprint = layout(model.space).fingerprint
    if basis.fingerprint != fingerprint:
        raise ParameterError(
            f"the basis was built on another mesh or space (fingerprint {basis.fingerprint}, "
            f"this model has {fingerprint})"
        )


class ReducedProblem(Protocol):
    """What :func:`newton` evaluates: a reduced residual r(q), then its tangent and round-off floor at that q."""

    def reduced_residual(self, q: np.ndarray) -> np.ndarray: ...

    def reduced_jacobian(self) -> np.ndarray: ...

    def floor(self) -> float: ...


# Newton's last step cut ‖r‖ by this factor or more: it is deep in its quadratic convergence,
# and the last tangent serves the next step (a chord step contracts ‖r‖ by about the tangent's
# relative change over the last step, itself of the order of that step's cut). On the bundled
# lung's inverse problem ‖r‖ fell 5e-2 → 1e-4 → 2e-9: the third tangent assembly, a fifth of a
# static point, is saved. (At 100, the first step's cut of 440× made the tangent serve where
# it was still a rough one: ‖r‖ then fell a hundredfold per step.)
CHORD = 1e4


def newton(
    problem: ReducedProblem, q: np.ndarray, options: NewtonOptions
) -> tuple[np.ndarray, bool, int, list[float], str]:
    """Newton's method on a reduced residual r(q) = 0 from ``q``, with a backtracking line search
    on ‖r‖: (q, converged, iterations, residual norms, reason). ``problem`` evaluates
    ``reduced_residual(q)``, then ``reduced_jacobian()`` and ``floor()`` (the round-off floor of r) at that q;
    once a step cut ‖r‖ by :data:`CHORD` or more, the next reuses its tangent.
    Converged when ‖r‖ ≤ max(rtol · the largest ‖r‖ met, atol, floor), or within ten floors once
    it arrived there quadratically (the last step cut it tenfold, or the one before already sat
    within ten floors), as the full solver's test (:mod:`lungmech.fem.convergence`): the floor is
    an estimate, and rounding the sampled sums (and θ of state-dependent loads) may exceed it."""
    r = problem.reduced_residual(q)
    residuals, floor = [float(np.linalg.norm(r))], 0.0
    for iteration in range(1, options.max_iterations + 1):
        if not np.isfinite(residuals[-1]):
            return q, False, iteration - 1, residuals, "DIVERGED_NANORINF"
        if iteration > 1 and _converged(residuals, max(options.rtol * max(residuals), options.atol), floor):
            return q, True, iteration - 1, residuals, "CONVERGED_FNORM"
        try:
            if iteration == 1 or residuals[-1] > residuals[-2] / CHORD:
                jacobian = problem.reduced_jacobian()
            if iteration == 1:  # the round-off floor of r, from the first tangent
                floor = problem.floor()
            step = np.linalg.solve(jacobian, -r)
        except np.linalg.LinAlgError:
            return q, False, iteration - 1, residuals, "DIVERGED_LINEAR_SOLVE"
        alpha = 1.0
        while True:
            trial = problem.reduced_residual(q + alpha * step)
            norm = float(np.linalg.norm(trial))
            if options.line_search in ("none", "basic") or norm <= (1 - 1e-4 * alpha) * residuals[-1] or alpha < 2**-10:
                break
            alpha /= 2
        q, r = q + alpha * step, trial
        residuals.append(norm)
    limit = max(options.rtol * max(residuals), options.atol, floor)
    return (
        q,
        False,
        options.max_iterations,
        residuals,
        f"DIVERGED_MAX_IT: reduced residual {residuals[-1]:.2e} > {limit:.2e}",
    )


def _converged(residuals: list[float], target: float, floor: float) -> bool:
    """‖r‖ at its target or floor, or within ten floors, arrived there quadratically."""
    now, before = residuals[-1], residuals[-2]
    return now <= max(target, floor) or (now <= 10 * floor and (before >= 10 * now or before <= 10 * floor))
