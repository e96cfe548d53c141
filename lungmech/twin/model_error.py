"""How far a model's answers to the images' data may be from the truth: ε per datum.

A reduced model answers for the full one on its mesh, and that for the lung itself, to within
the mesh's own error. At a few parameter points (beside the training), each step of such a
chain — the reduced model against the full one, the full one against the same lung refined
once — is measured on what the data see: each surface (or interior) node's motion from
end-expiration to end-inspiration, and the volume's change as a mean offset of the surface.
The steps' differences are summed (the triangle inequality) and the largest over the points is
ε, which :func:`lungmech.twin.uncertainty.laplace` takes as a bias.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from lungmech.fem.parametric import ParametricModel

__all__ = ["model_error"]


def model_error(
    chain: Sequence[ParametricModel], points: Sequence[Mapping[str, float]], end: float, area: float
) -> tuple[np.ndarray, list[dict]]:
    """ε per datum (m) of the first model of ``chain`` against the truth, bounded by the chain's
    steps (the reduced model against the full one on its mesh, that against the full model on
    a finer mesh: the error of reduction and the mesh's own): over ``points``, the largest sum
    of each step's difference in each surface node's motion to ``end`` and in the volume
    change's mean offset (ΔV / ``area``); and each point's worst numbers per step."""
    start = chain[0].stepping.start
    worst: np.ndarray | None = None
    checked = []
    for point in points:
        answers = [model.solve(point, times=[start, end]) for model in chain]
        motions = [np.asarray(a.outputs["probes"])[1] - np.asarray(a.outputs["probes"])[0] for a in answers]
        changes = [float(a.outputs["volume"][1] - a.outputs["volume"][0]) for a in answers]
        row = np.zeros(len(motions[0]) + 1)
        steps = []
        for k in range(len(chain) - 1):
            node = np.linalg.norm(motions[k] - motions[k + 1], axis=1)
            volume = abs(changes[k] - changes[k + 1]) / area
            row += np.append(node, volume)
            steps.append({"motion_error_max": float(node.max()), "volume_offset": volume})
        worst = row if worst is None else np.maximum(worst, row)
        checked.append({"parameters": dict(point), "steps": steps})
    assert worst is not None  # (three points)
    return worst, checked
