"""Reduced models of the breathing lung over its 3-parameter box, per basis size, measured by `lungmech trade`.

    python benchmarks/rom_parameters.py                  # 16 training points, k = 5, 10, 20, 40: Galerkin, ECSW τ = 1e-4
    python benchmarks/rom_parameters.py --taus           # Galerkin alone
    python benchmarks/rom_parameters.py --quick          # the sphere octant over its stiffness, k = 2, 3 (a minute)

A thin caller of :func:`lungmech.app.trade.trade`, the one measurement of models of a scene
(what RBniCS's ``error_analysis`` and ``speedup_analysis`` tabulate per basis size). The scene
is the bundled ``lung_breathing_parameters`` as the imaged-lung problem every command answers
(the image is the lung at end-expiration for every μ; each answer finds its reference at μ),
over the skeleton's stiffness c1 (100–400 Pa, log), the breath's depth (a factor on the pleural
pressure, 0.6–1.4) and the posture (gravity pitched, −90°–0°).

The family (``--build``): one POD (energy inner product) of the full model's breaths at
``--train`` Sobol' points (seed 0); at each basis size k of ``--sizes`` its leading vectors,
Galerkin, and hyper-reduced at each τ of ``--taus`` (default 1e-4). The full models: P1 on the
scene's mesh, the model the family reduces, and the reference P1 on that mesh refined once.
Points: ``--test`` seeded Sobol' points none was trained on, and the box's 8 corners. Two
trades share lungmech's cache (the full answers, the built models):

* ``pv``: each whole breath; the volume at every output time, relative to the breath's largest
  volume change;
* ``energy``: the state at end-inspiration (a static solve), in the energy norm relative to
  its change from the start.

Per model, the trade's columns: its error of reduction (against P1 on the scene's mesh: what
a larger basis removes) worst and mean, its error against the reference (the mesh's own added),
its own estimate, the warm online time of a breath and of a static point (each model measured
in a process of its own), the speed-up over P1 measured the same way, peak memory, offline
cost. The full solves run on Parsl's local workers (``--workers``; 0: one after another).
``--quick`` measures the same on the bundled sphere octant over its stiffness (3 points: its
corners are 2), from 2 training points. Writes results/rom_parameters{,_quick}.{md,csv,png}.
"""

from __future__ import annotations

import argparse
import copy
import logging
import sys
import tempfile
import time
import tomllib
from importlib import resources
from pathlib import Path

import machine
import numpy as np
from machine import provenance, say, write_results

import lungmech  # noqa: F401  (before dolfinx: it loads the MPI library dolfinx's bindings need)
from lungmech.app import scene as scenes
from lungmech.scenes import bundled

QUANTITIES = ("pv", "energy")
SCENE = "lung_breathing_parameters"
SPHERE = Path(str(resources.files("lungmech.scenes") / "sphere_inflation_parameters.toml"))  # --quick's


def lung_scene(size: str = "default", times: list[float] | None = None) -> scenes.Scene:
    """The bundled breathing lung over its three parameters (``lung_breathing_parameters``),
    without field output; at mesh size h = ``size`` mm ("default": the bundled mesh) and output
    ``times`` (s; default the scene's). (For the benchmarks that solve it in Python.)"""
    with resources.as_file(bundled(SCENE)) as path:
        table = copy.deepcopy(tomllib.loads(Path(path).read_text()))
    table["output"] = {"fields": False, "probes": table["output"]["probes"]}
    if times is not None:
        table["stepping"]["times"] = times
    if size != "default":
        table["geometry"]["mesh_size"] = float(size) / 1e3
    return scenes.parse(table)


