"""One `lungmech rom solve` as a process, start-up included: a hyper-reduced lung across mesh sizes.

    python benchmarks/rom_process.py            # the bundled lung at its mesh, h = 7 and 6 mm (minutes)
    python benchmarks/rom_process.py --quick    # the pulled block at one size (about 15 s): a smoke run

For each mesh size, a hyper-reduced model built by the documented command (``lungmech rom build
--hyper ecsw``; POD of 8 vectors at most, τ = 1e-3) is solved the way a user runs it, each a new
process with a warm JIT cache (one warm-up run first), and timed on the wall clock (median of
``--repeats``):

* ``rom solve model.npz``: the answer's numbers (summary.json, history.csv) from the model on its
  sampled cells alone, with no full mesh (:func:`lungmech.rom.store.load_body`);
* ``rom solve model.npz --fields``: also the full fields and the pictures (the full mesh built);
* ``rom solve model.npz --sweep points.csv``: ``--points`` parameter points (the quick case's
  block has a parameter; the bundled lung has none, so it has no sweep: "—").

The full model's ``lungmech run`` of the same scene is timed once, as the scale. Writes
results/rom_process{,_quick}.{md,csv,png}. One rank.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from importlib import resources
from pathlib import Path

import machine
from machine import provenance, say, write_results

LUNGMECH = [sys.executable, "-m", "lungmech.app.cli"]
QUICK_REPEATS = 1  # the quick case checks the benchmark runs; its timings are indicative
BLOCK = """title = "pulled block"
[geometry]
builder = "box"
cells = [{n}, {m}, {m}]
lengths = [2.0, 1.0, 1.0]
[material]
law = "neo_hookean"
E = 1.0e3
nu = 0.3
[[constraints]]
type = "clamp"
boundary = "x0"
[[loads]]
type = "traction"
boundary = "x1"
value = [0.0, 0.0, -10.0]
name = "pull"
[parameters.stiffness]
target = "material.E"
range = [500.0, 2000.0]
[output]
fields = true
"""


def lung_scene(size: str) -> str:
    """The bundled breathing lung's scene at mesh size ``size`` mm ("default": its own mesh)."""
    text = (resources.files("lungmech.scenes") / "lung_breathing.toml").read_text()
    if size == "default":
        return text
    return text.replace("[geometry]\n", f"[geometry]\nmesh_size = {float(size) / 1e3}\n", 1)


def python_as_users_have_it(folder: Path) -> dict[str, str]:
    """The environment of the timed processes: Python's bytecode cached, as a default Python
    caches it (here in ``folder``, not beside the sources), where the caller's environment
    turned that off (PYTHONDONTWRITEBYTECODE: every process would compile lungmech's modules
    anew, a quarter of a second)."""
    environment = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    environment.setdefault("PYTHONPYCACHEPREFIX", str(folder / "pycache"))
    return environment


def wall(command: list[str], repeats: int, warm_up: bool, environment: dict[str, str]) -> float:
    """The median wall time (s) of ``repeats`` runs of ``command``, after one warm-up run unless
    ``warm_up`` is False (its forms were compiled by a command before)."""
    seconds = []
    for _ in range(repeats + warm_up):
        tic = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True, env=environment)
        seconds.append(time.perf_counter() - tic)
        if done.returncode != 0:
            raise SystemExit(f"{' '.join(command)} failed: {done.stderr.strip() or done.stdout.strip()}")
    return statistics.median(seconds[warm_up:])


