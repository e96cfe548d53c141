"""Finite-strain kinematics as UFL expressions of a displacement field."""

import ufl


def deformation_gradient(u: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """F = I + ∇u (gradient with respect to the reference configuration)."""
    d = len(u)
    return ufl.variable(ufl.Identity(d) + ufl.grad(u))


def right_cauchy_green(F: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """C = FᵀF."""
    return F.T * F


def green_lagrange(F: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """E = ½(C − I)."""
    return 0.5 * (right_cauchy_green(F) - ufl.Identity(ufl.shape(F)[0]))


def small_strain(F: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """ε = sym(F − I), the linearised strain."""
    return ufl.sym(F - ufl.Identity(ufl.shape(F)[0]))


def invariants(F: ufl.core.expr.Expr) -> tuple[ufl.core.expr.Expr, ufl.core.expr.Expr, ufl.core.expr.Expr]:
    """(I1, I2, J) with I1 = tr C, I2 = ½(I1² − tr C²), J = det F."""
    C = right_cauchy_green(F)
    I1 = ufl.tr(C)
    I2 = 0.5 * (I1**2 - ufl.tr(C * C))
    return I1, I2, ufl.det(F)
