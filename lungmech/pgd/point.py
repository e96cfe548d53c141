"""One answer of a :class:`~lungmech.pgd.model.PGDModel` at μ: the terms' products q(μ) and
what the outputs at each time need, made once (an answer's whole online cost)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from lungmech.fem.sensitivity import ValueDerivatives
from lungmech.pgd import terms as separated

if TYPE_CHECKING:
    from lungmech.pgd.model import PGDModel

__all__ = ["Point"]


class Point:
    """One solve's evaluation at μ: q(μ), the terms' products, so that the state at time t is
    z = s R (q ∘ τ(t)) (s the load factor, τ the owner's timeline); the strain energy's A(c) for
    the values ``c`` of its entries (a linear model) or the owner's fit of it; the scalar
    ``loads`` at the path's end T, at t r(t)/r(T) of them; the shape coefficients ``a`` (none:
    no shape map); with ``derivatives`` (the model's value derivatives, its parameters set at
    μ), ∂q/∂μ, ∂A/∂μ and da/dμ; its ``indicator`` η(μ) from the values ``indicated`` at the
    loads' own scale (None: the build's estimate answers for it)."""

    def __init__(
        self,
        owner: PGDModel,
        values: Mapping[str, float],
        c: np.ndarray,
        loads: dict[str, float],
        a: np.ndarray,
        derivatives: ValueDerivatives | None,
        indicated: np.ndarray | None = None,
    ) -> None:
        model, d, self.online = owner.model, owner.decomposition, owner.online
        units = d.units(values)
        self.reduced, self.q = d.reduced, d.products(values, units)
        self.timeline, self.energy, self.values = owner.timeline, owner.energy, values
        self.fractions = owner.fractions
        # ξ at the probes on an imaged body, and its slopes: u = w − ξ
        reference = owner.reference if owner.reference is not None and len(owner.probe_points) else None
        self.xi = None if reference is None else reference.at_probes(values)
        self.xi_slopes = None if reference is None or derivatives is None else reference.probe_derivatives(values)
        weights = self.online.weights(units) if self.energy is None else np.ones(1)
        # A linear model's state at t and s is s ρ(t) z_T, z_T its state at the path's end (τ = 1
        # there): its strain energy (s ρ(t))² ½ z_Tᵀ A z_T, and its η at μ that of z_T with the
        # values at the loads' own scale (its residual a multiple of z_T's)
        end = self.reduced @ self.q
        self.energy_at_end, self.volume_powers = 0.0, None
        if self.energy is None:  # (its volume at t, at s ρ(t) z_T, a cubic in s ρ(t) without a shape map)
            quadratic, self.volume_powers = self.online.energy_and_volume(c, weights, end)
            self.energy_at_end = 0.5 * quadratic
        self.indicator = (
            None if self.energy is not None or indicated is None else self.online.indicator(indicated, weights, end)
        )
        self.loads, self.a = loads, a
        self.points = len(owner.probe_points)
        self.derivatives_at_end = derivatives
        if derivatives is not None:
            self.operator = self.online.operator(c, weights) if self.energy is None else None
            self.slopes = d.product_derivatives(values)
            n = self.slopes.shape[1]
            coefficients = () if model.shape is None else model.shape.coefficients
            self.da = np.array([derivatives.constants.get(c, np.zeros(n)) for c in coefficients]).reshape(-1, n)
            dc = np.concatenate([np.reshape(derivatives.constants[k], (-1, n)) for k in separated.constants(model)])
            energy = self.online.energy
            self.operator_slopes = np.einsum("k,ei,kemn->imn", weights, dc[self.online.entries], energy[:, 1:])
            for j in self.online.curves:  # the series' own slope, ∂(Π T_{kᵢ})/∂σⱼ dσⱼ/dμⱼ
                parameter = d.axes[j].parameter
                dw = self.online.weights(units, j) / parameter.unit_derivative(values[parameter.name])
                self.operator_slopes[j] += self.online.operator(c, dw)

    def state(self, t: float, factor: float = 1.0) -> np.ndarray:
        """z = s R (q ∘ τ(t))."""
        return factor * (self.reduced @ (self.q * self.timeline.at(t)))

    def _strain_energy(self, t: float, factor: float) -> float:
        if self.energy is None:  # (a linear model's timeline: its loads' one ramp, ρ(t) = τ(t))
            return (factor * float(self.timeline.at(t))) ** 2 * self.energy_at_end
        fitted, timeline = self.energy
        return float(fitted.factors(self.values, timeline.at(t))[0])

    def outputs(self, t: float, z: np.ndarray, factor: float = 1.0) -> dict[str, object]:
        """The outputs at time ``t``, the state there z (:meth:`state`), the load ``factor``."""
        if self.volume_powers is None:
            volume = self.online.volume_at(z, self.a)
        else:
            c0, c1, c2, c3 = self.volume_powers
            x = factor * float(self.timeline.at(t))
            volume = float(c0 + x * (c1 + x * (c2 + x * c3)))
        found: dict[str, object] = {"volume": volume, "strain_energy": self._strain_energy(t, factor)}
        if self.points:
            moved = self.online.probes @ z
            found["probes"] = (moved if self.xi is None else moved - self.xi).reshape(self.points, -1)
        found["loads"] = {label: f * value for (label, value), f in zip(self.loads.items(), self.fractions(t))}
        return found

    def derivatives(self, t: float, factor: float) -> dict[str, object]:
        """d(outputs)/dμ at time ``t``: dz/dμ = s R (∂q/∂μ ∘ τ(t)); the strain energy's, of a
        linear model, zᵀ A dz/dμ + ½ zᵀ (∂A/∂μ) z, else its fit's."""
        assert self.derivatives_at_end is not None  # (made with derivatives)
        tau = self.timeline.at(t)
        z, dz = self.state(t, factor), factor * (self.reduced @ (self.slopes * np.reshape(tau, (-1, 1))))
        if self.energy is None:
            assert self.operator is not None  # (a linear model's)
            energy = z @ self.operator @ dz + 0.5 * np.einsum("m,imn,n->i", z, self.operator_slopes, z)
        else:
            fitted, timeline = self.energy
            energy = fitted.factor_derivatives(self.values, timeline.at(t))[0]
        volume = self.online.volume_derivatives(z, self.a, dz, self.da)
        found: dict[str, object] = {"volume": volume, "strain_energy": energy}
        if self.points:
            moved = self.online.probes @ dz
            found["probes"] = (moved if self.xi_slopes is None else moved - self.xi_slopes).reshape(
                self.points, -1, dz.shape[1]
            )
        loads = self.derivatives_at_end.loads.items()
        found["loads"] = {label: f * d for (label, d), f in zip(loads, self.fractions(t))}
        return found
