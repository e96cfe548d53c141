"""A scene's PGD model, built a priori (no full solve) and written as a model file.

:func:`build` makes the scene's model, its PGD over the scene's [parameters] box along its load
path (:func:`lungmech.pgd.model.build`) and writes it with the scene and every file it reads
(:mod:`lungmech.app.model_file`), like ``rom build``'s files, so that ``lungmech rom solve
pgd.npz --set name=value`` and ``--sweep`` answer from it through the same ``solve(μ)``
(:func:`lungmech.app.reduce.reduced_order` loads either kind).
"""

from __future__ import annotations

import time
from pathlib import Path

from mpi4py import MPI

from lungmech import checks
from lungmech.app.model_file import file_bytes, scene_record
from lungmech.app.run import build_model
from lungmech.app.scene import Scene
from lungmech.errors import ParameterError
from lungmech.parallel.destination import hold_signals_until_swap, output_file
from lungmech.parallel.layout import layout
from lungmech.pgd.greedy import Options
from lungmech.pgd.model import build as pgd_build
from lungmech.pgd.store import write_pgd
from lungmech.rom import store

__all__ = ["build"]


def build(
    scene: Scene,
    path: str | Path,
    modes: int = 20,
    intervals: int = 32,
    tolerance: float = 1e-6,
    comm: MPI.Comm = MPI.COMM_WORLD,
) -> dict:
    """Build the PGD model of ``scene`` and save it to ``path`` (.npz); returns its summary.

    At most ``modes`` separated terms u ≈ Σₖ ūₖ(x) Πⱼ λₖʲ(μⱼ), the greedy stopping when a new
    term's amplitude falls below ``tolerance`` of the whole's; each parameter's modes are cubic
    splines on ``intervals`` intervals. Refused in one line before any work for a scene the PGD
    does not yet separate (an imaged body's [inverse], a nonlinear law, …) and where ``path`` is
    not the user's to replace (:mod:`lungmech.parallel.destination`). Collective."""
    checks.integer("PGD modes", modes, minimum=1)
    checks.integer("PGD intervals", intervals, minimum=1)
    options = Options(max_terms=modes, tolerance=tolerance)
    if scene.inverse is not None:
        raise ParameterError(
            "PGD: the scene's [inverse] (an imaged body, its reference found at every μ) is not yet separated; "
            "use 'lungmech rom build' for it"
        )
    path = store.suffixed(path)
    with output_file(path, comm, inputs=scene.inputs, ours=store.is_model) as staging:
        tic = time.perf_counter()
        model = build_model(scene, comm)
        built = time.perf_counter() - tic
        found, rounds = pgd_build(model, scene.stepping, scene.output.probes, intervals, options)
        extra = scene_record(scene, layout(model.space).fingerprint, model.parameters.describe()) | {
            "scales": None,
            "offline_seconds": {"build": built, **found.built["seconds"]},
        }
        arrays = {f"file:{name}": data for name, data in file_bytes(scene, comm).items()}
        hold_signals_until_swap()  # the model file is a collective write
        write_pgd(staging, found, extra, arrays)
    last = rounds[-1] if rounds else None
    return {
        "modes": found.size,
        "terms": found.decomposition.terms,
        "dofs": layout(model.space).size,
        "parameters": list(model.parameters.names),
        "intervals": intervals,
        "offline_seconds": extra["offline_seconds"],
        "last_amplitude": None if last is None else last.amplitude,
        "converged": bool(last is not None and not last.added),
        "path": str(Path(path).resolve()),
    }