def case(name: str, scene_text: str, folder: Path, repeats: int, points: list[float] | None, warm_up: bool) -> dict:
    """Build the hyper-reduced model of a scene, then time its solves (after a warm-up run each
    if ``warm_up``) and the full run."""
    environment = python_as_users_have_it(folder)
    scene, model = folder / f"{name}.toml", folder / f"{name}.npz"
    scene.write_text(scene_text)
    build = [*LUNGMECH, "rom", "build", str(scene), "-o", str(model), "--hyper", "ecsw"]
    build += ["--ecsw-tolerance", "1e-3", "--size", "8", "-q"] + (["--samples", "4"] if points else [])
    tic = time.perf_counter()
    done = subprocess.run(build, capture_output=True, text=True, env=environment)
    if done.returncode != 0:
        raise SystemExit(f"building {name} failed: {done.stderr.strip() or done.stdout.strip()}")
    offline = time.perf_counter() - tic
    out = folder / f"{name}-out"
    one = wall([*LUNGMECH, "rom", "solve", str(model), "-o", str(out), "-q"], repeats, warm_up, environment)
    fields = wall(
        [*LUNGMECH, "rom", "solve", str(model), "-o", str(out), "--fields", "-q"], repeats, warm_up, environment
    )
    csv = folder / f"{name}-points.csv"
    csv.write_text("stiffness\n" + "".join(f"{p}\n" for p in points) if points else "\n")
    sweep = [*LUNGMECH, "rom", "solve", str(model), "-o", str(folder / f"{name}-sweep")]
    swept = wall([*sweep, "--sweep", str(csv)], repeats, False, environment) if points else None  # rom solve's forms
    tic = time.perf_counter()
    full_run = [*LUNGMECH, "run", str(scene), "-o", str(folder / f"{name}-full"), "-q"]
    done = subprocess.run(full_run, capture_output=True, env=environment)
    full = time.perf_counter() - tic
    summary = json.loads((out / "summary.json").read_text())
    return {
        "case": name,
        "dofs": summary["dofs"],
        "cells": summary["cells"],
        "sampled_cells": summary["solver"],
        "offline_s": offline,
        "rom_solve_s": one,
        "rom_solve_fields_s": fields,
        "sweep_s": swept,
        "sweep_points": len(points) if points else None,
        "full_run_s": full,
        "full_over_rom_solve": full / one,
    }


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    dofs = [r["dofs"] for r in rows]
    for key, label in (
        ("rom_solve_s", "rom solve (sampled cells alone)"),
        ("rom_solve_fields_s", "rom solve --fields (full mesh)"),
        ("full_run_s", "run (full model)"),
    ):
        ax.loglog(dofs, [r[key] for r in rows], "o-", label=label)
    ax.axhline(1.0, color="grey", linestyle=":", label="1 s")
    ax.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("degrees of freedom of the full model [-]")
    ax.set_ylabel("wall time of the process [s]")
    ax.set_title("One solve as a process, start-up included (warm JIT cache)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the pulled block at one mesh size: a smoke run")
    parser.add_argument("--sizes", default="default,7,6", help="lung mesh sizes in mm ('default': the bundled mesh)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--points", type=int, default=4, help="points of the quick case's sweep")
    args = parser.parse_args()
    stem = "rom_process_quick" if args.quick else "rom_process"
    command = "python benchmarks/rom_process.py" + (" --quick" if args.quick else f" --sizes {args.sizes}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="lungmech-rom-process-") as work:
        folder = Path(work)
        if args.quick:
            points = [500.0 + 1500.0 * i / max(args.points - 1, 1) for i in range(args.points)]
            for n in (2,):  # (the sizes' trend is the full run's)
                text = BLOCK.format(n=2 * n, m=n)
                rows.append(case(f"block{n}", text, folder, QUICK_REPEATS, points, warm_up=False))
                say(rows[-1])
        else:
            for size in args.sizes.split(","):
                rows.append(case(f"lung-{size}", lung_scene(size), folder, args.repeats, None, warm_up=True))
                say(rows[-1])
    header = "| case | dofs | cells | rom solve [s] | rom solve --fields [s] | sweep [s] (points) | full run [s] | full / rom solve |"
    lines = [f"# One `rom solve` as a process\n\n{provenance(command)}\n", header, "|" + "---|" * 8]
    for r in rows:
        sweep = f"{r['sweep_s']:.2f} ({r['sweep_points']})" if r["sweep_s"] is not None else "—"
        lines.append(
            f"| {r['case']} | {r['dofs']} | {r['cells']} | {r['rom_solve_s']:.2f} | {r['rom_solve_fields_s']:.2f} | "
            f"{sweep} | {r['full_run_s']:.1f} | {r['full_over_rom_solve']:.0f}× |"
        )
    lines.append(
        "\nWall time of each command as a new process, start-up included, warm JIT cache, median of "
        + (
            f"{QUICK_REPEATS} run (a smoke run: its forms compiled by the build, no warm-up); "
            if args.quick
            else f"{args.repeats} runs after a warm-up; "
        )
        + "the full run once. "
        "Python's bytecode cached, as a default Python caches it. "
        "`rom solve` loads the model on its sampled cells alone and writes summary.json and history.csv; "
        "`--fields` builds the full mesh for the fields and the pictures."
    )
    machine.RESULTS.mkdir(parents=True, exist_ok=True)
    write_results(machine.RESULTS, stem, rows, "\n".join(lines) + "\n")
    plot(rows, machine.RESULTS / f"{stem}.png")
    say(f"wrote {machine.RESULTS / stem}.md")


if __name__ == "__main__":
    main()