def scene_file(folder: Path, size: str) -> Path:
    """The bundled scene's file, as it is ("default") or at mesh size h = ``size`` mm (its text
    with the size added to [geometry], written into ``folder``): a trade reads a scene file."""
    if size == "default":
        return Path(str(resources.files("lungmech.scenes") / f"{SCENE}.toml"))
    with resources.as_file(bundled(SCENE)) as path:
        text = Path(path).read_text()
    marker = 'builder = "lung_phantom"\n'
    if marker not in text:
        raise SystemExit(f"the bundled {SCENE} scene no longer has {marker.strip()!r} in [geometry]")
    written = folder / f"{SCENE}_h{size}.toml"
    written.write_text(text.replace(marker, f"{marker}mesh_size = {float(size) / 1e3!r}\n", 1))
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--train", type=int, default=16, help="training points (Sobol', seed 0)")
    parser.add_argument(
        "--test", type=int, default=8, help="interior test points (Sobol', seed 12345), with the corners"
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=[5, 10, 20, 40], help="basis sizes k")
    parser.add_argument(
        "--taus",
        type=float,
        nargs="*",
        default=[1e-4],
        help="ECSW tolerances τ at each size (default 1e-4; none: --taus)",
    )
    parser.add_argument("--mesh-size", default="default", help="mesh size h in mm, or 'default' (the bundled mesh)")
    parser.add_argument("--tolerance", type=float, default=1e-3, help="the trade's choice, on each quantity")
    parser.add_argument("--workers", type=int, default=None, help="Parsl's local workers (default 2; 0 with --quick)")
    parser.add_argument("--cache", default=None, help="lungmech's cache folder (default results/raw/lungmech-cache)")
    parser.add_argument("--quick", action="store_true", help="the sphere octant, 2 training points, k = 2, 3")
    args = parser.parse_args()
    if args.quick:
        args.train, args.test, args.sizes = 2, 1, [2, 3]
    workers = args.workers if args.workers is not None else (0 if args.quick else 2)
    logging.basicConfig(level=logging.INFO, format="%(message)s")  # the trades' progress lines
    began = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="lungmech-rom-parameters-") as folder:
        scene = SPHERE if args.quick else scene_file(Path(folder), args.mesh_size)
        cache = Path(args.cache) if args.cache else (Path(folder) / "cache" if args.quick else _default_cache())
        found = {quantity: _traded(scene, quantity, cache, workers, args) for quantity in QUANTITIES}
    stem = "rom_parameters_quick" if args.quick else "rom_parameters"
    table = rows(found)
    write_results(
        machine.RESULTS, stem, table, markdown(found, table, command(args), workers, time.perf_counter() - began)
    )
    plot(found, table, machine.RESULTS / f"{stem}.png")
    print((machine.RESULTS / f"{stem}.md").read_text())


def _default_cache() -> Path:
    return machine.RESULTS / "raw" / "lungmech-cache"


def _traded(scene: Path, quantity: str, cache: Path, workers: int, args: argparse.Namespace):
    """The trade of the family against P1 h and the reference P1 h/2, on ``quantity``."""
    from lungmech.app.ladder import Discretisation
    from lungmech.app.trade import Candidate, Family, trade
    from lungmech.parallel.engine import local_pool
    from lungmech.parallel.ensemble import Serial

    family = Family(taus=tuple(args.taus), sizes=tuple(args.sizes), samples=args.train, seed=0)
    settings = {"count": args.test, "cache": cache, "levels": 1, "full": [Candidate.full(Discretisation(0, 1))]}
    say(f"trade on {quantity}")
    if workers:
        with local_pool(workers, 1) as pool:
            return trade(scene, args.tolerance, quantity, build=family, ensemble=pool, **settings)
    return trade(scene, args.tolerance, quantity, build=family, ensemble=Serial(), **settings)


