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
from ufl.algorithms import expand_derivatives
from ufl.algorithms.analysis import has_exact_type
from ufl.differentiation import CoefficientDerivative

from lungmech import jit
from lungmech.fem.quantities import assemble_owned, vector_integral
from lungmech.fem.stacked import StackedSpace, stacked_form, units
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


class Bilinear(Protocol):
    """A form a(l, r; w) linear in each of two vectors l and r (and in the test function w: the
    model's own where ``test`` is None), none of whose integrals a unit l or r zeroes as a whole
    (:func:`lungmech.fem.stacked.stacked_form`)."""

    def __call__(
        self, left: ufl.core.expr.Expr, right: ufl.core.expr.Expr, test: ufl.core.expr.Expr | None = None
    ) -> ufl.Form: ...


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
    """Integrals over the whole mesh, columns as the owned dofs of the model's space. The
    columns of a form linear in a constant are assembled together, over a test space of as
    many copies of the model's element (:mod:`lungmech.fem.stacked`): one pass over the mesh
    for all of them (on a lung's balanced weight, 4.5 to 7 times faster than one per column)."""

    def __init__(self, model: Model) -> None:
        self.mesh, self.space = model.geometry.mesh, model.space
        self._vector = fem.Function(self.space).x
        self._owned = owned_size(self.space)
        self._stacks: dict[int, StackedSpace] = {}

    def vector(self, name: str, expr: ufl.core.expr.Expr, measure: ufl.Measure) -> Callable[[], np.ndarray]:
        return vector_integral(expr, measure, self.mesh)

    def column(self, name: str, form: ufl.Form) -> Callable[[], np.ndarray]:
        compiled = jit.form(form)
        return lambda: assemble_owned(compiled, self._vector, self._owned)

    def columns(self, name: str, form: ufl.Form, constant: fem.Constant) -> Callable[[], np.ndarray]:
        (test,) = form.arguments()
        plain = _replaceable(form)
        return self._stacked(
            lambda unit, copy: ufl.replace(plain, {constant: unit} | ({} if copy is None else {test: copy})),
            constant.ufl_shape,
        )

    def bilinear_columns(
        self, name: str, form: Bilinear, left: fem.Constant, right: fem.Constant
    ) -> Callable[[], tuple[np.ndarray, np.ndarray]]:
        # two stacked assemblies: one merged form would cost every column both terms
        over_right = self._stacked(lambda unit, copy: form(left, unit, copy), right.ufl_shape)
        over_left = self._stacked(lambda unit, copy: form(unit, right, copy), left.ufl_shape)
        return lambda: (over_right(), over_left())

    def _stacked(
        self, form_of: Callable[[ufl.core.expr.Expr, ufl.core.expr.Expr | None], ufl.Form], shape: tuple[int, ...]
    ) -> Callable[[], np.ndarray]:
        """The columns Σ_k a(e_k; w_k) of ``form_of(e_k, w_k)`` (w_k None: the model's own test
        function), e_k the unit tensors of ``shape``, in one assembly."""
        copies = int(np.prod(shape, dtype=int))
        if copies == 1:
            column = self.column("", form_of(units(shape)[0], None))
            return lambda: column()[:, None]
        if copies not in self._stacks:
            self._stacks[copies] = StackedSpace(self.space, copies)
        stack = self._stacks[copies]
        compiled = jit.form(stacked_form(stack, form_of, shape))
        return lambda: stack.columns(compiled)


def _replaceable(form: ufl.Form) -> ufl.Form:
    """``form`` with its derivatives in a coefficient applied (UFL replaces nothing under one),
    the others (of variables) kept."""
    if any(has_exact_type(integral.integrand(), CoefficientDerivative) for integral in form.integrals()):
        return expand_derivatives(form)
    return form


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
