"""The breathing lung hyper-reduced (ECSW) against its full model, at several mesh sizes.

    python benchmarks/ecsw_lung.py                   # the bundled mesh, h = 10 and 8 mm (about 15 minutes)
    python benchmarks/ecsw_lung.py --sizes default   # the bundled mesh only
    python benchmarks/ecsw_lung.py --quick           # h = 40 mm (seconds; ecsw_lung_quick.*)

The bundled breathing scene (``lungmech/scenes/lung_breathing.toml``: the poromechanical right
lung imaged at end-expiration, its unloaded reference found first, a breath of pleural pressure
−500 → −1000 → −500 Pa and the weight balanced by the pleural pressure gradient), with 20 output
times over the breath (every 0.1 s) and the mesh size h of its phantom. Offline: ``lungmech rom
build --scales 0.5,1.5 --size 12 --hyper ecsw`` (τ = 1e-4): the full breaths at load scales 0.5
and 1.5, their POD, a second pass sampling every Newton iterate. Online, the unseen breath at
scale 1 (the scene itself): the hyper-reduced model's ``solve()``, loaded on its sampled cells
alone as ``lungmech rom solve`` loads it (warm median of three: forms compiled; the answer is
the outputs at the 20 times, from reduced operators; the state's error from the same model
loaded with its fields), against the full model's solve of the same breath from the same start on the same
rank. Errors against the full model: the state in the energy norm relative to the breath's
largest change, the volume, the volume change, the strain energy and the probes.

Writes results/ecsw_lung.md, results/ecsw_lung.csv and results/ecsw_lung.png.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import machine
import numpy as np
from machine import SAME_START, provenance, time_against_dofs, write_results

import lungmech  # noqa: F401  (before dolfinx: it loads the MPI library dolfinx's bindings need)
from lungmech.app import scene as scenes
from lungmech.app.reduce import build, load
from lungmech.app.run import full_order_model
from lungmech.rom.reductor import errors

SCENE = Path(lungmech.__file__).parent / "scenes" / "lung_breathing.toml"
RESULTS = machine.RESULTS
TOLERANCE, SIZE, SCALES = 1e-4, 12, (0.5, 1.5)
TIMES = [round(0.1 * i, 1) for i in range(1, 20)]  # with the end: 20 outputs


def scene_at(size: str, folder: Path) -> Path:
    """The bundled scene with 20 output times and, unless ``size`` is "default", mesh size h mm."""
    text = SCENE.read_text()
    if size != "default":
        text = text.replace('side = "right"', f'side = "right"\nmesh_size = {float(size) / 1e3}')
    text = text.replace("[stepping]\n", f"[stepping]\ntimes = {TIMES}\n").replace("fields = true", "fields = false")
    path = folder / f"lung_{size}.toml"
    path.write_text(text)
    return path


def case(size: str, folder: Path) -> dict:
    scene = scenes.load(scene_at(size, folder))
    tic = time.perf_counter()
    summary = build(
        scene, folder / f"lung_{size}.npz", size=SIZE, scales=SCALES, hyper="ecsw", hyper_tolerance=TOLERANCE
    )
    offline = time.perf_counter() - tic
    reduced = load(folder / f"lung_{size}.npz")
    seconds = []
    for _ in range(3):
        tic = time.perf_counter()
        approximate = reduced.solve()
        seconds.append(time.perf_counter() - tic)
    full = full_order_model(scene, start="defaults")  # the defaults' reference moved to μ, as its greedy trains
    tic = time.perf_counter()
    exact = full.solve()
    full_seconds = time.perf_counter() - tic
    # the state's error needs the full mesh: the same model with its fields (its answers are the
    # body's, tests/test_reduced_body.py)
    with_fields = load(folder / f"lung_{size}.npz", fields=True)
    measured = errors(with_fields, exact, with_fields.solve())
    probes = float(np.abs(approximate.outputs["probes"] - exact.outputs["probes"]).max())
    hyper = summary["hyper"]
    cells = hyper["cells"]
    sampled = sum(hyper["samples"].values())
    return {
        "mesh": size,
        "dofs": summary["dofs"],
        "cells": cells,
        "basis": summary["size"],
        "outputs": len(approximate.times),
        **{f"sampled_{name}": n for name, n in hyper["samples"].items()},
        "sampled_percent": 100.0 * sampled / cells,
        "online_ms": 1e3 * statistics.median(seconds),
        "online_newton": approximate.newton_iterations,
        "full_ms": 1e3 * full_seconds,
        "full_newton": exact.newton_iterations,
        "speed_up": full_seconds / statistics.median(seconds),
        "error_energy": measured.energy,
        "error_volume": measured.volume,
        "error_volume_change": measured.volume_change,
        "error_strain_energy": measured.strain_energy,
        "error_probes_m": probes,
        "offline_s": offline,
        **{f"offline_{name}_s": value for name, value in summary["offline_seconds"].items()},
    }


def markdown(rows: list[dict], command: str) -> str:
    lines = [
        "# The breathing lung, hyper-reduced (ECSW) against its full model",
        "",
        f"{provenance(command)} POD of at most {SIZE} vectors of the breaths at load scales "
        f"{', '.join(map(str, SCALES))}; ECSW at τ = {TOLERANCE:g} on every Newton iterate; online: the unseen "
        f"breath at scale 1, {rows[0]['outputs']} outputs, warm median of three.",
        "",
        SAME_START,
        "",
        "| mesh h [mm] | dofs | cells | k | sampled cells (% of the mesh) | online [ms] | full [ms] | speed-up | "
        "error: state (energy), volume, volume change, strain energy | probes [m] | offline [s] |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        sampled = sum(v for k, v in r.items() if k.startswith("sampled_") and k != "sampled_percent")
        lines.append(
            f"| {r['mesh']} | {r['dofs']} | {r['cells']} | {r['basis']} | {sampled} ({r['sampled_percent']:.2f} %) | "
            f"{r['online_ms']:.1f} | {r['full_ms']:.0f} | {r['speed_up']:.0f}× | {r['error_energy']:.1e}, "
            f"{r['error_volume']:.1e}, {r['error_volume_change']:.1e}, {r['error_strain_energy']:.1e} | "
            f"{r['error_probes_m']:.1e} | {r['offline_s']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="default,10,8", help="mesh sizes h in mm, or 'default' (comma-separated)")
    parser.add_argument("--quick", action="store_true", help="smoke run: h = 40 mm (results ecsw_lung_quick.*)")
    args = parser.parse_args()
    if args.quick:
        args.sizes = "40"
    stem = "ecsw_lung_quick" if args.quick else "ecsw_lung"
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for size in args.sizes.split(","):
            rows.append(case(size.strip(), Path(folder)))
            r = rows[-1]
            print(f"{r['dofs']} dofs: online {r['online_ms']:.1f} ms, full {r['full_ms']:.0f} ms", flush=True)
    command = "python benchmarks/ecsw_lung.py" + (
        " --quick" if args.quick else f" --sizes {args.sizes}" if args.sizes != "default,10,8" else ""
    )
    write_results(RESULTS, stem, rows, markdown(rows, command))
    time_against_dofs(
        rows,
        [("full_ms", "full model"), ("online_ms", f"hyper-reduced (ECSW, τ = {TOLERANCE:g})")],
        f"one breath, {rows[0]['outputs']} outputs [ms]",
        "Breathing lung (poromechanics, balanced gravity): online time",
        RESULTS / f"{stem}.png",
    )
    print((RESULTS / f"{stem}.md").read_text())


if __name__ == "__main__":
    main()
