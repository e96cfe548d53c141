"""A reduced model of the breathing lung over a 3-parameter box, against the full model, measured.

    python benchmarks/rom_parameters.py              # 16 training points, 10 unseen points
    python benchmarks/rom_parameters.py --train 8 --test 10 --sizes 10 20 30
    python benchmarks/rom_parameters.py --quick      # h = 40 mm, 2 training points and 1 unseen

The scene is the bundled breathing lung over three parameters
(lungmech/scenes/lung_breathing_parameters.toml: poromechanics, balanced gravity, unloaded
reference found once at the default parameters):

* ``stiffness``: the skeleton's c1 (material.c1), 100–400 Pa, log scale;
* ``breath``: a factor on the pleural pressure (loads.pleural.amplitude), 0.6–1.4;
* ``posture``: gravity turned about the left–right axis (loads.gravity.pitch), −90° (supine) to 0°
  (upright).

``lungmech.app.reduce.build`` trains the POD basis (energy inner product) on the load paths at
TRAIN Sobol' points of the box (seed 0); the TEST unseen points are Sobol' points of another seed.
The basis is built once at the largest size; smaller ones are its leading vectors (POD is
nested). For each basis size: the worst and mean errors over the unseen points — the state in the energy
norm relative to its largest change along the path, the volume relative to the volume change
and to the volume, the strain energy — and the full and reduced solve times (same process, one
rank). Writes benchmarks/results/rom_parameters.{md,csv} and rom_parameters.png (--quick:
rom_parameters_quick.*).
"""

from __future__ import annotations

import argparse
import copy
import csv
import sys
import tempfile
import time
import tomllib
from importlib import resources
from pathlib import Path

import machine
import numpy as np
from machine import SAME_START, cpu_and_memory, say  # benchmarks/ is the script folder, first on sys.path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import dolfinx_solver  # noqa: F401  (MPI before the compiled bindings)
from mpi4py import MPI

from lungmech.app import reduce as reduce_app
from lungmech.app import scene as scenes
from lungmech.app.run import full_order_model
from lungmech.fem.parameters import Parameters
from lungmech.rom.reductor import errors
from lungmech.scenes import bundled

RESULTS = machine.RESULTS


