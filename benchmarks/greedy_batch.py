"""A greedy that adds B full solves a round, solved at once, against the one-point greedy.

    python benchmarks/greedy_batch.py           # the bundled lung from its unloaded mesh, 12 candidates (about 30 min)
    python benchmarks/greedy_batch.py --quick   # the sphere octant over its stiffness (under a minute)

The weak greedy (:mod:`lungmech.rom.greedy`) judges every candidate with the reduced model of
each round, then solves the full model where the indicator is largest. With ``batch`` B it
solves the B largest at once — on an ensemble's workers, in parallel — so the training needs
about B times fewer rounds of judging and its full solves overlap. The price: a batch's points
are chosen by one basis, so the basis may need a solve or two more for the same tolerance.

Three trainings of the same POD Galerkin model to the same tolerance (relative energy-norm
error, judged by the indicator with its safety factor) over the same seeded Sobol' candidates:
B = 1 in this process, B = 2 in this process (fewer rounds), and B = 2 on Parsl's 2 local workers
(:mod:`lungmech.app.training_paths`: fewer rounds and 2 solves at once). Each into a cache of its
own (every path solved). Per training: full solves, rounds, basis size, the tolerance met, the
offline wall time and its parts (full solves, judging), and the true error of the model at
held-out points (the full model solved there: max relative energy-norm error along the path,
:func:`lungmech.rom.accuracy.errors`). The lung is the bundled breathing lung
(``lung_breathing_parameters``) over stiffness × breath depth × posture, its mesh taken as the
unloaded lung (the scene without [inverse]: the greedy trains models of one start state; an
imaged body's training is not greedy yet). Writes results/greedy_batch{,_quick}.{md,csv,png}.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from importlib import resources
from pathlib import Path

import machine
from machine import provenance, say, write_results


def scene_file(quick: bool, folder: Path) -> Path:
    """The scene trained on: the sphere octant, or the bundled lung without [inverse]."""
    bundled = resources.files("lungmech.scenes")
    if quick:
        return Path(str(bundled / "sphere_inflation_parameters.toml"))
    text = (bundled / "lung_breathing_parameters.toml").read_text()
    start, end = text.index("\n[inverse]\n"), text.index("\n[stepping]\n")
    path = folder / "lung_unloaded_parameters.toml"
    path.write_text(text[:start] + text[end:])
    return path


def trained(full, where, scene: Path, candidates: list, tolerance: float, batch: int, ensemble, cache: Path):
    """The POD Galerkin model of one greedy training, and its offline wall time."""
    from lungmech.app import scene as scenes
    from lungmech.app.training_paths import EnsemblePaths
    from lungmech.rom.reductor import POD, Reductor, TrainingSet

    began = time.perf_counter()
    paths = EnsemblePaths(scenes.load(scene), full, where, ensemble, str(cache))
    with Reductor(full, POD(40), TrainingSet(candidates, tolerance=tolerance, batch=batch), paths=paths) as made:
        reduced = made.reduce()
    return reduced, time.perf_counter() - began


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="the sphere octant, 8 candidates")
    args = parser.parse_args()
    from mpi4py import MPI

    from lungmech._threads import cap_threads

    cap_threads()  # one BLAS thread, as a lungmech command and each worker have

    from lungmech.app import scene as scenes
    from lungmech.app.training_paths import training_model
    from lungmech.fem.parameters import Parameters
    from lungmech.parallel.engine import local_pool
    from lungmech.parallel.ensemble import Serial
    from lungmech.rom.accuracy import errors

    tolerance, count, held_out = (1e-6, 8, 3) if args.quick else (1e-2, 12, 4)
    rows = []
    with tempfile.TemporaryDirectory(prefix="lungmech-greedy-") as folder:
        scene = scene_file(args.quick, Path(folder))
        box = Parameters(scenes.load(scene).parameters)
        candidates, tests = box.sample(count, seed=0), box.sample(held_out, seed=99)
        full, where = training_model(scenes.load(scene), MPI.COMM_SELF)
        say(f"the full model at {held_out} held-out points")
        truths = [full.solve(point) for point in tests]
        full.reset()
        dofs = full.model.space.dofmap.index_map.size_global * full.model.space.dofmap.index_map_bs
        modes = [("B = 1, serial", 1, None), ("B = 2, serial", 2, None), ("B = 2, Parsl 2 workers", 2, "parsl")]
        for name, batch, engine in modes:
            say(name)
            cache = Path(folder) / f"cache-{len(rows)}"
            if engine:
                with local_pool(2, 1) as pool:
                    reduced, wall = trained(full, where, scene, candidates, tolerance, batch, pool, cache)
            else:
                serial = Serial(MPI.COMM_SELF)
                reduced, wall = trained(full, where, scene, candidates, tolerance, batch, serial, cache)
            record, timings = reduced.built["greedy"], reduced.built["timings"]
            measured = [errors(reduced, truth, reduced.solve(point)).energy for point, truth in zip(tests, truths)]
            rows.append(
                {
                    "training": name,
                    "batch": batch,
                    "full solves": record["full_solves"],
                    "rounds": _rounds(record, batch),
                    "basis size": reduced.size,
                    "met": record["met"],
                    "indicator × safety [-]": (record["rounds"][-1]["indicator"] or float("inf")) * record["safety"],
                    "held-out error max [-]": max(measured),
                    "offline [s]": wall,
                    "full solves [s]": timings.get("snapshots", 0.0),
                    "judging [s]": timings.get("judging", 0.0),
                }
            )
    base = rows[0]["offline [s]"]
    for row in rows:
        row["speed-up [-]"] = base / row["offline [s]"]
    command = "python benchmarks/greedy_batch.py" + (" --quick" if args.quick else "")
    what = "the sphere octant over its stiffness" if args.quick else "the bundled lung from its unloaded mesh"
    markdown = "\n".join(
        [
            "# A batch greedy against the one-point greedy",
            "",
            provenance(command, "one rank, and Parsl's 2 workers of one rank, on the machine's 2 cores"),
            "",
            f"POD Galerkin models of {what} ({dofs} dofs), trained to {tolerance:g} (relative energy-norm error, "
            f"the indicator × its safety factor) over {count} seeded Sobol' candidates; true errors at {held_out} "
            "held-out points (the full model solved there). Each training solves every path (a cache of its own).",
            "",
            "| training | full solves | rounds | basis size | met | indicator × safety [-] | held-out error max [-] "
            "| offline [s] | of it full solves [s] | of it judging [s] | speed-up [-] |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
            *(
                f"| {r['training']} | {r['full solves']} | {r['rounds']} | {r['basis size']} | {r['met']} | "
                f"{r['indicator × safety [-]']:.2e} | {r['held-out error max [-]']:.2e} | {r['offline [s]']:.1f} | "
                f"{r['full solves [s]']:.1f} | {r['judging [s]']:.1f} | {r['speed-up [-]']:.2f} |"
                for r in rows
            ),
            "",
            "Speed-up: the one-point greedy's offline time over each training's. Rounds: the reduced models "
            "that judged the candidates (the last one ended the training). Met: the largest indicator × safety "
            "over the candidates and the last model's own training points (its basis truncated, it is judged "
            "there too) is below the tolerance.",
            "",
        ]
    )
    stem = "greedy_batch_quick" if args.quick else "greedy_batch"
    write_results(machine.RESULTS, stem, rows, markdown)
    _plot(rows, machine.RESULTS / f"{stem}.png", f"greedy training of {what} to {tolerance:g}")
    print(markdown)


def _rounds(record: dict, batch: int) -> int:
    """The judging rounds of a greedy's record: a batch's solves shared one; the last ended it."""
    solved = record["full_solves"] - 1  # the defaults' path came before any round
    return -(-solved // batch) + 1


def _plot(rows: list[dict], path: Path, title: str) -> None:
    solves = [r["full solves [s]"] for r in rows]
    judging = [r["judging [s]"] for r in rows]
    parts = {
        "full solves": (solves, "tab:blue"),
        "judging (reduced solves)": (judging, "tab:orange"),
        "POD and the rest": ([r["offline [s]"] - a - b for r, a, b in zip(rows, solves, judging)], "0.7"),
    }
    notes = [
        f"×{r['speed-up [-]']:.2f}; {r['full solves']} solves, error {r['held-out error max [-]']:.1e}" for r in rows
    ]
    machine.stacked_bars([r["training"] for r in rows], parts, notes, "offline wall time [s]", title, path)


if __name__ == "__main__":
    main()
