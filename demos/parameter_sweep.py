"""A parameter sweep of the breathing lung: skeleton stiffness × pleural pressure, one compilation.

The bundled breathing scene (lungmech/scenes/lung_breathing.toml), without the tissue's weight,
gets two parameters:
``stiffness`` (the skeleton's c1, Pa) and ``pleural`` (the pleural pressure at end-expiration,
Pa; the breath doubles it). The demo solves the 3 × 3 grid of them through Python — one
FullOrderModel, whose forms are compiled once; the sweep counts FFCx calls and finds none — and
prints the tidal volume (end-inspiration minus end-expiration volume, litres) of each point. The
mesh is the lung imaged at end-expiration *at every point*: each solve finds the unloaded reference
for its own stiffness and pressure (the scene's [inverse]; ``lungmech run --set`` solves the same
problem). With ``--cli`` it runs the same grid through ``lungmech run SCENE --set ...`` in fresh
processes sharing a new FFCx cache and prints the compiled forms in the cache after each run: only
the first run adds any.
Writes parameter_sweep.png (tidal volume against stiffness, one curve per pleural pressure).

    python demos/parameter_sweep.py [-o demos/output/parameter_sweep] [--cli]
"""

import argparse
import copy
import os
import subprocess
import sys
import tempfile
import tomllib
from importlib import resources
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
from mpi4py import MPI

import matplotlib.pyplot as plt
import numpy as np

from lungmech.app import scene as scenes
from lungmech.app.run import full_order_model
from lungmech.parallel import on_root
from lungmech.parallel.destination import output_folder

STIFFNESS = (100.0, 200.0, 400.0)  # Pa, c1 of the skeleton
PLEURAL = (-300.0, -500.0, -700.0)  # Pa at end-expiration


def scene_table() -> dict:
    with resources.as_file(resources.files("lungmech.scenes") / "lung_breathing.toml") as path:
        table = copy.deepcopy(tomllib.loads(Path(path).read_text()))
    table["loads"][0]["name"] = "pleural"
    # Without the tissue's weight: balancing it costs a fixed point of Newton solves per step (until
    # the coefficients join the Newton solve), and the sweep is about stiffness and pressure.
    table["loads"] = [load for load in table["loads"] if load["type"] != "gravity"]
    table["parameters"] = {
        "stiffness": {"target": "material.c1", "range": [50.0, 800.0], "scale": "log"},
        "pleural": {"target": "loads.pleural.value", "range": [-1000.0, -200.0]},
    }
    table["output"] = {"fields": False}
    return table


def python_sweep(comm) -> tuple[np.ndarray, int]:
    """Tidal volumes (L) on the grid, and the FFCx calls the sweep made after the first build."""
    import dolfinx.jit  # after lungmech, which orders MPI before DOLFINx's bindings

    full = full_order_model(scenes.parse(scene_table()), comm)
    calls = []
    original = dolfinx.jit.ffcx_jit
    dolfinx.jit.ffcx_jit = lambda *args, **kwargs: calls.append(1) or original(*args, **kwargs)
    try:
        tidal = np.zeros((len(PLEURAL), len(STIFFNESS)))
        for i, pleural in enumerate(PLEURAL):
            for j, stiffness in enumerate(STIFFNESS):
                solution = full.solve({"stiffness": stiffness, "pleural": pleural})
                volume = dict(zip(solution.times, solution.outputs["volume"]))
                tidal[i, j] = (volume[1.0] - volume[2.0]) * 1e3  # t = 1: end-inspiration, 2: end-expiration
    finally:
        dolfinx.jit.ffcx_jit = original
    return tidal, len(calls)


def cli_sweep(folder: Path) -> list[int]:
    """The grid through ``lungmech run --set`` in fresh processes: compiled forms in a new FFCx
    cache after each run."""
    scene = folder / "lung_sweep.toml"
    scene.write_text(_toml(scene_table()))
    cache = Path(tempfile.mkdtemp(prefix="lungmech-ffcx-"))
    environment = os.environ | {"XDG_CACHE_HOME": str(cache)}
    counts = []
    for pleural in PLEURAL:
        for stiffness in STIFFNESS:
            command = [
                sys.executable,
                "-m",
                "lungmech.app.cli",
                "run",
                str(scene),
                "-q",
                "-o",
                str(folder / f"run_{stiffness:g}_{pleural:g}"),
                "--set",
                f"stiffness={stiffness}",
                "--set",
                f"pleural={pleural}",
            ]
            subprocess.run(command, check=True, env=environment, stdout=subprocess.DEVNULL)
            counts.append(sum(1 for _ in cache.rglob("*.so")))
    return counts


def _toml(table: dict) -> str:
    """A small TOML writer for the scene (tomllib reads only)."""

    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{" + ", ".join(f"{k} = {value(x)}" for k, x in v.items()) + "}"
        return repr(v)

    lines = [f"title = {value(table.get('title', ''))}"]
    for key, section in table.items():
        if isinstance(section, dict) and key != "parameters":
            lines += [f"[{key}]", *(f"{k} = {value(v)}" for k, v in section.items())]
        elif isinstance(section, list):
            for entry in section:
                lines += [f"[[{key}]]", *(f"{k} = {value(v)}" for k, v in entry.items())]
    for name, entry in table.get("parameters", {}).items():
        lines += [f"[parameters.{name}]", *(f"{k} = {value(v)}" for k, v in entry.items())]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "-o",
        "--output",
        type=Path,
        default=Path(__file__).resolve().parent / "output" / "parameter_sweep",
        help="output folder (staged; replaced only on success, and only if it is empty or lungmech's own)",
    )
    parser.add_argument("--cli", action="store_true", help="also sweep through 'lungmech run --set'")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    with output_folder(args.output, comm, inputs=[], command="demos/parameter_sweep.py") as folder:
        tidal, calls = python_sweep(comm)
        if comm.rank == 0:
            print("tidal volume [L] (rows: pleural pressure at end-expiration [Pa]; columns: c1 [Pa])")
            print("          " + "".join(f"{s:>10g}" for s in STIFFNESS))
            for pleural, row in zip(PLEURAL, tidal):
                print(f"{pleural:>10g}" + "".join(f"{v:>10.4f}" for v in row))
            print(f"FFCx calls during the 9-point Python sweep: {calls}")
        on_root(comm, lambda: _picture(tidal, folder / "parameter_sweep.png"))
        if args.cli and comm.rank == 0:
            counts = cli_sweep(folder)
            print(f"compiled forms in the fresh FFCx cache after each of the 9 CLI runs: {counts}")


def _picture(tidal: np.ndarray, path: Path) -> None:
    figure, axes = plt.subplots(figsize=(5.5, 4))
    for pleural, row in zip(PLEURAL, tidal):
        axes.plot(STIFFNESS, row, "o-", label=f"{pleural:g} Pa → {2 * pleural:g} Pa")
    axes.set_xscale("log")
    axes.set_xticks(STIFFNESS, [f"{s:g}" for s in STIFFNESS])
    axes.minorticks_off()
    axes.set_ylim(0.0, 1.05 * tidal.max())
    axes.set_xlabel("skeleton stiffness c1 [Pa]")
    axes.set_ylabel("tidal volume [L]")
    axes.set_title("Right lung phantom, imaged at end-expiration: tidal volume of one breath", fontsize=10)
    axes.legend(title="pleural pressure, expiration → inspiration", fontsize=8, title_fontsize=8, loc="lower left")
    figure.tight_layout()
    figure.savefig(path, dpi=150)


if __name__ == "__main__":
    main()
