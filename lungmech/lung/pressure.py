"""The pressure of a pressure–volume curve: which scalar loads make it, and how.

For a lung (the lung model, an alveolar pressure, or a follower pressure on the pleura) it is
the transpulmonary pressure P_L = p_alv − p_pl, p_pl the follower pressure on the pleura (or the
first follower pressure) and p_alv the alveolar pressure (0: atmospheric); for another body, the
first pressure load. It is a linear combination of the loads' values *as applied* (the model's
``scalar_loads()``), so a load amplitude set as a parameter is in it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from lungmech.fem.loads import FollowerPressure, Load, is_pressure
from lungmech.lung.poromechanics import AlveolarPressure, Poromechanics

if TYPE_CHECKING:
    from lungmech.fem.formulations import Formulation

__all__ = ["PressureAxis", "pressure_axis"]


@dataclass(frozen=True)
class PressureAxis:
    """P = Σ weights[label] · p_label (Pa); ``label`` names it, ``parts`` say what it is made
    of, ``lung`` whether it is a lung's transpulmonary pressure."""

    label: str
    weights: dict[str, float]
    parts: tuple[str, ...] = ()
    lung: bool = False

    def __call__(self, loads: Mapping[str, float]) -> float:
        """The pressure (Pa) for the loads' values (Pa) by label."""
        return float(sum(weight * loads[label] for label, weight in self.weights.items()))


def pressure_axis(loads: Sequence[Load], formulation: Formulation) -> PressureAxis | None:
    """The P–V curve's pressure of a body with these ``loads`` and ``formulation`` (see the
    module's doc), or None without pressure loads."""
    scalars = [load for load in loads if is_pressure(load)]
    if not scalars:
        return None
    alveolar = [load.label for load in scalars if isinstance(load, AlveolarPressure)]
    followers = [load for load in scalars if isinstance(load, FollowerPressure)]
    on_pleura = [
        load
        for load in followers
        if "pleura" in ((load.boundary,) if isinstance(load.boundary, str) else load.boundary)
    ]
    pleural = [load.label for load in (on_pleura or followers)[:1]]
    if alveolar or on_pleura or isinstance(formulation, Poromechanics):
        weights = {label: 1.0 for label in alveolar} | {label: -1.0 for label in pleural}
        parts = (f"p_pl: {' + '.join(pleural) or 'none (0)'}", f"p_alv: {' + '.join(alveolar) or 'atmospheric (0)'}")
        return PressureAxis("transpulmonary pressure p_alv − p_pl", weights, parts, lung=True)
    first = scalars[0].label
    return PressureAxis(first, {first: 1.0})
