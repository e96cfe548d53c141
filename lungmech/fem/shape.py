"""The body's shape as parameters: a template mesh moved by shape modes.

A population's lungs are one template mesh Ω₀ moved by a map (a registration each). With shape
modes mᵢ on Ω₀ (vector fields, m: the SVD of a library of such maps), a patient's lung is
χ_a(Ω₀), where

    χ_a(x̂) = x̂ + Σᵢ aᵢ mᵢ(x̂),   G = ∇χ_a = I + Σᵢ aᵢ ∇mᵢ,

and the coefficients aᵢ (the parameters ``shape.mode_<i>``, 1, 2, …) are Constants (``fem.Constant``): the
model's forms, written on Ω₀ (:mod:`lungmech.fem.placement` puts G into every kinematic
quantity: ∇ₓ = ∇_x̂ (·) G⁻¹, dx = det G dx̂, n da = det G G⁻ᵀ n̂ dâ), answer for any shape
without a new mesh or a new compile. The map must not fold a cell: det G > 0 at every quadrature
point (:meth:`ShapeMap.check`). With modes of the mesh's own (Lagrange, coordinate) degree, χ_a
is exactly the mesh whose nodes are moved by Σ aᵢ mᵢ, and the model on Ω₀ is the model on that
mesh to round-off.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import ufl
from dolfinx import fem
from ufl.core.expr import Expr

from lungmech.errors import ParameterError

__all__ = ["KIND", "ShapeMap", "mode_target"]

KIND = "shape"  # the parameters' target kind: shape.mode_1, shape.mode_2, …


def mode_target(number: int) -> str:
    """The target of the ``number``-th mode's coefficient (1-based): ``shape.mode_<number>``."""
    return f"{KIND}.mode_{number}"


@dataclass(frozen=True)
class ShapeMap:
    """χ_a(x̂) = x̂ + Σᵢ aᵢ mᵢ(x̂) on the mesh of ``modes`` (vector Functions, m), the
    coefficients a in ``coefficients`` (dimensionless Constants, zero: the template itself)."""

    modes: tuple[fem.Function, ...]
    coefficients: tuple[fem.Constant, ...]

    @classmethod
    def of(cls, modes: Sequence[fem.Function]) -> ShapeMap:
        """The map of ``modes``, at a = 0; each a vector field of its mesh's dimension."""
        modes = tuple(modes)
        if not modes:
            raise ParameterError("a shape map needs at least one mode")
        mesh = modes[0].function_space.mesh
        for number, mode in enumerate(modes, start=1):
            if not isinstance(mode, fem.Function) or mode.function_space.mesh is not mesh:
                raise ParameterError(f"shape mode {number}: must be a Function on the model's mesh")
            if mode.ufl_shape != (mesh.geometry.dim,):
                raise ParameterError(
                    f"shape mode {number}: must be a vector field of {mesh.geometry.dim} components "
                    f"(got shape {mode.ufl_shape})"
                )
        return cls(modes, tuple(fem.Constant(mesh, 0.0) for _ in modes))

    @property
    def displacement(self) -> Expr:
        """Σᵢ aᵢ mᵢ (m): where the template's points move to."""
        return sum((a * m for a, m in zip(self.coefficients[1:], self.modes[1:])), self.coefficients[0] * self.modes[0])

    @property
    def gradient(self) -> Expr:
        """G = I + ∇(Σᵢ aᵢ mᵢ)."""
        return ufl.Identity(len(self.modes[0])) + ufl.grad(self.displacement)

    @property
    def targets(self) -> tuple[str, ...]:
        """The parameters' targets, mode by mode."""
        return tuple(mode_target(number) for number in range(1, len(self.modes) + 1))

    def assign(self, values: Mapping[str, float]) -> None:
        """Set a from ``values`` by target key (``mode_1`` …); the modes not named are a = 0."""
        self.set([float(values.get(f"mode_{number}", 0.0)) for number in range(1, len(self.modes) + 1)])

    def set(self, a: Sequence[float] | np.ndarray) -> None:
        """Set the coefficients to ``a``, mode by mode."""
        for coefficient, value in zip(self.coefficients, a, strict=True):
            coefficient.value = np.asarray(float(value))

    def values(self) -> np.ndarray:
        """The current coefficients a."""
        return np.array([float(c.value) for c in self.coefficients])

    def check(self, smallest_jacobian: Callable[[], float], named: Mapping[str, float]) -> None:
        """Refuse a folded map: ``smallest_jacobian()`` (det G, the smallest over every
        quadrature point, collective) must be positive; ``named``: the parameters that set a."""
        found = smallest_jacobian()
        if not found > 0.0:
            shown = "undefined" if np.isnan(found) else f"{found:.3g}"
            values = ", ".join(f"{name} = {value:.4g}" for name, value in named.items())
            raise ParameterError(
                f"the shape at {values} folds the mesh: det ∇χ = {shown} ≤ 0 at a quadrature point; "
                "narrow the shape parameters' ranges"
            )
