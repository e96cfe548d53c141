"""Where the mesh lies: the body's reference configuration, or the body as imaged under load.

A model's forms are written with a few kinematic quantities of the mesh's points x
(:class:`Kinematics`): the reference position X, the displacement u from it, the deformation
gradient F, the reference volume dX and the reference area normal N dA. On a mesh of the
reference (the default) X = x, F = I + ∇u, dX = dx and N dA = N da.

An imaged body's mesh is instead its loaded state at the time it was imaged, t₀ (:class:`Image`),
and it never moves. Its reference is the image of the mesh under the *inverse map*
X(x) = x + ξ(x), with f = ∇ₓX = I + ∇ξ, and a later state is x + w(x), w the *motion* from the
image. Then (Govindjee & Mihalic 1996 for the inverse motion)

    F = (I + ∇w) f⁻¹,   dX = det f dx,   N dA = det f f⁻ᵀ n da,   u = w − ξ,

so the breath's potential is ∫ ψ(F) det f dx: every law, load and output written on the
reference holds unchanged. Two problems share these forms:

* ``Image.motion(t₀)``: the unknown is w (zero at t₀), ξ a given Function
  (:attr:`lungmech.fem.model.Model.reference_map`); the residual is δ_w Π, the tangent its
  derivative — symmetric where Π is a potential.
* ``Image.inverse(t₀)``: the unknown is ξ, with w = 0: the image's own equilibrium at the
  loads of t₀, R(ξ)[v] = ∂Π/∂w (w = 0, ξ)[v] = ∫ σ(f⁻¹) : ∇ₓv dx − (loads), the Cauchy stress
  balanced on the known deformed configuration. This residual is a mixed derivative of Π, not
  the gradient of any functional of ξ (the stationarity of Π in ξ is the balance of
  configurational forces, which differs at the boundary), so its tangent ∂R/∂ξ is not
  symmetric: it is solved with LU or GMRES, never with a symmetric factorisation or CG.

Other fields of the state (the lung's Φs, a mixed pressure) are unknowns of both problems.

A patient's shape is one factor more. On a template mesh x̂ mapped onto the image by
x = φ(x̂), g = ∇φ (a registration, :mod:`lungmech.registration`), the same forms hold with
∇ₓ = ∇_x̂ (·) g⁻¹ and dx = det g dx̂: F = (I + ∇_x̂ w g⁻¹)(I + ∇_x̂ ξ g⁻¹)⁻¹,
dX = det f det g dx̂ and N dA = det(f g) (f g)⁻ᵀ n̂ dâ; both problems and their unknowns are
unchanged, and g enters :class:`Kinematics` as f does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import dolfinx.mesh
import ufl
from ufl.core.expr import Expr

from lungmech import checks
from lungmech.errors import ParameterError
from lungmech.fem.kinematics import deformation_gradient

__all__ = ["Image", "Kinematics", "ReferenceMeasure", "kinematics"]


@dataclass(frozen=True)
class Image:
    """The mesh is the body imaged at ``time`` (s), loaded; the state's vector field is the
    ``unknown``: "motion" (w, from the image) or "inverse" (ξ = X − x, the inverse map's
    displacement, at w = 0: the inverse-motion problem)."""

    unknown: str
    time: float = 0.0
    UNKNOWNS: ClassVar[tuple[str, ...]] = ("motion", "inverse")

    def __post_init__(self) -> None:
        if self.unknown not in self.UNKNOWNS:
            raise ParameterError(f"image: unknown must be 'motion' or 'inverse' (got {self.unknown!r})")
        object.__setattr__(self, "time", checks.real("image: time", self.time))

    def check_start(self, time: float, body: str = "body") -> None:
        """A path of the imaged ``body`` starts at the time it was imaged, or is refused."""
        if abs(time - self.time) > 1e-12 * max(1.0, abs(time)):
            raise ParameterError(
                f"the {body} was imaged at t = {self.time:g} s; its path cannot start at t = {time:g} s"
            )

    @classmethod
    def motion(cls, time: float = 0.0) -> Image:
        """The breath from the image at ``time``: the unknown is the motion w."""
        return cls("motion", time)

    @classmethod
    def inverse(cls, time: float = 0.0) -> Image:
        """The image's equilibrium at ``time``: the unknown is the inverse map's ξ."""
        return cls("inverse", time)


class ReferenceMeasure(ufl.Measure):
    """dX = ``ratio`` dx (or dA = ``ratio`` da): a measure of the mesh that integrates over the
    reference.

    ``integrand * dX`` is ``(integrand * ratio) * dx``, so forms written on the reference hold on
    an imaged mesh. Calling it (``dX(1)``, another ``metadata``) keeps the ratio."""

    def __init__(self, dx: ufl.Measure, ratio: Expr) -> None:
        super().__init__(
            dx.integral_type(),
            domain=dx.ufl_domain(),
            subdomain_id=dx.subdomain_id(),
            metadata=dx.metadata(),
            subdomain_data=dx.subdomain_data(),
        )
        self.ratio = ratio

    def __call__(self, *args, **kwargs) -> ReferenceMeasure:  # type: ignore[no-untyped-def]  # ufl.Measure's own signature
        return ReferenceMeasure(super().__call__(*args, **kwargs), self.ratio)

    def __rmul__(self, integrand):  # type: ignore[no-untyped-def]  # ufl.Measure's own signature
        if isinstance(integrand, int | float):
            integrand = ufl.as_ufl(integrand)
        if not isinstance(integrand, Expr):
            return NotImplemented
        return super().__rmul__(integrand * self.ratio)


@dataclass(frozen=True)
class Kinematics:
    """The kinematic quantities a model's forms are written with, as UFL expressions of the
    mesh's points x (see the module): ``position`` X, ``u`` = current − X, ``F`` = ∂(current)/∂X
    (3 × 3 in 2-D, plane strain's λ₃ = 1 or the thickness stretch), ``volume_ratio`` dX/dx
    (None: 1, the mesh is the reference), ``area_normal`` N dA/da and ``motion`` w, the
    displacement from the mesh (u on the reference)."""

    position: Expr
    u: Expr
    F: Expr
    motion: Expr
    area_normal: Expr
    volume_ratio: Expr | None = None

    def reference_volume(self, dx: ufl.Measure) -> ufl.Measure:
        """dX from the mesh's ``dx``: ``dx`` itself on the reference, ``ratio · dx`` on an image."""
        return dx if self.volume_ratio is None else ReferenceMeasure(dx, self.volume_ratio)

    def reference_area(self, ds: ufl.Measure) -> ufl.Measure:
        """dA from the mesh's surface measure ``ds``: ``ds`` itself on the reference,
        |N dA/da| ds on an image."""
        if self.volume_ratio is None:
            return ds
        return ReferenceMeasure(ds, ufl.sqrt(ufl.dot(self.area_normal, self.area_normal)))


def kinematics(
    mesh: dolfinx.mesh.Mesh,
    vector: Expr,
    image: Image | None = None,
    reference_map: Expr | None = None,
    motion: Expr | None = None,
    thickness_stretch: Expr | None = None,
    shape: Expr | None = None,
) -> Kinematics:
    """The kinematics of a state whose vector field is ``vector``: u on a reference mesh
    (``image`` None); on an image, w (``image.unknown`` "motion", with ξ = ``reference_map``) or
    ξ (``image.unknown`` "inverse", with w = ``motion``, a zero Function the residual is the
    derivative along). ``shape``: the template map's displacement Σ aᵢ mᵢ (the mesh is a
    template x̂, the body's mesh x = x̂ + ``shape``, :mod:`lungmech.fem.shape`), or None."""
    x = ufl.SpatialCoordinate(mesh)
    N = ufl.FacetNormal(mesh)
    d = len(vector)
    if shape is None and image is None:  # the forms of a plain reference mesh, as they always were
        return Kinematics(x, vector, deformation_gradient(vector, thickness_stretch), vector, N)
    if shape is None:
        g_inv, ratio_g = ufl.Identity(d), None
    else:  # ∇ₓ = ∇_x̂ (·) g⁻¹, dx = det g dx̂, n da = det g g⁻ᵀ n̂ dâ
        g = ufl.Identity(d) + ufl.grad(shape)
        g_inv, ratio_g = ufl.inv(g), ufl.det(g)
        x = x + shape
        N = ratio_g * g_inv.T * N

    def grad(field: Expr) -> Expr:
        return ufl.grad(field) if shape is None else ufl.grad(field) * g_inv

    if image is None:
        F = ufl.Identity(d) + grad(vector)
        return Kinematics(x, vector, _embedded(F, thickness_stretch), vector, N, ratio_g)
    if image.unknown == "motion":
        assert reference_map is not None  # the model made it
        xi, w = reference_map, vector
    else:
        assert motion is not None  # the model made it
        xi, w = vector, motion
    f = ufl.Identity(d) + grad(xi)
    f_inv = ufl.inv(f)
    ratio = ufl.det(f) if ratio_g is None else ufl.det(f) * ratio_g
    F = (ufl.Identity(d) + grad(w)) * f_inv  # ∂(current)/∂x · ∂x/∂X
    return Kinematics(x + xi, w - xi, _embedded(F, thickness_stretch), w, ufl.det(f) * f_inv.T * N, ratio)


def _embedded(F: Expr, thickness_stretch: Expr | None) -> Expr:
    """``F`` as the variable laws differentiate by; a 2-D one as the 3 × 3 F of the slab with
    thickness stretch λ₃ (1: plane strain), see :mod:`lungmech.fem.kinematics`."""
    if F.ufl_shape[0] == 3:
        return ufl.variable(F)
    stretch = 1.0 if thickness_stretch is None else thickness_stretch
    return ufl.variable(ufl.as_matrix([[F[0, 0], F[0, 1], 0.0], [F[1, 0], F[1, 1], 0.0], [0.0, 0.0, stretch]]))
