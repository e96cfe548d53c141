"""Loads whose coefficients are global functionals of the state, kept exact inside Newton.

A :class:`lungmech.fem.loads.StateDependentWork` W(u, θ; v) has coefficients θ = Θ(u) (balanced
gravity: the centre of mass and the pressure that carries the weight). The residual seen by Newton
is R(u, Θ(u)), with θ recomputed from every iterate, and its tangent is

    J = K + U Vᵀ,   K = ∂R/∂u at frozen θ,   U = ∂R/∂θ = −∂W/∂θ,   V = (dΘ/du)ᵀ,

a sparse matrix plus a correction of rank m = dim θ (12 for gravity). Newton on this J converges
quadratically, and only K is ever factorised: the exact step follows from Woodbury's identity

    J⁻¹ r = y − Z (I + Vᵀ Z)⁻¹ Vᵀ y,   y = K⁻¹ r,   Z = K⁻¹ U,

i.e. m + 1 solves with the one factorisation; a Krylov solver applies J itself instead.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np
import ufl
from dolfinx import fem

from lungmech import jit
from lungmech.fem.quantities import assemble_owned, vector_integral
from lungmech.parallel.linalg import gram
from lungmech.parallel.owned import owned_size

if TYPE_CHECKING:
    from lungmech.fem.model import Model


@dataclass(frozen=True)
class Integral:
    """An integral a state-dependent load's coefficients are computed from: ∫ ``expr`` over
    ``measure`` (any value shape). ``affine``: affine in the state (e.g. the first moment of
    mass, ∫ρ₀ x dX with x = X + u), which a reduced model evaluates exactly."""

    expr: ufl.core.expr.Expr
    measure: ufl.Measure
    affine: bool = False


Bilinear = Callable[[ufl.core.expr.Expr, ufl.core.expr.Expr], ufl.Form]  # form(l, r), linear in each


class Integration(Protocol):
    """How a state-dependent load evaluates what its coefficients need (collective calls)."""

    def vector(self, name: str, expr: ufl.core.expr.Expr, measure: ufl.Measure) -> Callable[[], np.ndarray]:
        """∫ ``expr`` over ``measure``: the integral ``name`` (one of the load's ``integrals``) or
        a derivative of it with respect to a coefficient."""
        ...

    def column(self, name: str, form: ufl.Form) -> Callable[[], np.ndarray]:
        """A linear ``form`` in the model's test function, as a column of the solver's unknowns:
        the derivative with respect to the state of the integral ``name``, or, for ``name`` =
        "residual", of the load's own virtual work."""
        ...

    def columns(self, name: str, form: ufl.Form, constant: fem.Constant) -> Callable[[], np.ndarray]:
        """The columns (as :meth:`column`'s) of a ``form`` linear in ``constant``, one per entry of
        ``constant`` set to 1 and the others to 0 (in its flattened order), side by side."""
        ...

    def bilinear_columns(
        self, name: str, form: Bilinear, left: fem.Constant, right: fem.Constant
    ) -> Callable[[], tuple[np.ndarray, np.ndarray]]:
        """Both partial derivatives of the form ``form(l, r)``, linear in each of two vectors,
        as columns: (its columns over ``right``'s entries with l = ``left``, its columns over
        ``left``'s entries with r = ``right``), each as :meth:`columns`'. A function of the two
        vectors, so that an integration may put anything in their place (a derivative's form
        cannot have its constants replaced without being expanded first)."""
        ...


class FullIntegration:
    """Integrals over the whole mesh, columns as the owned dofs of the model's space."""

    def __init__(self, model: Model) -> None:
        self.mesh, space = model.geometry.mesh, model.space
        self._vector = fem.Function(space).x
        self._owned = owned_size(space)

    def vector(self, name: str, expr: ufl.core.expr.Expr, measure: ufl.Measure) -> Callable[[], np.ndarray]:
        return vector_integral(expr, measure, self.mesh)

    def column(self, name: str, form: ufl.Form) -> Callable[[], np.ndarray]:
        compiled = jit.form(form)
        return lambda: assemble_owned(compiled, self._vector, self._owned)

    def columns(self, name: str, form: ufl.Form, constant: fem.Constant) -> Callable[[], np.ndarray]:
        column = self.column(name, form)
        return lambda: each_unit(constant, column)

    def bilinear_columns(
        self, name: str, form: Bilinear, left: fem.Constant, right: fem.Constant
    ) -> Callable[[], tuple[np.ndarray, np.ndarray]]:
        # two sets of unit evaluations: one merged form would cost every evaluation both terms
        both = form(left, right)
        over_right, over_left = self.columns(name, both, right), self.columns(name, both, left)
        return lambda: (over_right(), over_left())


def each_unit(constant: fem.Constant, evaluate: Callable[[], np.ndarray]) -> np.ndarray:
    """``evaluate()`` with ``constant`` set to each unit vector in turn (flattened order), as
    columns side by side; ``constant`` keeps its value."""
    kept = np.array(constant.value, copy=True)
    units = np.eye(kept.size)
    try:
        columns = []
        for unit in units:
            constant.value = unit.reshape(kept.shape)
            columns.append(evaluate())
    finally:
        constant.value = kept
    return np.column_stack(columns)


class StateDependent:
    """The state-dependent loads of one model: θ ← Θ(u), and the low-rank part of the tangent."""

    def __init__(self, model: Model) -> None:
        self.terms = model.state_dependent
        space = model.space
        self.owned = owned_size(space)
        self.comm = space.mesh.comm
        self._constrained = model.constrained_dofs()  # their rows carry the constraint: U vanishes there

    def __bool__(self) -> bool:
        return bool(self.terms)

    def update(self) -> None:
        """Set every term's coefficients from the model's current state: θ = Θ(u)."""
        for term in self.terms:
            term.update()

    def low_rank(self) -> tuple[np.ndarray, np.ndarray]:
        """(U, V), owned rows × m, with J = K + U Vᵀ at the current state (after :meth:`update`)."""
        pairs = [term.linearise() for term in self.terms]
        U = -np.hstack([work for work, _ in pairs])
        V = np.hstack([gradient for _, gradient in pairs])
        U[self._constrained] = 0.0
        return U, V

    def woodbury(
        self, y: np.ndarray, U: np.ndarray, V: np.ndarray, solve: Callable[[np.ndarray], np.ndarray]
    ) -> np.ndarray:
        """(K + U Vᵀ)⁻¹ r from y = K⁻¹ r, with ``solve(b)`` = K⁻¹ b (owned rows; a column or
        several side by side; collective)."""
        Z = np.column_stack([solve(U[:, j]) for j in range(U.shape[1])])
        small = np.eye(U.shape[1]) + gram(V, Z, self.comm)
        columns = y.reshape(len(y), -1)
        corrected = columns - Z @ np.linalg.solve(small, gram(V, columns, self.comm))
        return corrected.reshape(y.shape)
