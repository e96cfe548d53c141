"""Gravity, optionally balanced by a heterogeneous pleural pressure (after Peyraut & Genet 2024).

The weight of the lung, ∫ ρ0 g dX, is carried in vivo by the pleural pressure, which is higher
(less negative) at the bottom than at the top. With ``balanced_on`` boundaries, this load adds
to the dead weight a follower pressure on those boundaries,

    q(x) = b · y + y · B y,   y = (x − x_G) / L,

with x the current position, x_G the current centre of mass and L a fixed length. Its gradient
b (the hydrostatic part) and the symmetric B (the least correction, smallest |B|) are chosen at
every residual evaluation so that the pressure's resultant force and moment cancel those of the
weight exactly: the held region (hilum) then carries no weight. On a closed surface with
x_G at the volume centroid, B = 0 and b = L M g/|ω|: the hydrostatic pressure of a fluid of the
lung's mean density. The moment condition needs the quadratic term otherwise, since a
pressure linear in x has the moment of a buoyant body about the volume centroid.

The coefficients are global functionals of the state, θ = Θ(u). They are kept exact: θ is
recomputed from the state before every residual evaluation, and the Newton tangent carries their
derivative dΘ/du (a rank-12 term, see :mod:`lungmech.fem.state_dependent`), so one Newton solve
converges quadratically to a state that is balanced exactly. The length L is a Constant, so
another mesh of the same kind reuses the compiled forms.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

import numpy as np
import ufl
from dolfinx import fem
from ufl.algorithms import expand_derivatives
from ufl.core.expr import Expr

from lungmech import checks
from lungmech.errors import ParameterError
from lungmech.fem.loads import Named, StateDependentWork
from lungmech.fem.ramp import Ramp
from lungmech.fem.state_dependent import FullIntegration, Integral, Integration

if TYPE_CHECKING:
    from lungmech.fem.model import Model


def _quadratic_basis(y: Expr) -> list[Expr]:
    """b·y + y·B y as a linear combination: (y1, y2, y3, y1², y2², y3², 2y1y2, 2y1y3, 2y2y3)."""
    return [y[0], y[1], y[2], y[0] ** 2, y[1] ** 2, y[2] ** 2, 2 * y[0] * y[1], 2 * y[0] * y[2], 2 * y[1] * y[2]]


# Weights of the nine coefficients in |B|² (b is free): off-diagonal entries count twice.
_NORM = np.diag([0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 2.0, 2.0, 2.0])


@dataclass(frozen=True)
class Gravity(Named):
    """The weight ρ0 g per unit reference volume, optionally balanced by pleural pressure.

    Args:
        density: mass per unit reference volume ρ0 (for the lung, the solid density times Φs0;
            the air weighs nothing).
        acceleration: the gravity vector g, e.g. (0, 0, −9.81) for an upright patient.
        balanced_on: boundaries carrying the balancing pressure (e.g. pleura, diaphragm,
            mediastinum); empty: the held region carries the weight.
        ramp: time profile of g.
    """

    density: float
    acceleration: Sequence[float]
    balanced_on: tuple[str, ...] = ()
    ramp: Ramp = field(default_factory=Ramp)
    name: str = ""
    kind: ClassVar[str] = "gravity"

    def __post_init__(self) -> None:
        checks.real("gravity: density", self.density, positive=True)
        try:
            object.__setattr__(self, "acceleration", checks.vector("acceleration", self.acceleration, (2, 3)))
        except ParameterError:
            raise ParameterError(f"gravity: acceleration needs 2 or 3 components (got {self.acceleration!r})") from None
        object.__setattr__(self, "balanced_on", checks.names("gravity: balanced_on", self.balanced_on, empty=True))
        if not isinstance(self.ramp, Ramp) or not isinstance(self.name, str):
            raise ParameterError("gravity: ramp must be a Ramp and name a string")

    @property
    def value(self) -> Sequence[float]:
        return self.acceleration

    def potential(self, model: Model, value: Expr) -> ufl.Form:
        return -self.density * ufl.dot(value, model.u) * model.dx

    def virtual_work(self, model: Model, v: Expr, value: fem.Constant) -> StateDependentWork | None:
        if not self.balanced_on:
            return None
        if model.geometry.mesh.geometry.dim != 3:
            raise ParameterError(
                "gravity: balanced_on is for 3-D bodies; in 2-D the weight is carried where it is held"
            )
        pressure = _BalancingPressure(self, model, v, value)
        # bound to the whole mesh when the full solver first asks (a hyper-reduced model binds
        # its own integration, and never compiles these)
        full = functools.cache(lambda: pressure.bind(FullIntegration(model)))
        return StateDependentWork(
            pressure.form, lambda: full().update(), lambda: full().linearise(), pressure.integrals, pressure.bind
        )


class _BalancingPressure:
    """The balancing pressure q = Σ c_k φ_k((x − x_G)/L) on the balanced boundaries: its virtual
    work, and the integrals its coefficients θ = (x_G, c) = Θ(u) and their derivatives come from
    (:meth:`bind` evaluates them on the whole mesh, or on a hyper-reduced model's sample).

    Θ is defined by x_G = ∫ρ0 x dX / ∫ρ0 dX and the least-correction conditions

        [N  Aᵀ] [c]   [   0   ]
        [A  0 ] [λ] = [−M g; 0]     (A c: the force and moment of q about x_G; N: the |B|² weights)

    so dΘ/du follows from the implicit-function theorem: with dA = A_u δu + A_xG δx_G,
    [dc; dλ] = −K⁺ [dAᵀλ; dA c]. Row j of dc/du is the derivative of the one functional
    Σ_ik T⁽ʲ⁾_ik A_ik(u, x_G), T⁽ʲ⁾ = λ ⊗ K⁺_{j,c} + K⁺_{j,λ} ⊗ c, so one compiled form serves
    all nine rows.
    """

    def __init__(self, gravity: Gravity, model: Model, v: Expr, value: fem.Constant) -> None:
        geometry = model.geometry
        mesh = geometry.mesh
        self.value = value
        # A Constant, not a literal: a new mesh (a new patient) reuses the compiled forms.
        length = fem.Constant(mesh, geometry.size)
        self.centre = fem.Constant(mesh, np.zeros(3))
        self.coefficients = fem.Constant(mesh, np.zeros(9))
        centre = ufl.variable(self.centre)  # so that ∂/∂x_G is ufl.diff
        x = model.position + model.u  # the current position
        y = x - centre
        basis = ufl.as_vector(_quadratic_basis(y / length))
        q = ufl.dot(self.coefficients, basis)
        F = model.F
        n_da = ufl.det(F) * ufl.inv(F).T * model.area_normal  # Nanson: current n da per mesh area
        self.surface = surface = geometry.ds(gravity.balanced_on)
        self.form = -q * ufl.dot(n_da, v) * surface

        # A: resultant force and moment (about x_G) of −φ_k n da for each basis pressure φ_k;
        # [mass, first moment]: recomputed with the rest, as the reference itself may move (inverse problem)
        response = ufl.as_matrix(
            [[-basis[k] * n_da[i] for k in range(9)] for i in range(3)]
            + [[-basis[k] * ufl.cross(y, n_da)[i] for k in range(9)] for i in range(3)]
        )
        self.integrals = {
            # affine in the state on a reference mesh; on an image dX = det(I + ∇ξ) dx, and ξ
            # moves with μ (the inverse problem's unknown; a reduced breath's coefficient); on a
            # shape map x and dX = det G dx̂ move with a (parameters): sampled, not affine
            "moments": Integral(
                gravity.density * ufl.as_vector([1, *x]), model.dx, affine=model.image is None and model.shape is None
            ),
            "response": Integral(response, surface),
        }
        w = ufl.TestFunction(model.space)
        # ∂W/∂θ · (d, a), W the virtual work above
        self.direction = fem.Constant(mesh, np.zeros(12))  # (d, a): along the centre, along the coefficients
        d = ufl.as_vector([self.direction[i] for i in range(3)])
        a = ufl.as_vector([self.direction[3 + i] for i in range(9)])
        self.work_derivative = -(ufl.dot(a, basis) + ufl.dot(ufl.diff(q, centre), d)) * ufl.dot(n_da, v) * surface
        # lᵀ A r's derivative in u (a vector), for the rank-2 weights λ ⊗ q + r ⊗ c of dΘ/du
        # (its columns over r with l = λ, and over l with r = c: the integration's bilinear
        # columns); ∂A/∂x_G (6 × 9 × 3 numbers, contracted in numpy)
        self.left, self.right = fem.Constant(mesh, np.zeros(6)), fem.Constant(mesh, np.zeros(9))

        def contraction_u(left: Expr, right: Expr, test: Expr | None = None) -> ufl.Form:
            return ufl.derivative(ufl.dot(left, response * right) * surface, model.state, w if test is None else test)

        self.contraction_u = contraction_u
        self.response_centre = ufl.diff(response, centre)
        # ∂(∫ρ0 x_a dX)/∂u, a = 1, 2, 3 (independent of the state on a reference mesh)
        self.first_moment_u = [ufl.derivative(gravity.density * x[a] * model.dx, model.state, w) for a in range(3)]
        # ∂M/∂u of the mass M = ∫ρ0 dX, None where it is 0: on the reference, and on an image's
        # motion (dX = det(I + ∇ξ) dx); the inverse problem's M moves with its unknown ξ
        mass_u = ufl.derivative(gravity.density * model.dx, model.state, w)
        self.mass_u = None if expand_derivatives(mass_u).empty() else mass_u

        # Can these boundaries balance a weight along g at all? Checked once, on the reference
        # of a whole body (a hyper-reduced model's piece of one holds a few of its cells only).
        if geometry.whole is not None:
            return
        full = FullIntegration(model)
        mass, first_moment = np.split(full.vector("moments", *self._integral("moments"))(), [1])
        self.centre.value = first_moment / mass
        A = full.vector("response", *self._integral("response"))()
        target = np.concatenate([-mass * np.asarray(gravity.acceleration, dtype=float), np.zeros(3)])
        if np.linalg.norm(A @ _least_correction(A, target)[0] - target) > 1e-8 * np.linalg.norm(target):
            raise ParameterError(
                f"gravity: no pressure on {', '.join(gravity.balanced_on)} can balance the weight's force "
                "and moment; name the boundaries that surround the body (e.g. pleura, diaphragm, mediastinum)"
            )

    def _integral(self, name: str) -> tuple[Expr, ufl.Measure]:
        return self.integrals[name].expr, self.integrals[name].measure

    def bind(self, integration: Integration) -> _Balance:
        """θ = Θ(u) and its linearisation, with every integral evaluated by ``integration``."""
        return _Balance(self, integration)


class _Balance:
    """Θ and dΘ/du of one balancing pressure, its integrals evaluated by one integration."""

    def __init__(self, pressure: _BalancingPressure, integration: Integration) -> None:
        self.pressure = p = pressure
        self._moments = integration.vector("moments", *p._integral("moments"))
        self._response = integration.vector("response", *p._integral("response"))
        self._work_derivative = integration.columns("residual", p.work_derivative, p.direction)
        # (λᵀ (∂A/∂u) e_k, e_iᵀ (∂A/∂u) c)
        self._response_u = integration.bilinear_columns("response", p.contraction_u, p.left, p.right)
        self._response_centre = integration.vector("response", p.response_centre, p.surface)
        self._first_moment_u = [integration.column("moments", form) for form in p.first_moment_u]
        self._mass_u = None if p.mass_u is None else integration.column("moments", p.mass_u)

    def update(self) -> None:
        """θ ← Θ(u): the centre of mass and the least correction balancing the current weight."""
        p = self.pressure
        mass, first_moment = np.split(self._moments(), [1])
        self.mass = float(mass[0])
        p.centre.value = first_moment / mass  # the response is measured about the new centre
        self._A = self._response()
        weight = mass * np.asarray(p.value.value, dtype=float)
        # The pressure's force cancels the weight; its moment about x_G is zero, like the weight's.
        p.coefficients.value, self._multipliers, self._kkt_inverse = _least_correction(
            self._A, np.concatenate([-weight, np.zeros(3)])
        )

    def linearise(self) -> tuple[np.ndarray, np.ndarray]:
        """(∂W/∂θ, dΘ/du) at the current state (after :meth:`update`), as columns of the
        integration's unknowns."""
        p = self.pressure
        work = self._work_derivative()  # the 12 directions θ = (x_G, c) at once
        # dx_G/du = (∂(∫ρ0 x dX)/∂u − x_G ∂M/∂u) / M
        mass_u = None if self._mass_u is None else self._mass_u()
        centre_u = [moment() / self.mass for moment in self._first_moment_u]
        if mass_u is not None:
            centre_u = [column - p.centre.value[a] * mass_u / self.mass for a, column in enumerate(centre_u)]
        Q, c, lam = self._kkt_inverse[:9], p.coefficients.value, self._multipliers
        response_centre = self._response_centre()
        # Σ T_ik ∂A_ik/∂u for T_j = λ ⊗ Q_j[:9] + Q_j[9:] ⊗ c: from 9 + 6 columns
        p.left.value, p.right.value = lam, c
        left, right = self._response_u()
        # along[j, d] = Σ_ik T⁽ʲ⁾_ik ∂A_ik/∂x_G,d, contracted for all nine rows at once (a loop
        # over j cost a third of the reduced tangent online)
        along = Q[:, :9] @ np.einsum("i,ikd->kd", lam, response_centre) + Q[:, 9:] @ np.einsum(
            "k,ikd->id", c, response_centre
        )
        centre = np.column_stack(centre_u)
        coefficients = -(left @ Q[:, :9].T + right @ Q[:, 9:].T + centre @ along.T)
        if mass_u is not None:  # and the weight's, −M g the force the pressure balances: c = Q[:, 9:12] (−M g)
            coefficients += np.outer(mass_u, Q[:, 9:12] @ -np.asarray(p.value.value, dtype=float))
        return work, np.hstack([centre, coefficients])

    def rounding(self) -> np.ndarray:
        """The size of θ's rounding errors (after :meth:`update`): ε |x_G| for the centre, and
        for the coefficients Skeel's componentwise bound on the KKT solve that gives them,
        ε |K⁺| (|K| |s| + |b|), s = (c, λ) and b its right-hand side (a normwise condition number
        would be far too pessimistic: the force and moment rows of A carry m² and m³)."""
        p = self.pressure
        kkt = np.block([[_NORM, self._A.T], [self._A, np.zeros((6, 6))]])
        solution = np.concatenate([p.coefficients.value, self._multipliers])
        weight = self.mass * np.asarray(p.value.value, dtype=float)
        rhs = np.concatenate([np.zeros(9), -weight, np.zeros(3)])
        eps = np.finfo(float).eps
        bound = eps * np.abs(self._kkt_inverse) @ (np.abs(kkt) @ np.abs(solution) + np.abs(rhs))
        return np.concatenate([eps * np.abs(p.centre.value), bound[:9]])


def _least_correction(A: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients c of A c = target with the smallest |B| (b is left free), their multipliers λ
    and the (pseudo-)inverse of the KKT matrix [[N, Aᵀ], [A, 0]] they solve."""
    kkt = np.block([[_NORM, A.T], [A, np.zeros((6, 6))]])
    # symmetric equilibration before the SVD: A's force and moment rows carry m² and m³, and the
    # unscaled system's condition number (~1e9 on a lung) would round c to ~1e-7 of itself
    largest = np.abs(kkt).max(axis=1)
    scale = 1.0 / np.sqrt(np.where(largest > 0, largest, 1.0))  # a zero row (an unbalanceable load) stays
    equilibrated = scale[:, None] * kkt * scale[None, :]
    inverse = _inverse(equilibrated)
    inverse = scale[:, None] * inverse * scale[None, :]
    solution = inverse @ np.concatenate([np.zeros(9), target])
    return solution[:9], solution[9:], inverse


def _inverse(matrix: np.ndarray) -> np.ndarray:
    """The inverse of an equilibrated KKT matrix by LU (a tenth of an SVD's cost: it is taken at
    every residual evaluation, online too), or its pseudo-inverse where it is singular (a
    boundary that cannot carry a moment: the least-squares balance, as before the LU)."""
    try:
        inverse = np.linalg.inv(matrix)
        if np.all(np.isfinite(inverse)) and np.abs(matrix @ inverse - _IDENTITY).max() <= 1e-10:
            return inverse
    except np.linalg.LinAlgError:
        pass
    return np.linalg.pinv(matrix)


_IDENTITY = np.eye(15)