def rows(found: dict) -> list[dict]:
    """One row per model (the reference left out): the trade's columns of each quantity side by
    side, the online times of a breath (``pv``) and of a static point (``energy``)."""
    from lungmech.app import trade_report

    by_quantity = {q: {row["model"]: row for row in trade_report.rows(t)} for q, t in found.items()}
    breath, static = by_quantity["pv"], by_quantity["energy"]
    scene_mesh = found["pv"].own
    out = []
    for name, row in breath.items():
        if row["family"] == "reference":
            continue
        line = {
            "model": name,
            "family": row["family"],
            "dofs": row["dofs"],
            "basis size": row["basis size"],
            "ECSW τ": row["ECSW τ"],
        }
        for q, label in (("pv", "P–V"), ("energy", "energy-norm")):
            mine, reference = by_quantity[q][name], found[q].reference
            column = f"{trade_report.COLUMNS[q][0]} max [-]"
            line[f"{label} reduction error max [-]"] = mine["reduction error max [-]"]
            line[f"{label} reduction error mean [-]"] = _mean(found[q].reduction.get(name, {}).get(q))
            line[f"{label} error against {reference} max [-]"] = mine[column]
        line["own estimate max [-]"] = row["own estimate max [-]"]
        line["failed points"] = max(row["failed points"], static[name]["failed points"])
        line["whole path [ms]"] = row["online [ms]"]
        line["static point [ms]"] = static[name]["online [ms]"]
        full = breath.get(scene_mesh, {}).get("online [ms]")
        line["speed-up, whole path [-]"] = None if not full or not row["online [ms]"] else full / row["online [ms]"]
        line["peak RSS [MiB]"] = max(row["peak RSS [MiB]"] or 0.0, static[name]["peak RSS [MiB]"] or 0.0)
        line["offline [s]"] = row["offline [s]"]
        line["full solves"] = row["full solves"]
        out.append(line)
    return out


def _mean(values) -> float | None:
    finite = None if values is None else np.asarray(values)[np.isfinite(values)]
    return None if finite is None or not finite.size else float(finite.mean())


def markdown(found: dict, table: list[dict], command: str, workers: int, seconds: float) -> str:
    from lungmech.trade import quantities
    from lungmech.trade.points import failure_bound

    breath = found["pv"]
    kinds = ", ".join(f"{breath.points.kinds.count(k)} {k}" for k in dict.fromkeys(breath.points.kinds))
    engine = f"Parsl's {workers} local workers of 1 rank" if workers else "one process"
    columns = list(table[0])
    lines = [
        f"# Reduced models of {Path(breath.scene).stem} over its parameter box, per basis size",
        "",
        provenance(command, f"full solves on {engine}; each model measured on one rank"),
        "",
        "Measured by `lungmech trade` (two trades sharing one cache: the whole path, and the static state at "
        f"the largest load, t = {found['energy'].times[0]:g} s). "
        + (
            "The imaged lung: the image is the lung at end-expiration for every μ, each answer finds its "
            "reference at μ. "
            if "lung" in Path(breath.scene).stem
            else ""
        )
        + f"{len(breath.points)} points ({kinds}), none a model was trained on; "
        f"with none failing, the share of the box that could fail is below {failure_bound(len(breath.points)):.1%} (95 %).",
        "",
        f"- Reduction error: against {breath.own}, the full model the family reduces, with the same denominators: "
        f"P–V, {quantities.DENOMINATORS['pv']}; energy norm, {quantities.DENOMINATORS['energy']}.",
        f"- Error against {breath.reference}: the same, against the scene's mesh refined once (the mesh's own "
        "error added): where it stops falling with k, the mesh, not the basis, limits the model.",
        "- Times: warm medians per point in the model's own process (the whole path at the scene's output times; "
        "a static point, the state at the largest load); speed-up: the full model's whole path over the model's.",
        f"- The whole run took {seconds / 60:.1f} min; full solves: pv {_solves(breath)}, energy {_solves(found['energy'])}.",
        "",
        "| " + " | ".join(columns) + " |",
        "|" + "---|" * len(columns),
    ]
    for row in table:
        lines.append("| " + " | ".join(_cell(row[c]) for c in columns) + " |")
    lines.append("")
    for q, t in found.items():
        lines.append(f"- Choice on {q} at {t.tolerance:g}: {t.choice.reason if t.choice else 'none'}")
    notes = list(dict.fromkeys(note for t in found.values() for note in t.notes))
    if notes:
        lines += ["", "Notes:", "", *(f"- {note}" for note in notes)]
    return "\n".join(lines) + "\n"