def lung_scene(size: str = "default", times: list[float] | None = None) -> scenes.Scene:
    """The bundled breathing lung over its three parameters (``lung_breathing_parameters``),
    without field output; at mesh size h = ``size`` mm ("default": the bundled mesh) and output
    ``times`` (s; default the scene's)."""
    with resources.as_file(bundled("lung_breathing_parameters")) as path:
        table = copy.deepcopy(tomllib.loads(Path(path).read_text()))
    table["output"] = {"fields": False, "probes": table["output"]["probes"]}
    if times is not None:
        table["stepping"]["times"] = times
    if size != "default":
        table["geometry"]["mesh_size"] = float(size) / 1e3
    return scenes.parse(table)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", type=int, default=16, help="training points (Sobol', seed 0)")
    parser.add_argument("--test", type=int, default=10, help="unseen points (Sobol', seed 12345)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[10, 20, 40], help="basis sizes")
    parser.add_argument("--mesh-size", default="default", help="mesh size h in mm, or 'default' (the bundled mesh)")
    parser.add_argument(
        "--quick", action="store_true", help="smoke run: h = 40 mm, 2 training points and 1 unseen, sizes 2 4"
    )
    args = parser.parse_args()
    if args.quick:
        args.train, args.test, args.sizes, args.mesh_size = 2, 1, [2, 4], "40"
    comm = MPI.COMM_WORLD
    scene = lung_scene(args.mesh_size)
    box = Parameters(scene.parameters)
    unseen = box.sample(args.test, seed=12345)

    say("full model: building (unloaded reference at the default parameters)")
    full = full_order_model(scene, comm, start="defaults")  # the defaults' reference moved to μ, as its greedy trains
    dofs = full.model.space.dofmap.index_map.size_global * full.model.space.dofmap.index_map_bs
    references, full_seconds = [], []
    for j, mu in enumerate(unseen):
        solution = full.solve(mu)
        references.append(solution)
        full_seconds.append(solution.seconds)
        say(f"  unseen point {j}: {mu} full solve {solution.seconds:.1f} s")

    rows = []
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "lung.npz"
        tic = time.perf_counter()
        summary = reduce_app.build(scene, path, size=max(args.sizes), samples=args.train, inner="energy", comm=comm)
        offline = time.perf_counter() - tic
        largest = reduce_app.load(path, comm)
        say(f"offline: {offline:.0f} s, basis of {largest.size} vectors")
        for size in sorted(args.sizes):
            reduced = largest.truncated(min(size, largest.size))  # POD bases are nested
            measured, seconds = [], []
            for mu, reference in zip(unseen, references):
                approximate = reduced.solve(mu)
                seconds.append(approximate.seconds)
                measured.append(errors(reduced, reference, approximate))
            row = {
                "basis size [1]": reduced.size,
                "asked size [1]": size,
                "training points [1]": args.train,
                "unseen points [1]": len(unseen),
                "energy-norm error, max [1]": max(e.energy for e in measured),
                "energy-norm error, mean [1]": float(np.mean([e.energy for e in measured])),
                "volume error / volume change, max [1]": max(e.volume_change for e in measured),
                "volume error / volume, max [1]": max(e.volume for e in measured),
                "strain-energy error, max [1]": max(e.strain_energy for e in measured),
                "full solve, median [s]": float(np.median(full_seconds)),
                "reduced solve, median [s]": float(np.median(seconds)),
                "speed-up [1]": float(np.median(full_seconds) / np.median(seconds)),
                "offline build [s]": offline,
                "snapshots [s]": summary["offline_seconds"].get("snapshots", 0.0),
            }
            rows.append(row)
            say(f"size {reduced.size}: " + ", ".join(f"{k} {v:.3g}" for k, v in row.items()))
    if comm.rank == 0:
        write(rows, dofs, args, box, unseen, "rom_parameters_quick" if args.quick else "rom_parameters")


def write(rows: list[dict], dofs: int, args, box: Parameters, unseen: list[dict], stem: str) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    with open(RESULTS / f"{stem}.csv", "w", newline="") as stream:
        table = csv.DictWriter(stream, fieldnames=list(rows[0]))
        table.writeheader()
        table.writerows(rows)
    cpu, memory = cpu_and_memory()
    lines = [
        "# Reduced breathing lung over a 3-parameter box",
        "",
        f"Command: `python benchmarks/rom_parameters.py --train {args.train} --test {args.test} "
        f"--sizes {' '.join(map(str, args.sizes))}"
        + (f" --mesh-size {args.mesh_size}" if args.mesh_size != "default" else "")
        + f"` on {cpu}, {memory}, 1 rank. Full model: {dofs} dofs. "
        "Times are wall-clock times on the machine as it was (other jobs may have run beside): the errors "
        "are the result, the times an indication.",
        "",
        SAME_START,
        "",
        "Parameters: " + "; ".join(f"{p.name} = {p.target} in [{p.range[0]:g}, {p.range[1]:g}]" for p in box),
        "",
        "| " + " | ".join(rows[0]) + " |",
        "|" + "---|" * len(rows[0]),
    ]
    for row in rows:
        lines.append("| " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v) for v in row.values()) + " |")
    lines += ["", "Unseen points: " + "; ".join(", ".join(f"{k} {v:.4g}" for k, v in mu.items()) for mu in unseen)]
    (RESULTS / f"{stem}.md").write_text("\n".join(lines) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(6, 4))
    sizes = [row["basis size [1]"] for row in rows]
    axes.semilogy(sizes, [row["energy-norm error, max [1]"] for row in rows], "o-", label="state, energy norm (max)")
    axes.semilogy(
        sizes,
        [row["volume error / volume change, max [1]"] for row in rows],
        "s-",
        label="volume / volume change (max)",
    )
    axes.axhline(1e-3, color="grey", lw=0.8, ls="--", label="target of the state: 1e-3")
    axes.axhline(1e-4, color="grey", lw=0.8, ls=":", label="target of the volume: 1e-4")
    axes.set_xlabel("basis size k [1]")
    axes.set_ylabel("relative error over unseen points [1]")
    axes.set_title("Reduced lung over stiffness × breath × posture")
    axes.legend()
    figure.tight_layout()
    figure.savefig(RESULTS / f"{stem}.png", dpi=150)


if __name__ == "__main__":
    main()
