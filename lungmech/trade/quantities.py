"""A candidate's errors against the reference, each with its stated denominator.

Answers are those of :func:`lungmech.app.answers.answer` (SI units), point by point, the
candidate's and the reference's at the same μ and output times. Per point:

* ``volume`` — the volume at the last output time (a static answer: the equilibrium there),
  |V − V_ref| / |V_ref − V_ref,start|: relative to the volume change of the path to it;
* ``pv`` — the P–V curve: max over the output times of |V(t) − V_ref(t)|, relative to the
  path's largest volume change max_t |V_ref(t) − V_ref,start|;
* ``probes`` — the largest probe displacement error |u − u_ref| at the last output time,
  relative to the probes' largest motion |u_ref| (and in mm: :func:`probe_millimetres`);
* ``energy`` — the state at the last output time, in the energy norm on the reference's mesh,
  relative to the reference's change of state from its start: fields, not answers' numbers
  (:mod:`lungmech.app.field_errors` measures them).

A failed answer's error is nan (it failed there; it is never dropped), and so is every
answer's where the reference failed (it cannot be judged there). The same denominators
make a level's answers comparable with another's for the observed order (:func:`normalised`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lungmech.errors import ParameterError

__all__ = ["DENOMINATORS", "FIELDS", "QUANTITIES", "errors", "expected_order", "normalised", "probe_millimetres"]

QUANTITIES = ("volume", "pv", "probes", "energy")
DENOMINATORS = {
    "volume": "the volume change to the last output time",
    "pv": "the path's largest volume change",
    "probes": "the probes' largest displacement",
    "energy": "the state's change from the start to the last output time",
}
FIELDS = ("energy",)  # measured on fields (lungmech.app.field_errors), not on answers


def expected_order(quantity: str, degree: int) -> float:
    """The order at which the quantity converges under refinement with elements of ``degree``
    p on one polyhedron: 2p for the volume (a smooth functional of the solution), p + 1 for a
    point's displacement, p for the state in the energy norm."""
    orders = {"volume": 2.0 * degree, "pv": 2.0 * degree, "probes": degree + 1.0, "energy": float(degree)}
    return orders[_known(quantity)]


def normalised(answers: Sequence[dict], references: Sequence[dict], quantity: str) -> np.ndarray:
    """Each answer's quantity over the reference's denominator at its point (nan where either
    failed): rows of a level, for :func:`lungmech.trade.convergence.observed_order`."""
    _of_answers(quantity)
    width = next((len(_values(r, quantity)) for r in references if r["failed"] is None), 1)
    rows = []
    for found, reference in zip(answers, references, strict=True):
        if found["failed"] is not None or reference["failed"] is not None:
            rows.append(np.full(width, np.nan))
            continue
        rows.append(_values(found, quantity) / _denominator(reference, quantity))
    return np.array(rows)


def errors(answers: Sequence[dict], references: Sequence[dict], quantity: str) -> np.ndarray:
    """The relative error of each answer at its point (see the module's doc); nan where it failed."""
    _of_answers(quantity)
    found = []
    for answer, reference in zip(answers, references, strict=True):
        if answer["failed"] is not None or reference["failed"] is not None:
            found.append(np.nan)  # failed there, or not judged there: the reference failed
            continue
        difference = np.abs(_values(answer, quantity) - _values(reference, quantity))
        found.append(float(difference.max() / _denominator(reference, quantity)) if difference.size else 0.0)
    return np.array(found)


def probe_millimetres(answers: Sequence[dict], references: Sequence[dict]) -> np.ndarray:
    """The largest probe displacement error at the last output time per point, in mm (nan: failed)."""
    found = []
    for answer, reference in zip(answers, references, strict=True):
        if answer["failed"] is not None or reference["failed"] is not None or not reference["probes"]:
            found.append(np.nan)
            continue
        difference = np.asarray(answer["probes"][-1]) - np.asarray(reference["probes"][-1])
        found.append(float(np.linalg.norm(difference, axis=-1).max() * 1e3))
    return np.array(found)


def _known(quantity: str) -> str:
    if quantity not in QUANTITIES:
        raise ParameterError(f"quantity must be one of {', '.join(QUANTITIES)} (got {quantity!r})")
    return quantity


def _of_answers(quantity: str) -> str:
    if _known(quantity) in FIELDS:
        raise ParameterError(
            f"the quantity {quantity!r} is measured on fields (lungmech.app.field_errors), not answers"
        )
    return quantity


def _values(answer: dict, quantity: str) -> np.ndarray:
    """The numbers the quantity compares: the last volume, the curve, the last probes."""
    if quantity == "volume":
        return np.array([answer["volume"][-1]])
    if quantity == "pv":
        return np.asarray(answer["volume"], dtype=float)
    if not answer["probes"]:
        raise ParameterError("the quantity 'probes' needs probes: give [output] probes in the scene")
    return np.asarray(answer["probes"][-1], dtype=float).ravel()


def _denominator(reference: dict, quantity: str) -> float:
    """The reference's own scale of the quantity at its point (see the module's doc)."""
    if quantity == "probes":
        motion = float(np.linalg.norm(np.asarray(reference["probes"][-1]), axis=-1).max())
        return motion if motion > 0 else 1.0
    start = reference["start_volume"]
    if start is None:
        raise ParameterError("the reference's answer has no start volume: its volume change is unknown")
    volumes = np.asarray(reference["volume"], dtype=float)
    change = float(np.abs((volumes[-1:] if quantity == "volume" else volumes) - start).max())
    return change if change > 0 else 1.0
