"""How far a model's answers to the images' data are from those of the models it stands for.

A reduced model answers for the full one on its mesh, and that for the lung itself, to within
the mesh's own error. At a few parameter points (beside the training), each model of such a
chain — the reduced model, the full one, the full one on the same lung refined once — is
asked for the residual of the same data (:func:`lungmech.twin.fit.predict`: each surface
node's distance, the volume's change, any interior motion), and the model's error as the data
see it is the difference δr = r_last − r_first, signed, row by row: the sign pattern is what
carries it into the estimate (:func:`lungmech.twin.uncertainty.laplace` takes it as a bias).
Each step's largest difference on the surface and its volume offset are kept for the report.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from lungmech.twin.fit import View, predict

__all__ = ["model_error"]


def model_error(chain: Sequence[View], points: Sequence[Mapping[str, float]]) -> tuple[np.ndarray, list[dict]]:
    """The first view's model error against the last one's at each of ``points`` (parameter
    values, every view's fixed ones given): δr = r_last − r_first (points × rows, m), and each
    point's numbers per step (the reduction's, then the mesh's: the largest surface difference
    and the volume's offset, m)."""
    rows = len(chain[0].nodes.points)
    errors, checked = [], []
    for point in points:
        residuals = [predict(view, point, sensitivities=False).residual for view in chain]
        steps = [
            {
                "surface_error_max": float(np.abs(after[:rows] - before[:rows]).max()),
                "volume_offset": float(abs(after[rows] - before[rows])),
            }
            for before, after in zip(residuals[:-1], residuals[1:])
        ]
        errors.append(residuals[-1] - residuals[0])
        checked.append({"parameters": dict(point), "steps": steps})
    return np.array(errors), checked
