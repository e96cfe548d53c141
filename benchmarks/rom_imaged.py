"""The real-time lung at every μ: the imaged problem's hyper-reduced model against its full model.

    python benchmarks/rom_imaged.py                        # the bundled mesh and h = 8 mm (about 2 h)
    python benchmarks/rom_imaged.py --sizes default        # the bundled mesh alone (about 15 min)
    python benchmarks/rom_imaged.py --quick                # h = 40 mm, 3 training points, 1 unseen, no corners

The bundled breathing lung over the three parameters of ``benchmarks/rom_parameters.py``
(stiffness c1 100–400 Pa, log; breath depth 0.6–1.4; posture −90°–0°) as a twin poses it: the
mesh is the image at end-expiration for every μ, each answer finds the unloaded reference at its
μ and breathes from the image (:mod:`lungmech.rom.imaged`; the definition of
``benchmarks/rom_real_time.py`` moved one reference, the defaults', to μ instead). For each mesh
size h:

* offline: the full model on the image (:class:`lungmech.fem.inverse_motion.InverseMotion`) at
  ``--train`` Sobol' points (seed 0): the POD bases of the inverse map ξ and of the breath
  (``--size`` vectors at most, energy norm), then one more pass of the same solves for the ECSW
  training of both residuals, and an NNLS per τ of ``--taus``;
* the full model at ``--unseen`` Sobol' points of another seed and the box's 8 corners, each its
  own solve (kept between runs: ``benchmarks/resumable.py``);
* for every τ and basis size k (``--size`` and its half): the hyper-reduced model at the same
  points: warm time per breath of 20 outputs and per static point (``solve(μ, times=[t₀])``: the
  reference at μ and the outputs of the image), medians, of the model as `lungmech rom solve`
  loads it (on its body of sampled cells, no full mesh); and the worst errors against the full
  model: the reference volume relative to the image's volume and to the inflation
  |V_image − V_ref| the inverse problem undoes, the start volume against the image's, the
  breath's volume relative to its volume change, the state in the energy norm relative to the
  breath's largest change, the probes; its own error indicator against the true energy-norm
  error; the sampled cells of each problem;
* at the first ``--run-points`` points, `lungmech run --set`'s full model (its mesh moved to
  the reference by a fixed point, :class:`lungmech.lung.inverse.Imaged`): against the full model
  on the image (two full models of the one problem), and the answers of `rom solve --set` (the
  model on its body) against it.

Writes results/rom_imaged.{md,csv} (--quick: rom_imaged_quick.*) and rom_imaged.png. One rank.
Rows of mesh sizes not measured by this run are kept from the CSV with their command and date.
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

from mpi4py import MPI

import machine
import numpy as np
from machine import by_size, provenance, read_results, say
from resumable import cached, code_version
from rom_parameters import lung_scene
from rom_real_time import _digest, static_seconds, timed

import lungmech  # noqa: F401  (before dolfinx: it loads the MPI library dolfinx's bindings need)
from lungmech.app.run import build_model, full_order_model
from lungmech.fem.parameters import Parameters
from lungmech.fem.parametric import Solution
from lungmech.fem.placement import Image
from lungmech.rom import store
from lungmech.rom.hyper_reduced import HyperReducedSolver
from lungmech.rom.reduced import ReducedModel
from lungmech.rom.reductor import ECSW, POD, Reductor, TrainingSet, errors

RESULTS = machine.RESULTS
VERSIONS = {"all": code_version(), "full": code_version(["rom"])}  # what the kept answers depend on
TIMES = [round(0.1 * i, 1) for i in range(1, 20)]  # with the end: 20 outputs
SIZES = "default,8"
# the targets: start volume 1e-4 of the image's, breath volume 1e-3 of its change, energy 1e-2;
# the reference volume 1e-4 of the image's too (of the inflation it undoes: stricter, reported beside)
TARGETS = {
    "reference_volume_max": 1e-4,
    "start_volume_max": 1e-4,
    "volume_change_max": 1e-3,
    "energy_max": 1e-2,
}


CORNERS = " and the box's 8 corners"  # in the table's preamble, where the run solved them


def corners(box: Parameters) -> list[dict[str, float]]:
    """The 2ᵈ corners of the parameter box."""
    return [box.from_unit(np.array(c, dtype=float)) for c in itertools.product((0.0, 1.0), repeat=len(box))]


def inflation(solution: Solution) -> float:
    """|V_image − V_ref| of a solution (m³): the volume the inverse problem undoes."""
    details = solution.start.details
    return abs(details["imaged_volume"] - details["reference_volume"])


def judged(reduced: ReducedModel, references: list[Solution], answers: list[Solution], statics: list) -> dict:
    """The worst errors of the reduced ``answers`` (and ``statics``, the static answers at the
    same points) against the full ``references``, and the indicator against the true error."""
    measured = [errors(reduced, f, a) for f, a in zip(references, answers)]
    image = reduced.start_volume
    missed = [
        abs(a.start.details["reference_volume"] - f.start.details["reference_volume"])
        for f, a in zip(references, answers)
    ]
    reference = [m / inflation(f) for m, f in zip(missed, references)]
    probes = [
        float(np.abs(a.outputs["probes"] - f.outputs["probes"]).max() / np.abs(f.outputs["probes"]).max())
        for f, a in zip(references, answers)
    ]
    ratios = [a.indicator / m.energy for a, m in zip(answers, measured) if a.indicator is not None and m.energy > 0]
    return {
        "reference_volume_max": max(missed) / image,
        "reference_inflation_max": max(reference),
        "reference_inflation_mean": float(np.mean(reference)),
        "start_volume_max": max(abs(s.outputs["volume"][0] - image) / image for s in statics),
        "volume_change_max": max(m.volume_change for m in measured),
        "energy_max": max(m.energy for m in measured),
        "energy_mean": float(np.mean([m.energy for m in measured])),
        "probes_max": max(probes),
        "indicator_over_error_min": min(ratios, default=None),
        "indicator_over_error_max": max(ratios, default=None),
    }


def by_run(scene, points: list[dict], name: str) -> list[Solution]:
    """`lungmech run --set`'s answers at ``points``: the full model that moves its mesh to the
    reference by a fixed point (kept between runs)."""
    fixed_point = full_order_model(scene) if points else None
    return [cached(f"{name}-run-{_digest(mu)}", VERSIONS["full"], partial(fixed_point.solve, mu)) for mu in points]


def volumes_against(answers: list[Solution], references: list[Solution], of: Callable) -> tuple[float, float]:
    """The worst reference-volume error of ``answers`` against ``references``, relative to
    ``of(reference)`` (the image's volume, or the inflation), and the worst breath-volume error
    relative to the breath's volume change."""
    reference, volume = [], []
    for a, f in zip(answers, references):
        reference.append(abs(a.start.details["reference_volume"] - f.start.details["reference_volume"]) / of(f))
        change = np.abs(f.outputs["volume"] - f.start.details["imaged_volume"]).max()
        volume.append(float(np.abs(a.outputs["volume"] - f.outputs["volume"]).max() / change))
    return max(reference), max(volume)


def image_volume(solution: Solution) -> float:
    """The image's volume (m³)."""
    return solution.start.details["imaged_volume"]


def on_body(reduced: ReducedModel, scene) -> ReducedModel:
    """``reduced`` as `lungmech rom solve` loads it: written to a model file and loaded on its
    body of sampled cells alone, no full mesh (what the online times are of)."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "model.npz"
        store.write_reduced(path, reduced)
        build = partial(build_model, scene, MPI.COMM_WORLD, image=Image.motion(scene.stepping.start))
        return store.load_body(path, build, scene.stepping, scene.newton)


def case(size: str, args) -> list[dict]:
    scene = lung_scene(size, TIMES)
    box = Parameters(scene.parameters)
    say(f"h = {size}: building the full model on the image")
    full = full_order_model(scene, start="inverse_motion")
    model, mesh = full.model, full.model.geometry.mesh
    dofs = model.space.dofmap.index_map.size_global * model.space.dofmap.index_map_bs
    cells = mesh.topology.index_map(mesh.topology.dim).size_global
    name = f"rom_imaged-{size}-{_digest(scene)}"
    unseen = [*box.sample(args.unseen, seed=12345), *(corners(box) if args.corners else [])]
    references = []
    for j, mu in enumerate(unseen):
        references.append(cached(f"{name}-full-{_digest(mu)}", VERSIONS["full"], partial(full.solve, mu)))
        say(f"  full model at unseen point {j}: {references[-1].seconds:.1f} s")
    full_median = statistics.median(r.seconds for r in references)
    base = {"mesh h [mm]": size, "dofs": dofs, "cells": cells, "full_s_median": full_median, "points": len(unseen)}
    base |= {"command": command_line(args), "date": time.strftime("%Y-%m-%d"), "code": VERSIONS["all"]}
    run = by_run(scene, unseen[: args.run_points], name)
    if run:  # `run --set` against the full model on the image: two full models of one problem
        against = volumes_against(run, references, inflation)
        base |= {"run_points": len(run), "run_reference_volume_max": against[0], "run_volume_change_max": against[1]}
    rows = []
    tic = time.perf_counter()
    with Reductor(full, POD(args.size), TrainingSet(box.sample(args.train, seed=0))) as reductor:
        k = reductor.basis.size
        say(
            f"  bases: breath {k}, inverse motion {reductor.inverse_basis.size} vectors ({time.perf_counter() - tic:.0f} s)"
        )
        for tau in args.taus:
            for size_k in sorted({k} if args.quick else {k, max(1, k // 2)}, reverse=True):
                reduced = reductor.reduce(ECSW(tau, size=size_k))
                answers = [reduced.solve(mu) for mu in unseen]
                statics = [reduced.solve(mu, times=[reduced.stepping.start]) for mu in unseen]
                shipped = on_body(reduced, scene)
                solved, seconds = timed(shipped, unseen)  # `rom solve --set`'s answers
                versus = volumes_against(solved, run, image_volume) if run else (None, None)
                assert reduced.image is not None and isinstance(reduced.image.solver, HyperReducedSolver)
                inverse = reduced.image.solver.sample
                rows.append(
                    base
                    | {"model": "ECSW", "k": size_k, "tau": tau, "inverse_k": reductor.inverse_basis.size}
                    | {"online_ms_median": 1e3 * statistics.median(seconds)}
                    | {"static_ms_median": 1e3 * statistics.median(static_seconds(shipped, unseen))}
                    | {"speed_up": full_median / statistics.median(seconds)}
                    | {"inverse_newton_median": statistics.median(a.start.newton_iterations for a in answers)}
                    | {"sampled_cells": reduced.sample.cells_per_type(mesh.comm)["cell"]}
                    | {"inverse_sampled_cells": inverse.cells_per_type(mesh.comm)["cell"]}
                    | judged(reduced, references, answers, statics)
                    | {"rom_solve_reference_volume_max": versus[0], "rom_solve_volume_change_max": versus[1]}
                )
                r = rows[-1]
                say(
                    f"  ECSW τ = {tau:g}, k = {size_k}: breath {r['online_ms_median']:.0f} ms, static "
                    f"{r['static_ms_median']:.1f} ms; reference {r['reference_volume_max']:.1e}, "
                    f"volume {r['volume_change_max']:.1e}, energy {r['energy_max']:.1e}"
                )
        offline = {f"offline_{part}_s": seconds for part, seconds in reductor.timings.items()}
    offline["offline_s"] = time.perf_counter() - tic
    return [row | offline for row in rows]


def markdown(rows: list[dict], command: str, args, date: str | None = None) -> str:
    date = date or time.strftime("%Y-%m-%d")
    lines = [
        "# The real-time lung at every μ: its reference found on the image at each point",
        "",
        f"{provenance(command)} POD bases of the inverse map and of the breath from {args.train} training points "
        f"(Sobol', seed 0); {args.unseen} unseen points (Sobol', another seed){CORNERS if args.corners else ''}. The full "
        "model solves the image's equilibrium at each μ, then the breath from the image; a reduced answer the "
        "same, reduced. Times are warm medians over the points; a breath has 20 outputs, a static point is the "
        "reference at μ and the image's outputs, both of the model as `lungmech rom solve` loads it (on its body "
        "of sampled cells). Errors are the worst over the points: the reference volume relative to the image's "
        "volume and to the inflation |V_image − V_ref| the inverse problem undoes, the start volume to the "
        "image's, the breath's volume to its volume change, the state in the energy norm to the breath's "
        "largest change, the probes' displacement to its largest.",
        "",
        *[
            f"Rows of h = {', '.join(dict.fromkeys(str(r['mesh h [mm]']) for r in rows if (r['command'], r['date']) == (c, d)))} "
            f"(kept from an earlier run): `{c}`, {d}."
            for c, d in dict.fromkeys((r["command"], r["date"]) for r in rows)
            if (c, d) != (command, date)
        ],
        "",
        "| h [mm] | dofs | τ | k (ξ) | sampled cells: breath, ξ | breath [ms] | static point [ms] | full [s] | "
        "speed-up | reference volume: of the image, of the inflation | start volume | volume / change | "
        "energy norm: max, mean | probes | indicator / error |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ratio = (
            f"{r['indicator_over_error_min']:.2f}–{r['indicator_over_error_max']:.2f}"
            if r.get("indicator_over_error_min") is not None
            else "—"
        )
        lines.append(
            f"| {r['mesh h [mm]']} | {r['dofs']} | {r['tau']:g} | {r['k']} ({r['inverse_k']}) | "
            f"{r['sampled_cells']}, {r['inverse_sampled_cells']} | {r['online_ms_median']:.0f} | "
            f"{r['static_ms_median']:.1f} | {r['full_s_median']:.1f} | {r['speed_up']:.0f}× | "
            f"{r['reference_volume_max']:.1e}, {r['reference_inflation_max']:.1e} | {r['start_volume_max']:.1e} | "
            f"{r['volume_change_max']:.1e} | "
            f"{r['energy_max']:.1e}, {r['energy_mean']:.1e} | {r['probes_max']:.1e} | {ratio} |"
        )
    lines += ["", *targets(rows), "", *offline(rows)]
    return "\n".join(lines) + "\n"


def targets(rows: list[dict]) -> list[str]:
    """Per mesh size, the fastest model meeting every accuracy target, its static point against
    10 ms, and the static point's growth from the smallest mesh to the largest."""

    def verdict(value: float, limit: float) -> str:
        return f"met ({value / limit:.2g} of it)" if value <= limit else f"**missed**: {value / limit:.2g}× over"

    lines = [
        "## Targets",
        "",
        "Per mesh size, the fastest hyper-reduced model within every accuracy target (reference and start "
        "volume ≤ 1e-4 of the image's, breath volume ≤ 1e-3 of its change, energy norm ≤ 1e-2):",
        "",
        "| h [mm] | dofs | τ, k | static point ≤ 10 ms | breath | `rom solve --set` against `run --set` "
        "(reference ≤ 1e-4 of the image, volume ≤ 1e-3 of the change) | `run --set` against the image's full model |",
        "|---|---|---|---|---|---|---|",
    ]
    sizes = sorted({(r["dofs"], str(r["mesh h [mm]"])) for r in rows})
    best = {}
    for dofs, size in sizes:
        mine = [r for r in rows if str(r["mesh h [mm]"]) == size]
        run = (
            f"reference {mine[0]['run_reference_volume_max']:.1e} (of the inflation), volume "
            f"{mine[0]['run_volume_change_max']:.1e} at {mine[0]['run_points']} points"
            if mine[0].get("run_points")
            else "—"
        )
        accurate = [r for r in mine if all(r[key] <= limit for key, limit in TARGETS.items())]
        if not accurate:
            lines.append(f"| {size} | {dofs} | none as accurate | — | — | — | {run} |")
            continue
        best[size] = fastest = min(accurate, key=lambda r: r["static_ms_median"])
        lines.append(
            f"| {size} | {dofs} | {fastest['tau']:g}, {fastest['k']} | {fastest['static_ms_median']:.1f} ms: "
            f"{verdict(fastest['static_ms_median'], 10.0)} | {fastest['online_ms_median']:.0f} ms | "
            f"{agreement(fastest)} | {run} |"
        )
    if len(sizes) > 1:
        (small, smallest), (large, largest) = sizes[0], sizes[-1]
        lines += ["", f"Static point from {small} to {large} dofs ({large / small:.1f}×), per τ and k:", ""]
        for tau, k in sorted({(r["tau"], r["k"]) for r in rows}):
            ends = [
                next((r for r in rows if str(r["mesh h [mm]"]) == s and (r["tau"], r["k"]) == (tau, k)), None)
                for s in (smallest, largest)
            ]
            if ends[0] is not None and ends[1] is not None:
                a, b = ends[0]["static_ms_median"], ends[1]["static_ms_median"]
                lines.append(f"- τ = {tau:g}, k = {k}: {a:.1f} → {b:.1f} ms, {b / a:.2f}×")
    return lines


def agreement(row: dict) -> str:
    """`rom solve --set` against `run --set` in a row, with its verdict (— where not measured)."""
    reference, volume = row.get("rom_solve_reference_volume_max"), row.get("rom_solve_volume_change_max")
    if reference is None or volume is None:
        return "—"
    met = "met" if reference <= 1e-4 and volume <= 1e-3 else "**missed**"
    return f"{met}: reference {reference:.1e}, volume {volume:.1e} at {row['run_points']} points"


def offline(rows: list[dict]) -> list[str]:
    """The offline build of each mesh size, by part, against the moved-reference definition's
    greedy (``rom_real_time.csv``, where it has the size)."""
    lines = ["## Offline", ""]
    earlier = RESULTS / "rom_real_time.csv"
    greedy = {str(r["mesh h [mm]"]): r["offline_greedy_s"] for r in read_results(earlier)} if earlier.exists() else {}
    for size, r in {str(r["mesh h [mm]"]): r for r in rows}.items():
        parts = ", ".join(
            f"{part.removeprefix('offline_').removesuffix('_s')} {value:.0f} s"
            for part, value in r.items()
            if part.startswith("offline_") and part != "offline_s" and isinstance(value, float) and value >= 0.5
        )
        against = f"; the moved reference's greedy build: {greedy[size]:.0f} s" if size in greedy else ""
        lines.append(f"- h = {size}: {r['offline_s']:.0f} s ({parts}){against}.")
    return lines


def plot(rows: list[dict], path) -> None:
    """Error against online time: the breath's energy-norm error against the time per breath
    (left), the reference volume's against the time per static point (right); colour the mesh,
    marker the model (τ, k); the targets dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    from matplotlib.ticker import FuncFormatter

    fig, axes = plt.subplots(1, 2, figsize=(10.0, 4.8))
    sizes = list(dict.fromkeys(str(r["mesh h [mm]"]) for r in rows))
    colours = dict(zip(sizes, plt.cm.viridis(np.linspace(0.0, 0.8, len(sizes)))))
    models = sorted({(r["tau"], r["k"]) for r in rows}, key=lambda m: (-m[0], -m[1]))
    markers = dict(zip(models, itertools.cycle("o^sDvP")))
    panels = [
        ("online_ms_median", "energy_max", "a breath of 20 outputs [ms]", "worst energy-norm error [1]", 1e-2, None),
        (
            "static_ms_median",
            "reference_volume_max",
            "a static point [ms]",
            "worst reference-volume error, of the image's [1]",
            1e-4,
            10,
        ),
    ]
    for ax, (x, y, xlabel, ylabel, target, limit) in zip(axes, panels):
        for r in rows:
            ax.loglog(r[x], r[y], markers[(r["tau"], r["k"])], color=colours[str(r["mesh h [mm]"])], alpha=0.85)
        ax.axhline(target, color="grey", lw=0.8, ls="--")
        if limit:
            ax.axvline(limit, color="grey", lw=0.8, ls=":")
        ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        ax.xaxis.set_minor_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3, which="both")
    handles = [Patch(color=colours[s]) for s in sizes]
    labels = [
        ("bundled mesh" if s == "default" else f"h = {s} mm")
        + f", {next(r['dofs'] for r in rows if str(r['mesh h [mm]']) == s)} dofs"
        for s in sizes
    ]
    handles += [Line2D([], [], ls="none", marker=markers[m], color="grey") for m in models]
    labels += [f"ECSW τ = {tau:.0e}, k = {k}" for tau, k in models]
    fig.legend(handles, labels, fontsize=7, loc="lower center", ncol=4)
    fig.suptitle("The imaged lung at every μ: hyper-reduced against full (dashed: targets; dotted: 10 ms)", fontsize=10)
    fig.tight_layout(rect=(0, 0.1, 1, 0.95))
    fig.savefig(path, dpi=130)
    plt.close(fig)


def command_line(args) -> str:
    if args.quick:
        return "python benchmarks/rom_imaged.py --quick"
    defaults = {"sizes": SIZES, "train": 12, "unseen": 20, "size": 20, "run_points": 10}
    changed = [f"--{k.replace('_', '-')} {getattr(args, k)}" for k, v in defaults.items() if getattr(args, k) != v]
    return " ".join(["python benchmarks/rom_imaged.py", *changed])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default=SIZES, help="mesh sizes h in mm, or 'default' (comma-separated)")
    parser.add_argument("--train", type=int, default=12, help="training points (Sobol', seed 0)")
    parser.add_argument("--unseen", type=int, default=20, help="unseen points (Sobol', seed 12345), with the corners")
    parser.add_argument("--size", type=int, default=20, help="the breath's basis size (and its half)")
    parser.add_argument("--taus", type=float, nargs="+", default=[1e-4, 1e-5], help="ECSW tolerances")
    parser.add_argument(
        "--run-points", type=int, default=10, help="points where `run --set` is solved and compared (the first unseen)"
    )
    parser.add_argument("--replot", action="store_true", help="redraw the table and plot from the CSV")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: h = 40 mm, 3 training points, 1 unseen point (not the corners), τ = 1e-3, k = 4",
    )
    args = parser.parse_args()
    args.corners = not args.quick  # the smoke run's time goes to the method, not to more full solves
    if args.quick:
        args.sizes, args.train, args.unseen, args.size, args.taus, args.run_points = "40", 3, 1, 4, [1e-3], 1
    for option in ("train", "unseen", "size"):
        if getattr(args, option) < 1:
            parser.error(f"--{option}: a positive number (got {getattr(args, option)})")
    stem = "rom_imaged_quick" if args.quick else "rom_imaged"

    by_size(args, stem, case, markdown, plot, command_line(args))


if __name__ == "__main__":
    main()