def _solves(found) -> str:
    return f"{found.full_solves.get('solved', 0)} solved, {found.full_solves.get('kept', 0)} kept"


def _cell(value) -> str:
    if value is None:
        return "—"
    if isinstance(value, float):
        return f"{value:.2e}" if value and (abs(value) < 1e-2 or abs(value) >= 1e4) else f"{value:.3g}"
    return str(value)


def plot(found: dict, table: list[dict], path: Path) -> None:
    """The worst reduction error per basis size (a line per quantity and family), and the mesh's
    own error (P1 on the scene's mesh against the reference) as a line across."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    figure, axes = plt.subplots(figsize=(7.5, 6))
    colours = {"pv": "tab:blue", "energy": "tab:orange"}
    labels = {"pv": "P–V", "energy": "energy norm"}
    for q, colour in colours.items():
        column = f"{'P–V' if q == 'pv' else 'energy-norm'} reduction error max [-]"
        for tau in sorted(
            {row["ECSW τ"] for row in table if row["basis size"]}, key=lambda t: -1.0 if t is None else t
        ):
            mine = sorted(
                (row["basis size"], row[column])
                for row in table
                if row["ECSW τ"] == tau and row["basis size"] and row[column]
            )
            if mine:
                style = "o-" if tau is None else "s--"
                family = "Galerkin" if tau is None else f"ECSW τ = {tau:g}"
                axes.semilogy(*zip(*mine), style, color=colour, label=f"{labels[q]}, {family}")
        if q == "energy":  # the indicator estimates the state's error of reduction in the energy norm
            own = sorted(
                (row["basis size"], row["own estimate max [-]"])
                for row in table
                if row["ECSW τ"] is None and row["basis size"] and row["own estimate max [-]"]
            )
            if own:
                axes.semilogy(*zip(*own), "^", color="grey", mfc="none", label="Galerkin's own estimate (energy norm)")
        mesh = next((row for row in table if row["model"] == found[q].own), None)
        against = f"{'P–V' if q == 'pv' else 'energy-norm'} error against {found[q].reference} max [-]"
        if mesh is not None and mesh[against]:
            label = f"{labels[q]}: {found[q].own} against {found[q].reference} (the mesh's own error)"
            axes.axhline(mesh[against], color=colour, lw=0.9, ls=":", label=label)
    axes.xaxis.set_major_locator(MaxNLocator(integer=True))
    axes.set_xlabel("basis size k [-]")
    axes.set_ylabel(f"worst relative error over {len(found['pv'].points)} points [-]")
    axes.set_title(f"{Path(found['pv'].scene).stem}: the error of reduction per basis size", fontsize=10)
    axes.legend(fontsize=7.5, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2)  # below: the lines stay clear
    figure.tight_layout()
    figure.savefig(path, dpi=150)
    plt.close(figure)


def command(args: argparse.Namespace) -> str:
    if args.quick:
        return "python benchmarks/rom_parameters.py --quick"
    parts = ["python benchmarks/rom_parameters.py"]
    if args.train != 16:
        parts.append(f"--train {args.train}")
    if args.test != 8:
        parts.append(f"--test {args.test}")
    if args.sizes != [5, 10, 20, 40]:
        parts.append("--sizes " + " ".join(map(str, args.sizes)))
    if args.taus != [1e-4]:
        parts.append("--taus " + " ".join(f"{t:g}" for t in args.taus))
    if args.mesh_size != "default":
        parts.append(f"--mesh-size {args.mesh_size}")
    return " ".join(parts)


if __name__ == "__main__":
    sys.exit(main())
