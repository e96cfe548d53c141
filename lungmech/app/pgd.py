"""A scene's PGD model, built a priori (no full solve) or fitted to full solves, and written as a
model file.

:func:`build` makes the scene's model, its PGD over the scene's [parameters] box along its load
path — a priori (:func:`lungmech.pgd.model.build` for a linear model;
:func:`lungmech.pgd.newton.build_nonlinear`, Newton on the parameters' Gauss grid, for a
nonlinear one; :func:`lungmech.pgd.imaged_newton.build_imaged` for an imaged body, its
reference ξ(μ) and its breath each by Newton), or with ``samples``
fitted to that many full solves (:func:`lungmech.pgd.fitted.fitted`: any model; the solves run
on an ensemble and are kept in lungmech's cache, as ``rom build``'s training) — and writes it with the scene and every file it reads
(:mod:`lungmech.app.model_file`), like ``rom build``'s files, so that ``lungmech rom solve
pgd.npz --set name=value`` and ``--sweep`` answer from it through the same ``solve(μ)``
(:func:`lungmech.app.reduce.reduced_order` loads either kind).
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

from mpi4py import MPI

from lungmech import checks
from lungmech.app.model_file import file_bytes, scene_record
from lungmech.app.reduce import training_solves
from lungmech.app.run import build_model
from lungmech.app.scene import Scene
from lungmech.app.training_paths import EnsemblePaths, forget, training_model
from lungmech.errors import ParameterError
from lungmech.parallel.destination import hold_signals_until_swap, output_file
from lungmech.parallel.ensemble import Ensemble
from lungmech.parallel.layout import layout
from lungmech.pgd.fitted import fitted
from lungmech.pgd.fitting import FIT
from lungmech.pgd.greedy import Options
from lungmech.pgd.imaged_newton import build_imaged
from lungmech.pgd.model import build as pgd_build
from lungmech.pgd.newton import INTERVALS as NEWTON_INTERVALS
from lungmech.pgd.newton import QUADRATURE, Newton, build_nonlinear
from lungmech.pgd.store import write_pgd
from lungmech.pgd.terms import affine_in_state
from lungmech.rom import store

__all__ = ["INTERVALS", "build"]

INTERVALS = 32  # a priori, a linear model: the splines' own error is the PGD's (2e-6 on the beam of the docs)


def build(
    scene: Scene,
    path: str | Path,
    modes: int = 20,
    intervals: int | None = None,
    tolerance: float = 1e-6,
    comm: MPI.Comm = MPI.COMM_WORLD,
    samples: int | None = None,
    seed: int = 0,
    ensemble: Ensemble | None = None,
    cache: str | Path | None = None,
    quadrature: int = QUADRATURE,
) -> dict:
    """Build the PGD model of ``scene`` and save it to ``path`` (.npz); returns its summary.

    At most ``modes`` separated terms u ≈ Σₖ ūₖ(x) Πⱼ λₖʲ(μⱼ), the greedy stopping when a new
    term's amplitude falls below ``tolerance`` of the whole's; each parameter's modes are cubic
    splines on ``intervals`` intervals (default :data:`INTERVALS`; a nonlinear model's
    :data:`lungmech.pgd.newton.INTERVALS`, its residual assembled at the axes' Gauss grid, or
    at ``quadrature`` Sobol' points where the grid has more; fitted, chosen on held-out
    samples, :data:`lungmech.pgd.fitted.INTERVALS`). With ``samples``, the terms are fitted to the full
    model's solves at that many Sobol' points (``seed``) of the box, run on ``ensemble`` and kept
    in ``cache`` (:func:`lungmech.app.reduce.training_solves`), their number chosen on held-out
    samples up to ``modes`` (an imaged body's [inverse] too: its reference fitted beside the
    breath; a priori, both by Newton: :mod:`lungmech.pgd.imaged_newton`). Refused in one line
    before any work where ``path`` is not the user's to replace
    (:mod:`lungmech.parallel.destination`). Collective."""
    checks.integer("PGD modes", modes, minimum=1)
    if intervals is not None:
        checks.integer("PGD intervals", intervals, minimum=1)
    if samples is not None:
        checks.integer("PGD samples", samples, minimum=8)
        checks.integer("PGD seed", seed, minimum=0)
    elif ensemble is not None or cache is not None:
        raise ParameterError("PGD: an ensemble or a cache runs full solves: give --samples for a PGD fitted to them")
    options = Options(max_terms=modes, tolerance=tolerance)
    newton = Newton(quadrature=quadrature, seed=seed)  # (checked before any work; a linear model's greedy needs none)
    solves = training_solves(scene, ensemble, cache, comm) if samples is not None else None
    path = store.suffixed(path)
    with output_file(path, comm, inputs=scene.inputs, ours=store.is_model) as staging:
        tic = time.perf_counter()
        if samples is None and scene.inverse is not None:  # its reference and its breath, each by Newton
            full, _ = training_model(scene, comm)
            model, built = full.model, time.perf_counter() - tic
            how = intervals or NEWTON_INTERVALS
            found, rounds = build_imaged(full, scene.output.probes, how, options, newton)
        elif samples is None:
            model = build_model(scene, comm)
            built = time.perf_counter() - tic
            if affine_in_state(model):
                found, rounds = pgd_build(model, scene.stepping, scene.output.probes, intervals or INTERVALS, options)
            else:
                how = intervals or NEWTON_INTERVALS
                found, rounds = build_nonlinear(model, scene.stepping, scene.output.probes, how, options, newton)
        else:
            full, where = training_model(scene, comm)
            model, built, rounds = full.model, time.perf_counter() - tic, []
            paths = None if solves is None else EnsemblePaths(scene, full, where, *solves)
            fit_options = replace(FIT, max_terms=modes, tolerance=tolerance)
            try:
                found, _ = fitted(full, samples, intervals, fit_options, scene.output.probes, seed, paths)
            finally:
                forget()
        extra = scene_record(scene, layout(model.space).fingerprint, model.parameters.describe()) | {
            "scales": None,
            "offline_seconds": {"build": built, **found.built["seconds"]},
        }
        arrays = {f"file:{name}": data for name, data in file_bytes(scene, comm).items()}
        hold_signals_until_swap()  # the model file is a collective write
        write_pgd(staging, found, extra, arrays)
    last = rounds[-1] if rounds else None
    held_out = found.built.get("held_out")
    return {
        "modes": found.size,
        "terms": found.decomposition.terms,
        "dofs": layout(model.space).size,
        "parameters": list(model.parameters.names),
        "intervals": [axis.intervals for axis in found.decomposition.axes],
        "offline_seconds": extra["offline_seconds"],
        "last_amplitude": None if last is None else last.amplitude,
        "converged": bool(last is not None and not last.added),
        "samples": samples,
        "held_out": None if held_out is None else min(held_out),
        "newton_iterations": found.built.get("newton_iterations"),  # a nonlinear model's, a priori
        "quadrature": found.built.get("quadrature"),
        "estimate": found.built.get("estimate"),
        "path": str(Path(path).resolve()),
    }
