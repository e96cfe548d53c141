"""Hyperelastic strain-energy laws.

A law is a small frozen dataclass with one method, ``psi(F) -> ufl.Expr``: the strain energy per
unit reference volume (Pa = J/m³). Stresses are never written by hand; they come from UFL
differentiation (see :func:`first_piola`). Parameters are plain floats (validated on
construction) or UFL expressions such as ``dolfinx.fem.Constant`` (see :func:`with_constants`),
so one compiled form serves every parameter value.

Notation, used in every docstring below: F the deformation gradient, C = FᵀF, I1 = tr C,
I2 = ½(I1² − tr C²), J = det F, E = ½(C − I) (Green–Lagrange), ε = sym(F − I) (linearised
strain). Moduli are in Pa, ratios and exponents are dimensionless (unit 1). "Small-strain limit"
names the Lamé parameters (μ, λ) of the linear law that ψ agrees with to second order in ∇u;
the small-strain bulk modulus is then K = λ + 2μ/3.

Laws with a volumetric split (``psi = psi_iso + bulk/2 · g(J)²``, see :class:`VolumetricSplit`)
also run in the mixed displacement–pressure formulation, which stays accurate as ν → 0.5 and is
exactly incompressible when ``bulk = inf``.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping
from typing import TYPE_CHECKING

import ufl

from lungmech.fem.law_base import Material, Param, VolumetricSplit, lame_from_young
from lungmech.fem.laws import (
    CiarletGeymonat,
    ExponentialCiarletGeymonat,
    LinearElastic,
    MooneyRivlin,
    NeoHookean,
    SaintVenantKirchhoff,
    StableNeoHookean,
    Sum,
)

if TYPE_CHECKING:
    import dolfinx.mesh

__all__ = [
    "LAWS",
    "CiarletGeymonat",
    "ExponentialCiarletGeymonat",
    "LinearElastic",
    "Material",
    "MooneyRivlin",
    "NeoHookean",
    "Param",
    "SaintVenantKirchhoff",
    "StableNeoHookean",
    "Sum",
    "VolumetricSplit",
    "first_piola",
    "lame_from_young",
    "numbers_of",
    "shear_modulus",
    "with_constants",
    "with_values",
]


def numbers_of(law: Material) -> dict[str, float]:
    """The law's numeric parameters by path: ``"mu"``, or ``"terms[1].c1"`` inside a :class:`Sum`.

    Parameters already given as UFL expressions are left out.
    """
    if isinstance(law, Sum):
        return {f"terms[{i}].{path}": v for i, term in enumerate(law.terms) for path, v in numbers_of(term).items()}
    values = {f.name: getattr(law, f.name) for f in dataclasses.fields(law)}
    return {name: float(v) for name, v in values.items() if isinstance(v, numbers.Real) and not isinstance(v, bool)}


def with_values(law: Material, values: Mapping[str, Param]) -> Material:
    """A copy of ``law`` with the parameters at the paths of :func:`numbers_of` replaced."""
    if isinstance(law, Sum):
        parts: list[dict[str, Param]] = [{} for _ in law.terms]
        for path, v in values.items():
            index, _, rest = path.removeprefix("terms[").partition("].")
            parts[int(index)][rest] = v
        return dataclasses.replace(law, terms=tuple(with_values(term, part) for term, part in zip(law.terms, parts)))
    return dataclasses.replace(law, **values) if values else law


def with_constants(law: Material, mesh: dolfinx.mesh.Mesh) -> Material:
    """A copy of ``law`` whose finite parameters are ``fem.Constant`` objects on ``mesh``.

    Forms built from it compile once; changing a parameter is then ``law.mu.value = ...``.
    Infinite parameters (incompressible limits) stay floats: they change the form's structure.
    A :class:`Sum` is converted term by term. Values and units are unchanged.
    """
    from dolfinx import fem

    finite = {path: v for path, v in numbers_of(law).items() if math.isfinite(v)}
    return with_values(law, {path: fem.Constant(mesh, v) for path, v in finite.items()})


def first_piola(law: Material, F: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """The first Piola–Kirchhoff stress P = ∂ψ/∂F (Pa) by UFL differentiation.

    ``F`` must be a ``ufl.variable``. The Cauchy stress is σ = J⁻¹ P Fᵀ.
    """
    return ufl.diff(law.psi(F), F)


def shear_modulus(law: Material, mesh: dolfinx.mesh.Mesh) -> ufl.core.expr.Expr:
    """The initial shear modulus μ₀ = ∂²ψ/∂γ² at γ = 0 of a simple shear F = I + γ e₁⊗e₂ (Pa; a
    UFL expression, a field where the law's parameters are). J = 1 in simple shear, so a split
    law's bulk term adds nothing and ψ_iso is used (it is defined also for bulk = inf).
    Neo-Hookean: μ; Mooney–Rivlin: 2(c1 + c2)."""
    from dolfinx import fem

    gamma = ufl.variable(fem.Constant(mesh, 0.0))
    F = ufl.variable(ufl.Identity(3) + gamma * ufl.outer(ufl.unit_vector(0, 3), ufl.unit_vector(1, 3)))
    psi = law.psi_iso(F) if isinstance(law, VolumetricSplit) else law.psi(F)
    return ufl.diff(ufl.diff(psi, gamma), gamma)


# The laws a scene names by `law = "..."` (besides the composite `sum` and `lung_skeleton`).
LAWS: dict[str, type] = {
    law.name: law
    for law in (
        LinearElastic,
        SaintVenantKirchhoff,
        NeoHookean,
        StableNeoHookean,
        MooneyRivlin,
        CiarletGeymonat,
        ExponentialCiarletGeymonat,
    )
}
