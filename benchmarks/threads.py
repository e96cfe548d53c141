"""One BLAS thread, or the machine's: an offline build, quiet and under a background load.

    python benchmarks/threads.py            # the bundled imaged lung's ECSW build, 2 training points (about 6 min)
    python benchmarks/threads.py --quick    # the sphere octant's, under a load of 1 (under a minute)

On a shared machine other jobs hold the cores. NumPy's OpenBLAS starts a thread per core, and
threads that spin-wait for cores another load holds cost far more than a second thread gives
(issue 31: the bundled lung's build took 124 s quiet and 1684 s at a load of 2–8). A CLI command
now caps its BLAS threads to one unless the user set ``OPENBLAS_NUM_THREADS``
(:func:`lungmech._threads.cap_threads`). This measures that choice: the same
``lungmech rom build … --hyper ecsw`` four times — capped (the default) and with the machine's
threads (``OPENBLAS_NUM_THREADS`` = its cores), each quiet and under a background load of busy
processes (``--load``, default 4) — and reports each build's wall time, its parts (the ECSW
training, compression and NNLS: the dense algebra) and its ratio loaded / quiet. Target: capped,
≤ 3×. Writes results/threads{,_quick}.{md,csv,png}.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import machine
from machine import provenance, say, write_results

PARTS = ("ecsw_training", "ecsw_compression", "nnls")  # where the build's dense algebra is


def busy(_: int) -> None:
    """A background job: one core's worth of work, forever (until terminated)."""
    while True:
        pass


def build(scene: str, samples: int, threads: int | None, folder: Path) -> dict:
    """One ``rom build`` of ``scene`` in a fresh process (``threads``: OPENBLAS_NUM_THREADS, None:
    lungmech's default): its wall time and its parts' seconds."""
    from lungmech.rom import store

    env = dict(os.environ)
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env.pop(name, None)
    if threads is not None:
        env["OPENBLAS_NUM_THREADS"] = str(threads)
    model = folder / f"model-{time.monotonic_ns()}.npz"
    lungmech = Path(sys.executable).parent / "lungmech"  # the console script beside this Python
    command = [str(lungmech), "rom", "build", scene, "--samples", str(samples)]
    command += ["--hyper", "ecsw", "-o", str(model), "-q", "--cache", str(folder / f"cache-{model.stem}")]
    began = time.perf_counter()
    subprocess.run(command, check=True, env=env, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - began
    seconds = store.read(model, arrays=False)[0]["extra"]["offline_seconds"]
    return {"wall [s]": wall} | {f"{part} [s]": float(seconds.get(part, 0.0)) for part in PARTS}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="the sphere octant under a load of 1")
    parser.add_argument("--load", type=int, default=None, help="busy background processes (default 4; 1 with --quick)")
    args = parser.parse_args()
    load = args.load if args.load is not None else (1 if args.quick else 4)
    scene = "sphere_inflation_parameters" if args.quick else "lung_breathing_parameters"
    samples = 2
    cores = os.cpu_count() or 1
    rows = []
    with tempfile.TemporaryDirectory(prefix="lungmech-threads-") as folder:
        for threads, name in ((None, "1 (lungmech's default)"), (cores, f"{cores} (the machine's cores)")):
            say(f"{name}: quiet")
            quiet = build(scene, samples, threads, Path(folder))
            say(f"{name}: under a load of {load}")
            with multiprocessing.get_context("spawn").Pool(load) as pool:
                pool.map_async(busy, range(load))
                time.sleep(1.0)  # the load running before the build starts
                loaded = build(scene, samples, threads, Path(folder))
                pool.terminate()
            for condition, found in (("quiet", quiet), (f"load {load}", loaded)):
                rows.append({"BLAS threads": name, "condition": condition} | found)
            rows[-1]["loaded / quiet [-]"] = loaded["wall [s]"] / quiet["wall [s]"]
    command = "python benchmarks/threads.py" + (" --quick" if args.quick else "")
    what = "the sphere octant" if args.quick else "the bundled imaged lung"
    capped = rows[1]["loaded / quiet [-]"]
    markdown = "\n".join(
        [
            "# BLAS threads: a build quiet and under a background load",
            "",
            provenance(command, f"one rank on the machine's {cores} cores"),
            "",
            f"`lungmech rom build {scene} --samples {samples} --hyper ecsw` ({what}), each in a fresh process, "
            f"quiet and under {load} busy background process{'es' * (load > 1)}; the parts are the build's own timings.",
            "",
            "| BLAS threads | condition | wall [s] | ECSW training [s] | of it compression [s] | NNLS [s] | loaded / quiet [-] |",
            "|---|---|---|---|---|---|---|",
            *(
                f"| {r['BLAS threads']} | {r['condition']} | {r['wall [s]']:.1f} | {r['ecsw_training [s]']:.1f} | "
                f"{r['ecsw_compression [s]']:.1f} | {r['nnls [s]']:.2f} | "
                + (f"{r['loaded / quiet [-]']:.2f} |" if "loaded / quiet [-]" in r else " |")
                for r in rows
            ),
            "",
            f"Capped to one thread, the build under the load takes {capped:.2f}× its quiet time "
            f"(target ≤ 3×); with {cores} threads {rows[3]['loaded / quiet [-]']:.2f}×.",
            "",
        ]
    )
    stem = "threads_quick" if args.quick else "threads"
    write_results(machine.RESULTS, stem, rows, markdown)
    _plot(rows, machine.RESULTS / f"{stem}.png", f"{what}'s ECSW build, quiet and under a load of {load}")
    print(markdown)


def _plot(rows: list[dict], path: Path, title: str) -> None:
    labels = [
        f"{r['BLAS threads'].split(' ')[0]} BLAS thread{'s' * (r['BLAS threads'][0] != '1')}, {r['condition']}"
        for r in rows
    ]
    parts = {  # the compression is a part of the ECSW training: drawn apart, not twice
        "ECSW training, but its compression": (
            [r["ecsw_training [s]"] - r["ecsw_compression [s]"] for r in rows],
            "tab:blue",
        ),
        "ECSW compression": ([r["ecsw_compression [s]"] for r in rows], "tab:orange"),
        "NNLS": ([r["nnls [s]"] for r in rows], "tab:red"),
        "full solves and the rest": ([r["wall [s]"] - r["ecsw_training [s]"] - r["nnls [s]"] for r in rows], "0.7"),
    }
    ratio = [r.get("loaded / quiet [-]") for r in rows]
    notes = ["" if x is None else f"×{x:.2f} of quiet" for x in ratio]
    machine.stacked_bars(labels, parts, notes, "wall time of the build [s]", title, path)


if __name__ == "__main__":
    main()
