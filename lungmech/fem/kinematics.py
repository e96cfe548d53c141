"""Finite-strain kinematics as UFL expressions of a displacement field.

In 2-D the body is a slab seen in its plane (x, y): the state is u = (u_x, u_y)(x, y), and every
law sees the 3 × 3 deformation gradient

    F = [[1 + ∂u_x/∂x, ∂u_x/∂y, 0],
         [∂u_y/∂x, 1 + ∂u_y/∂y, 0],
         [0,           0,      λ₃]],

with the thickness stretch λ₃ = 1 in plane strain (a long body, its ends held) and an unknown
in plane stress (a thin plate, its faces free: λ₃ makes S₃₃ = 0). So J = det F, the invariants
and every law are those of the 3-D body; energies, volumes and forces are per unit reference
thickness.
"""

import ufl

PLANES = ("strain", "stress")


def deformation_gradient(
    u: ufl.core.expr.Expr, thickness_stretch: ufl.core.expr.Expr | None = None
) -> ufl.core.expr.Expr:
    """F = I + ∇u (gradient with respect to the reference configuration); for a 2-D u, the 3 × 3
    F of the slab with thickness stretch λ₃ (1: plane strain; the unknown of plane stress)."""
    d = len(u)
    G = ufl.Identity(d) + ufl.grad(u)
    if d == 3:
        return ufl.variable(G)
    stretch = 1.0 if thickness_stretch is None else thickness_stretch
    return ufl.variable(ufl.as_matrix([[G[0, 0], G[0, 1], 0.0], [G[1, 0], G[1, 1], 0.0], [0.0, 0.0, stretch]]))


def current_area_normal(F: ufl.core.expr.Expr, N: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """n da = J F⁻ᵀ N dA (Nanson): the current outward normal times the current area, per unit
    reference area. In 2-D (N in the plane, F 3 × 3) its in-plane part, per unit reference
    thickness (it carries λ₃: a plate thinning in plane stress offers less area)."""
    if len(N) == F.ufl_shape[0]:
        return ufl.det(F) * ufl.inv(F).T * N
    n = ufl.det(F) * ufl.inv(F).T * ufl.as_vector([N[0], N[1], 0.0])
    return ufl.as_vector([n[0], n[1]])


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
