"""What ``lungmech personalise`` reports: ``report.json``'s plain values, each with its unit."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lungmech.twin.fit import Estimate, Fit
from lungmech.twin.uncertainty import Uncertainty

if TYPE_CHECKING:
    from lungmech.app.personalise import Patient

__all__ = ["UNITS", "report"]


def report(
    patient: Patient,
    fit: Fit,
    found: Estimate,
    uncertainty: Uncertainty,
    draws: np.ndarray,
    full_residual: np.ndarray,
    seconds: dict[str, float],
) -> dict:
    """The report's plain values (each with its unit: :data:`UNITS`) of an estimate ``found``
    of ``patient`` on ``fit``: the parameters with their intervals (``uncertainty``) and the
    resampled estimates' spread (``draws``), the correlations and weak combinations, the fit
    per pair beside the full models' (``full_residual``), the checks, the registrations and
    the ``seconds``."""
    parameters = {}
    spread = draws.std(axis=0, ddof=1) if len(draws) > 1 else np.full(len(fit.names), np.nan)
    deviation = np.sqrt(np.diag(uncertainty.covariance))
    for i, name in enumerate(fit.names):
        interval = uncertainty.intervals[name]
        parameters[name] = {
            "value": found.values[name],
            "unit": patient.box.named(name).unit or "1",
            "interval": None if interval.low is None else [interval.low, interval.high],
            "note": interval.reason,
            "at_bound": found.active[name],
            "deviation_unit_box": float(deviation[i]),
            "resampled_deviation_unit_box": float(spread[i]),
            "noise_half_width_unit_box": float(interval.noise),
            "model_bias_unit_box": float(interval.bias),
        }
    views = []
    for view, rows, inside in zip(fit.views, fit.surface_rows(), fit.interior_rows()):
        surface, full = found.residual[rows], full_residual[rows]
        volume = rows[-1] + 1
        views.append(
            {
                "pair": view.name,
                "fixed": dict(view.fixed),
                "surface_rms": float(np.sqrt(np.mean(surface**2))),
                "surface_max": float(np.abs(surface).max()),
                "volume_offset": float(found.residual[volume]),
                "full_order_surface_rms": float(np.sqrt(np.mean(full**2))),
                "full_order_volume_offset": float(full_residual[volume]),
            }
        )
        if view.interior is not None:  # the field's misfit, in m (unweighed), and its weight
            misfit = found.residual[inside] / view.interior.weight
            views[-1]["interior"] = {
                "points": len(view.interior.points),
                "smoothing": view.interior.smoothing,
                "weight": view.interior.weight,
                "rms": float(np.sqrt(np.mean(misfit**2))),
                "full_order_rms": float(np.sqrt(np.mean((full_residual[inside] / view.interior.weight) ** 2))),
            }
    surfaces = np.concatenate([found.residual[rows] for rows in fit.surface_rows()])
    full_surfaces = np.concatenate([full_residual[rows] for rows in fit.surface_rows()])
    return {
        "parameters": parameters,
        "fixed": {view.name: dict(view.fixed) for view in fit.views},
        "level": uncertainty.level,
        "noise_sigma": uncertainty.sigma,
        "correlation": np.asarray(uncertainty.correlation).tolist(),
        "directions": [
            {"combination": d.combination, "deviation_unit_box": d.deviation, "weak": d.weak, "text": d.text()}
            for d in uncertainty.directions
        ],
        "fit": {
            "surface_rms": float(np.sqrt(np.mean(surfaces**2))),
            "surface_max": float(np.abs(surfaces).max()),
            "full_order_surface_rms": float(np.sqrt(np.mean(full_surfaces**2))),
            "pairs": views,
            "evaluations": found.evaluations,
            "message": found.message,
            "history": found.history,
        },
        "model_check": list(patient.checked),
        "registration": list(patient.registered),
        "seconds": seconds,
        "units": UNITS,
    }


UNITS = {
    "value": "the parameter's unit",
    "interval": "the parameter's unit",
    "deviation_unit_box": "1 (fraction of the parameter's range, log range on a log scale)",
    "noise_sigma": "m",
    "surface_rms": "m",
    "surface_max": "m",
    "volume_offset": "m (volume mismatch over the surface area)",
    "surface_error_max": "m (the largest change of a surface datum over a check's step)",
    "model_bias_unit_box": "1 (fraction of the parameter's range: the model error's shift, each side)",
    "noise_half_width_unit_box": "1 (fraction of the parameter's range: the interval's half-width from noise)",
    "cost": "m^2",
    "seconds": "s",
    "interior.rms": "m (the displacement field's misfit per component)",
    "interior.weight": "1 (the surface's noise over the field's)",
    "smoothing": "m",
    "registration[].shape_coefficients": "1 (standard deviations of the population's library: the fit to the surface)",
    "registration[].shape_projected": "1 (standard deviations: the registration's mapping projected on the modes)",
    "registration[].shape_surface_rms": "m (the segmentation's surface from the template's at the patient's shape, RMS)",
    "registration[].shape_surface_largest": "m (the same at the worst node)",
    "registration[].shape_left_out_rms": "m (what the population's modes leave out of the patient's shape, RMS)",
    "registration[].shape_left_out_largest": "m (the same at the worst node)",
}
