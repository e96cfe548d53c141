"""The real-time lung: hyper-reduced (ECSW) over a 3-parameter box, against its full model.

    python benchmarks/rom_real_time.py                          # h = bundled, 6, 5.5 mm (3 h)
    python benchmarks/rom_real_time.py --sizes default --unseen 6 --candidates 8   # minutes
    python benchmarks/rom_real_time.py --quick                  # h = 40 mm, 1 candidate, 1 unseen point (seconds)

The bundled breathing lung (``lungmech/scenes/lung_breathing.toml``: poromechanics, balanced
gravity, unloaded reference found once at the defaults) with 20 output times over the breath and
the three parameters of ``benchmarks/rom_parameters.py``: the skeleton's stiffness c1 (100–400
Pa, log), the breath's depth (pleural amplitude 0.6–1.4) and the posture (gravity pitched
−90°–0°). For each mesh size h:

* offline: the greedy training to ``--tolerance`` (:mod:`lungmech.rom.greedy`; POD in the energy
  norm; ``--candidates`` Sobol' points, seed 0), judging the hyper-reduced model at
  ``--judge-tau`` τ (its sample comes with the basis: that is the model's offline build); then
  one :class:`lungmech.rom.reductor.Reductor` of it makes every model of this table: the
  Newton iterates the greedy kept replayed once (on the basis and its enrichment W of the next
  POD directions) and an ECSW sample for every τ of ``--taus`` (an NNLS each; the judged τ's
  is the greedy's own);
* the full model at ``--unseen`` Sobol' points of another seed (each its own default solve from
  the scene's start: approach to μ, then the breath);
* for every τ and basis size k (the greedy basis and its leading halves): the hyper-reduced
  model at the same points: warm time per point (median; one warm-up solve first) and per
  static point (``solve(μ, times=[0])``: the end-expiration state at μ alone, with its
  outputs), the worst
  and mean errors against the full model (state in the energy norm relative to the breath's
  change, volume, volume change, probes), its own error indicator against the true error, the
  sampled cells and facets; and the Galerkin model (no hyper-reduction) of the greedy basis
  as the baseline (at the first ``--galerkin-points`` points, if given: it touches the whole
  mesh, minutes a point on the finest).

Writes results/rom_real_time.{md,csv} (--quick: rom_real_time_quick.*) and the Pareto plot
rom_real_time.png (error against
online time per point, per mesh size, the full and Galerkin models marked). One rank. The rows
of mesh sizes not measured by this run are kept from the CSV, each with its own command and
date (the sizes of a run are measured one after another: a run per size is as good).
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import logging
import statistics
import time
from functools import partial
from pathlib import Path

import machine
import numpy as np
from machine import SAME_START, by_size, provenance, say
from resumable import cached, code_version, kept
from rom_parameters import lung_scene

import lungmech  # noqa: F401  (before dolfinx: it loads the MPI library dolfinx's bindings need)
from lungmech.app.run import full_order_model
from lungmech.fem.parameters import Parameters
from lungmech.rom.greedy import greedy
from lungmech.rom.reduced import ReducedModel
from lungmech.rom.reductor import ECSW, Reductor, errors

RESULTS = machine.RESULTS
# the code this run imported, as it started (see resumable.py): all of it, and the full model's
VERSIONS = {"all": code_version(), "full": code_version(["rom"])}
TIMES = [round(0.1 * i, 1) for i in range(1, 20)]  # with the end: 20 outputs
# the bundled mesh (6.5k dofs) to 104k dofs: the issue's ≥ 100k, over ≥ 10× in mesh size
SIZES = "default,6,5.5"


def timed(reduced: ReducedModel, points: list[dict]) -> tuple[list, list[float]]:
    """The answers at ``points`` and the seconds of each, after one warm-up solve."""
    reduced.solve(points[0])
    answers, seconds = [], []
    for point in points:
        tic = time.perf_counter()
        answers.append(reduced.solve(point))
        seconds.append(time.perf_counter() - tic)
    return answers, seconds


def static_seconds(reduced: ReducedModel, points: list[dict]) -> list[float]:
    """The seconds of each static answer ``solve(μ, times=[start])``: the lung at end-expiration
    (the scene's start) moved to the point's parameters, and its outputs (the breath not
    followed)."""
    start, seconds = reduced.stepping.start, []
    for point in [points[0], *points]:  # the first: a warm-up
        tic = time.perf_counter()
        reduced.solve(point, times=[start])
        seconds.append(time.perf_counter() - tic)
    return seconds[1:]


def judged(reduced: ReducedModel, references: list, answers: list) -> dict:
    """Worst and mean errors of ``answers`` against the full ``references``, and the indicator's."""
    measured = [errors(reduced, f, a) for f, a in zip(references, answers)]
    probes = [
        float(np.abs(a.outputs["probes"] - f.outputs["probes"]).max() / np.abs(f.outputs["probes"]).max())
        for f, a in zip(references, answers)
    ]
    ratios = [a.indicator / m.energy for a, m in zip(answers, measured) if a.indicator is not None and m.energy > 0]
    return {
        "error_energy_max": max(m.energy for m in measured),
        "error_energy_mean": float(np.mean([m.energy for m in measured])),
        "error_volume_max": max(m.volume for m in measured),
        "error_volume_change_max": max(m.volume_change for m in measured),
        "error_probes_max": max(probes),
        "indicator_over_error_min": min(ratios) if ratios else None,
        "indicator_over_error_max": max(ratios) if ratios else None,
    }


def case(size: str, args) -> list[dict]:
    scene = lung_scene(size, TIMES)
    box = Parameters(scene.parameters)
    say(f"h = {size}: building the full model")
    full = full_order_model(scene, start="defaults")  # the defaults' reference moved to μ, as its greedy trains
    model = full.model
    dofs = model.space.dofmap.index_map.size_global * model.space.dofmap.index_map_bs
    mesh = model.geometry.mesh
    cells = mesh.topology.index_map(mesh.topology.dim).size_global

    def trained_greedy() -> tuple:
        offline = {}
        tic = time.perf_counter()
        candidates = box.sample(args.candidates, seed=0)
        trained = greedy(full, candidates, args.tolerance, 40, "energy", timings=offline, hyper=args.judge_tau)
        offline["greedy"] = time.perf_counter() - tic
        return trained, offline

    # each kept between runs (see resumable.py): the greedy by the whole code, the full
    # model's answers by all of it but the reduced models'
    name = f"rom_real_time-{size}-{_digest(scene)}"
    setup = f"{args.tolerance:g}-{args.candidates}-{args.judge_tau:g}"
    key = f"{name}-greedy-{setup}"
    (trained, offline), greedy_code = kept(key, VERSIONS["all"], trained_greedy, any_version=args.reuse_greedy)
    k = trained.basis.size
    say(f"  greedy: {k} vectors from {len(trained.training)} full paths, met {trained.met} ({offline['greedy']:.0f} s)")
    unseen = box.sample(args.unseen, seed=12345)
    references, full_seconds = [], []
    for j, mu in enumerate(unseen):
        references.append(cached(f"{name}-full-{_digest(mu)}", VERSIONS["full"], partial(full.solve, mu)))
        full_seconds.append(references[-1].seconds)
        say(f"  full model at unseen point {j}: {full_seconds[-1]:.1f} s")
    full_median = statistics.median(full_seconds)
    base = {"mesh h [mm]": size, "dofs": dofs, "cells": cells, "full_s_median": full_median}
    base |= {"command": command_line(args), "date": time.strftime("%Y-%m-%d")}
    base |= {"code": VERSIONS["all"], "greedy_code": greedy_code}  # lungmech's committed tree (resumable.py)
    rows = []
    with Reductor(full, trained) as reductor:
        galerkin = reductor.reduce()
        # the baseline touches the whole mesh (minutes a point at 5 mm): kept between runs too, and
        # at the first --galerkin-points points only, when asked
        some = unseen[: args.galerkin_points or None]
        answers, seconds = cached(
            f"{name}-galerkin-{setup}-{greedy_code}-{_digest(some)}", VERSIONS["all"], partial(timed, galerkin, some)
        )
        rows.append(
            base
            | {"model": "Galerkin", "k": k, "tau": None, "online_ms_median": 1e3 * statistics.median(seconds)}
            | {"speed_up": full_median / statistics.median(seconds), "points": len(some)}
            | judged(galerkin, references[: len(some)], answers)
        )
        say(f"  Galerkin k = {k}: {rows[-1]['online_ms_median']:.0f} ms, error {rows[-1]['error_energy_max']:.1e}")
        for tau in args.taus:
            for size_k in sorted({k} if args.quick else {k, max(1, k // 2)}, reverse=True):
                reduced = reductor.reduce(ECSW(tau, size=size_k))
                counted = reduced.sample.cells_per_type(mesh.comm)
                answers, seconds = timed(reduced, unseen)
                online = statistics.median(seconds)
                rows.append(
                    base
                    | {
                        "model": "ECSW",
                        "k": size_k,
                        "tau": tau,
                        "online_ms_median": 1e3 * online,
                        "points": len(unseen),
                    }
                    | {"static_ms_median": 1e3 * statistics.median(static_seconds(reduced, unseen))}
                    | {
                        "speed_up": full_median / online,
                        "online_newton_median": statistics.median(a.newton_iterations for a in answers),
                    }
                    | {"sampled_cells": counted["cell"], "sampled_facet_cells": counted["exterior_facet"]}
                    | {"sampled_percent": 100.0 * (counted["cell"] + counted["exterior_facet"]) / cells}
                    | {f"offline_nnls_{tau:g}_s": reduced.built["timings"]["nnls"]}
                    | judged(reduced, references, answers)
                )
                r = rows[-1]
                say(
                    f"  ECSW τ = {tau:g}, k = {size_k}: {r['online_ms_median']:.1f} ms ({r['speed_up']:.0f}×), "
                    f"error {r['error_energy_max']:.1e}, volume {r['error_volume_max']:.1e}"
                )
        # its replay of the greedy's iterates, and of that the tangents and the compressions
        offline |= {
            "replay" + part.removeprefix("ecsw_replay").replace("ecsw", ""): value
            for part, value in reductor.timings.items()
        }
    offline.setdefault("replay", 0.0)  # every τ the greedy's own: nothing replayed
    for row in rows:
        row |= {f"offline_{part}_s": value for part, value in offline.items()}
    return rows


def markdown(rows: list[dict], command: str, args, date: str | None = None) -> str:
    date = date or time.strftime("%Y-%m-%d")
    lines = [
        "# The real-time lung: hyper-reduced over stiffness × breath × posture",
        "",
        f"{provenance(command)} Greedy training to {args.tolerance:g} over {args.candidates} candidates, judging "
        f"the hyper-reduced model at τ = {args.judge_tau:g}; "
        f"{args.unseen} unseen points (Sobol', another seed); online times are warm medians over the unseen "
        "points, each a whole breath of 20 outputs from the scene's start (approach to μ, then the breath); "
        "the full model's the same, by its own default solve. A static point is the end-expiration state "
        "at μ alone (reduced Newton from the defaults' state) with its outputs. A run resumes a stopped one: "
        "the greedy and the full model's answers of the same code are kept between runs (benchmarks/resumable.py), "
        "with the times they took then.",
        "",
        SAME_START,
        *[
            f"Rows of h = {', '.join(dict.fromkeys(str(r['mesh h [mm]']) for r in rows if (r['command'], r['date']) == (c, d)))} "
            f"(kept from an earlier run): `{c}`, {d}."
            for c, d in dict.fromkeys((r["command"], r["date"]) for r in rows)
            if (c, d) != (command, date)
        ],
        *[
            f"The greedy of h = {r['mesh h [mm]']} was trained by lungmech's code {r['greedy_code']}; its online "
            f"models are code {r['code']}'s."
            for r in {str(r["mesh h [mm]"]): r for r in rows}.values()
            if r.get("greedy_code") and r.get("greedy_code") != r.get("code")
        ],
        "",
        "| h [mm] | dofs | model | k | τ | sampled cells (% of the mesh) | online per point [ms] | static point [ms] | "
        "full per point [s] | "
        "speed-up | energy-norm error: max, mean | volume error max | probes error max | indicator / error | "
        "offline [s]: greedy (its full solves, ECSW), NNLS at τ |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        sampled = (
            f"{r['sampled_cells'] + r['sampled_facet_cells']} ({r['sampled_percent']:.2f} %)" if r["tau"] else "all"
        )
        ratio = (
            f"{r['indicator_over_error_min']:.2f}–{r['indicator_over_error_max']:.2f}"
            if r["indicator_over_error_min"] is not None
            else "—"
        )
        nnls = r.get(f"offline_nnls_{r['tau']:g}_s", 0.0) if r["tau"] else 0.0
        static = f"{r['static_ms_median']:.1f}" if r.get("static_ms_median") is not None else "—"
        points = f" (at the first {r['points']} points)" if (r.get("points") or args.unseen) < args.unseen else ""
        lines.append(
            f"| {r['mesh h [mm]']} | {r['dofs']} | {r['model']}{points} | {r['k']} | {r['tau'] or '—'} | {sampled} | "
            f"{r['online_ms_median']:.1f} | {static} | {r['full_s_median']:.1f} | {r['speed_up']:.0f}× | "
            f"{r['error_energy_max']:.1e}, {r['error_energy_mean']:.1e} | {r['error_volume_max']:.1e} | "
            f"{r['error_probes_max']:.1e} | {ratio} | {r['offline_greedy_s']:.0f} "
            f"({r['offline_snapshots_s']:.0f}, {r['offline_ecsw_training_s'] + r['offline_nnls_s']:.0f}), "
            f"{nnls:.1f} |"
        )
    return "\n".join([*lines, "", *targets(rows)]) + "\n"


ACCURATE = {"error_energy_max": 1e-2, "error_volume_max": 1e-3}  # the issue's: 1 % energy norm, 0.1 % volume


def targets(rows: list[dict]) -> list[str]:
    """The issue's targets against the rows: per mesh size, the fastest hyper-reduced model as
    accurate as asked (its breath, static point and speed-up), and how the online time of each
    (τ, basis) grows from the smallest mesh to the largest. Each says by how much it is met or
    missed."""

    def verdict(value: float, limit: float, at_most: bool = True) -> str:
        if at_most:
            return f"met ({value / limit:.2g} of it)" if value <= limit else f"**missed**: {value / limit:.2g}× over"
        return f"met ({value / limit:.2g}× it)" if value >= limit else f"**missed**: {limit / value:.2g}× short"

    lines = [
        "## Targets",
        "",
        "Per mesh size, the fastest hyper-reduced model with ≤ 1 % energy-norm and ≤ 0.1 % volume error over "
        "the unseen points:",
        "",
        "| h [mm] | dofs | τ, k | breath ≤ 0.2 s | static point ≤ 10 ms | ≥ 1000× faster |",
        "|---|---|---|---|---|---|",
    ]
    sizes = sorted({(r["dofs"], str(r["mesh h [mm]"])) for r in rows})
    for dofs, size in sizes:
        accurate = [
            r
            for r in rows
            if str(r["mesh h [mm]"]) == size
            and r["model"] == "ECSW"
            and all(r[key] <= limit for key, limit in ACCURATE.items())
        ]
        if not accurate:
            lines.append(f"| {size} | {dofs} | none as accurate | — | — | — |")
            continue
        best = min(accurate, key=lambda r: r["online_ms_median"])
        lines.append(
            f"| {size} | {dofs} | {best['tau']:g}, {best['k']} | {best['online_ms_median']:.0f} ms: "
            f"{verdict(best['online_ms_median'], 200.0)} | {best['static_ms_median']:.1f} ms: "
            f"{verdict(best['static_ms_median'], 10.0)} | {best['speed_up']:.0f}×: "
            f"{verdict(best['speed_up'], 1000.0, at_most=False)} |"
        )
    if len(sizes) > 1:
        (small, smallest), (large, largest) = sizes[0], sizes[-1]
        lines += [
            "",
            f"Online time from the smallest mesh ({small} dofs) to the largest ({large} dofs, {large / small:.1f}×; "
            "the target: flat within 1.5× over ≥ 10×), per τ, for the greedy's basis and its leading half:",
            "",
        ]
        for role in ("greedy basis", "leading half"):
            for tau in sorted({r["tau"] for r in rows if r["model"] == "ECSW"}):
                ends = []
                for size in (smallest, largest):
                    mine = [r for r in rows if str(r["mesh h [mm]"]) == size and r["tau"] == tau]
                    if mine:
                        ends.append((max if role == "greedy basis" else min)(mine, key=lambda r: r["k"]))
                if len(ends) == 2:
                    growth = ends[1]["online_ms_median"] / ends[0]["online_ms_median"]
                    lines.append(
                        f"- τ = {tau:g}, {role} (k = {ends[0]['k']} → {ends[1]['k']}): "
                        f"{ends[0]['online_ms_median']:.0f} → {ends[1]['online_ms_median']:.0f} ms, "
                        f"{growth:.2f}×: {verdict(growth, 1.5)}"
                        + ("" if large / small >= 10 else " (over less than the 10× range)")
                    )
    return lines


def pareto(rows: list[dict], path: Path) -> None:
    """Error against time per parameter point: colour the mesh size, marker the ECSW model
    (τ, and the greedy's basis or its leading half; a size's points of one model lie together
    when the online time is flat); the Galerkin baseline; the full model (exact: drawn at the
    bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    fig, ax = plt.subplots(figsize=(8.0, 6.2))
    sizes = list(dict.fromkeys(r["mesh h [mm]"] for r in rows))
    colours = dict(zip(sizes, plt.cm.viridis(np.linspace(0.0, 0.85, len(sizes)))))
    hyper = [r for r in rows if r["model"] == "ECSW"]
    greedy_k = {size: max((r["k"] for r in hyper if r["mesh h [mm]"] == size), default=0) for size in sizes}
    role = {True: "the greedy's basis", False: "its leading half"}

    def model(r: dict) -> tuple[float, bool]:  # (τ, whether its basis is the greedy's)
        return float(r["tau"]), r["k"] == greedy_k[r["mesh h [mm]"]]

    models = sorted({model(r) for r in hyper}, key=lambda m: (-m[0], not m[1]))
    markers = dict(zip(models, itertools.cycle("o^vDPXh<>")))  # more τ than shapes: shapes repeat
    floor = min(r["error_energy_max"] for r in rows) / 3
    for r in hyper:
        ax.loglog(
            1e-3 * r["online_ms_median"],
            r["error_energy_max"],
            markers[model(r)],
            color=colours[r["mesh h [mm]"]],
            alpha=0.85,
        )
    for size in sizes:
        g = next(r for r in rows if r["mesh h [mm]"] == size and r["model"] == "Galerkin")
        ax.loglog(1e-3 * g["online_ms_median"], g["error_energy_max"], "s", mfc="none", color=colours[size])
        ax.loglog(g["full_s_median"], floor, "*", ms=11, color=colours[size])
    handles = [Patch(color=colours[size]) for size in sizes]
    labels = [
        ("bundled mesh" if size == "default" else f"h = {size} mm")
        + f", {next(r['dofs'] for r in rows if r['mesh h [mm]'] == size)} dofs"
        for size in sizes
    ]
    for (tau, greedy_basis), marker in markers.items():
        handles.append(Line2D([], [], ls="none", marker=marker, color="grey"))
        labels.append(f"ECSW, τ = {tau:.0e}, {role[greedy_basis]}")
    handles += [
        Line2D([], [], ls="none", marker="s", mfc="none", color="grey"),
        Line2D([], [], ls="none", marker="*", ms=11, color="grey"),
        Line2D([], [], color="grey", lw=0.8, ls="--"),
        Line2D([], [], color="grey", lw=0.8, ls=":"),
    ]
    labels += [
        "Galerkin, no hyper-reduction",
        "full model, exact (drawn at the bottom)",
        "target: 1 % energy-norm error",
        "target: 0.2 s per breath of ≥ 20 outputs",
    ]
    ax.axhline(1e-2, color="grey", lw=0.8, ls="--")
    ax.axvline(0.2, color="grey", lw=0.8, ls=":")
    ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("time per parameter point: a breath of 20 outputs from the start [s]")
    ax.set_ylabel("worst energy-norm error over the unseen points [1]")
    ax.set_title("Breathing lung over stiffness × breath × posture (colour: mesh; marker: model)", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(handles, labels, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def _digest(value) -> str:
    """8 hex digits of ``repr(value)``: a scene, a parameter point."""
    return hashlib.sha1(repr(value).encode()).hexdigest()[:8]


def command_line(args) -> str:
    """This run's command line (the options that differ from the defaults)."""
    if args.quick:
        return "python benchmarks/rom_real_time.py --quick"
    return (
        "python benchmarks/rom_real_time.py"
        + (f" --sizes {args.sizes}" if args.sizes != SIZES else "")
        + (f" --unseen {args.unseen}" if args.unseen != 20 else "")
        + (f" --candidates {args.candidates}" if args.candidates != 16 else "")
        + (" --reuse-greedy" if args.reuse_greedy else "")
        + (f" --galerkin-points {args.galerkin_points}" if args.galerkin_points else "")
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default=SIZES, help="mesh sizes h in mm, or 'default' (comma-separated)")
    parser.add_argument("--tolerance", type=float, default=1e-3, help="greedy training tolerance")
    parser.add_argument("--candidates", type=int, default=16, help="greedy candidate points")
    parser.add_argument("--unseen", type=int, default=20, help="unseen points")
    parser.add_argument("--taus", type=float, nargs="+", default=[1e-3, 1e-4, 1e-5], help="ECSW tolerances")
    parser.add_argument("--judge-tau", type=float, default=1e-4, help="the ECSW tolerance the greedy judges with")
    parser.add_argument("--replot", action="store_true", help="redraw the plot from results/rom_real_time.csv")
    parser.add_argument(
        "--reuse-greedy",
        action="store_true",
        help="a greedy kept from another code version serves (the online models are this code's; the table says so)",
    )
    parser.add_argument(
        "--galerkin-points", type=int, default=0, help="the Galerkin baseline at the first N unseen points (0: all)"
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: h = 40 mm, 1 candidate, 1 unseen point, τ = 1e-3 (results rom_real_time_quick.*)",
    )
    args = parser.parse_args()
    if args.quick:
        args.sizes, args.candidates, args.unseen, args.taus, args.tolerance = "40", 1, 1, [1e-3], 1e-2
        args.galerkin_points = 1
    stem = "rom_real_time_quick" if args.quick else "rom_real_time"
    if args.galerkin_points < 0:
        parser.error(f"--galerkin-points: a number of points, 0 for all (got {args.galerkin_points})")

    # the clock time of each greedy round, to see where an offline build goes
    logging.basicConfig(level=logging.INFO, format="    %(asctime)s %(message)s", datefmt="%H:%M:%S")
    by_size(args, stem, case, markdown, pareto, command_line(args))


if __name__ == "__main__":
    main()
