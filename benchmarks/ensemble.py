"""Many full solves at once: the ensemble layer's throughput on this machine.

    python benchmarks/ensemble.py            # the bundled imaged lung at its mesh, 16 points (minutes)
    python benchmarks/ensemble.py --quick    # the same lung remeshed 2× coarser, 4 points (about a minute)

The same N full solves (static, at end-inspiration, of the imaged lung over its 3-parameter box:
``lungmech.app.answers.solved`` on seeded Sobol' points) run three ways, each into a cache of its
own so that every answer is solved:

* serially, in this process on one rank (:class:`~lungmech.parallel.ensemble.Serial`);
* in 2 groups of 1 rank inside one ``mpiexec -n 2`` (:class:`~lungmech.parallel.ensemble.Groups`;
  this script started under mpiexec);
* on Parsl's 2 local workers of 1 rank (:func:`lungmech.parallel.engine.local_pool`).

Per mode: the wall time of ``map`` (the engine's start-up apart), the solves per minute, the
parallel efficiency T_serial / (2 T) on the 2 cores, and whether the answers equal the serial ones
bit for bit. Writes results/ensemble{,_quick}.{md,csv,png}.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from functools import partial
from importlib import resources
from pathlib import Path

import machine
from machine import provenance, say, write_results

SCENE = "lung_breathing_parameters.toml"


def tasks(level: int, count: int) -> list:
    """``count`` static solves of the bundled lung at mesh ``level`` (−1: remeshed 2× coarser)."""
    from lungmech.app import scene as scenes
    from lungmech.app.answers import Task
    from lungmech.app.ladder import Discretisation
    from lungmech.app.trade import peak_time
    from lungmech.fem.parameters import Parameters
    from lungmech.trade.points import validation_points

    with resources.as_file(resources.files("lungmech.scenes") / SCENE) as path:
        scene = scenes.load(path)
        points = validation_points(Parameters(scene.parameters), count, seed=7).points[:count]
        return [Task(str(path), point, Discretisation(level, 1), (peak_time(scene),)) for point in points]


def timed(ensemble, work: list, cache: Path) -> tuple[float, list]:
    """The wall time of the ensemble's ``map`` over ``work``, and its outcomes."""
    from lungmech.app import answers

    began = time.perf_counter()
    found = ensemble.map(partial(answers.solved, cache=str(cache)), work)
    answers.forget()
    return time.perf_counter() - began, found


def groups_part(args: argparse.Namespace) -> None:
    """Under ``mpiexec -n 2``: the tasks in 2 groups of 1 rank; rank 0 writes the time and volumes."""
    from mpi4py import MPI

    from lungmech.parallel.ensemble import Groups

    groups = Groups(1, MPI.COMM_WORLD)
    seconds, found = timed(groups, tasks(args.level, args.points), Path(args.cache))
    groups.free()
    if MPI.COMM_WORLD.rank == 0:
        Path(args.groups_part).write_text(json.dumps({"seconds": seconds, "volumes": _volumes(found)}))


def _volumes(found: list) -> list:
    return [None if o.value is None or o.value["failed"] else o.value["volume"] for o in found]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="2× coarser mesh, 4 points")
    parser.add_argument("--points", type=int, default=None, help="solves (default 16; 4 with --quick)")
    parser.add_argument("--groups-part", help=argparse.SUPPRESS)
    parser.add_argument("--cache", help=argparse.SUPPRESS)
    parser.add_argument("--level", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    args.points = args.points or (4 if args.quick else 16)
    args.level = args.level if args.level is not None else (-1 if args.quick else 0)
    if args.groups_part:
        groups_part(args)
        return
    from mpi4py import MPI

    from lungmech.parallel.engine import local_pool
    from lungmech.parallel.ensemble import Serial

    work = tasks(args.level, args.points)
    mesh = "remeshed 2× coarser (2h)" if args.level < 0 else "at its own mesh (h)"
    rows = []
    with tempfile.TemporaryDirectory(prefix="lungmech-ensemble-") as folder:
        say("serial")
        serial_seconds, serial = timed(Serial(MPI.COMM_SELF), work, Path(folder) / "serial")
        reference = _volumes(serial)
        rows.append(_row("serial, 1 rank", serial_seconds, serial_seconds, len(work), reference, reference))
        say("2 groups of 1 rank")
        told = Path(folder) / "groups.json"
        mpiexec = Path(sys.executable).parent / "mpiexec"
        command = [str(mpiexec if mpiexec.exists() else "mpiexec"), "-n", "2", sys.executable, __file__]
        command += ["--groups-part", str(told), "--cache", str(Path(folder) / "groups"), "--level", str(args.level)]
        subprocess.run(command + ["--points", str(args.points)], check=True, env=os.environ)
        parted = json.loads(told.read_text())
        rows.append(
            _row(
                "2 groups of 1 rank (mpiexec -n 2)",
                parted["seconds"],
                serial_seconds,
                len(work),
                parted["volumes"],
                reference,
            )
        )
        say("Parsl, 2 workers of 1 rank")
        began = time.perf_counter()
        with local_pool(2, 1) as pool:
            start_up = time.perf_counter() - began
            seconds, found = timed(pool, work, Path(folder) / "parsl")
        rows.append(
            _row("Parsl, 2 local workers of 1 rank", seconds, serial_seconds, len(work), _volumes(found), reference)
            | {"engine start-up [s]": start_up}
        )
    command = "python benchmarks/ensemble.py" + (" --quick" if args.quick else "")
    dofs = serial[0].value["dofs"] if serial[0].value else None
    markdown = "\n".join(
        [
            "# Many full solves at once: the ensemble's throughput",
            "",
            provenance(command, "1 and 2 ranks on the machine's 2 cores"),
            "",
            f"{len(work)} static solves (end-inspiration) of the bundled imaged lung {mesh}, {dofs} dofs, over its "
            "3-parameter box (stiffness, breath depth, posture), each mode into a cache of its own. Efficiency: "
            "T_serial / (2 T) on 2 cores.",
            "",
            "| mode | wall [s] | solves per minute | speed-up [-] | parallel efficiency [-] | answers as serial |",
            "|---|---|---|---|---|---|",
            *(
                f"| {r['mode']} | {r['wall [s]']:.1f} | {r['solves per minute']:.2f} | {r['speed-up [-]']:.2f} | "
                f"{r['parallel efficiency [-]']:.2f} | {r['answers as serial']} |"
                for r in rows
            ),
            "",
            f"Parsl's start-up, apart from its wall time: {rows[-1]['engine start-up [s]']:.1f} s. A one-rank task "
            "runs in its Parsl worker, and a group solves in its own ranks: each keeps its last model for its "
            "next task.",
            "",
        ]
    )
    stem = "ensemble_quick" if args.quick else "ensemble"
    write_results(machine.RESULTS, stem, rows, markdown)
    _plot(rows, machine.RESULTS / f"{stem}.png", f"{len(work)} full solves of the imaged lung {mesh}")
    print(markdown)


def _row(mode: str, seconds: float, serial: float, count: int, volumes: list, reference: list) -> dict:
    same = "bitwise" if volumes == reference else "differ"
    return {
        "mode": mode,
        "wall [s]": seconds,
        "solves per minute": 60.0 * count / seconds,
        "speed-up [-]": serial / seconds,
        "parallel efficiency [-]": serial / seconds / (1 if mode.startswith("serial") else 2),
        "answers as serial": same,
    }


def _plot(rows: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.6))
    names = [r["mode"] for r in rows]
    bars = ax.barh(names, [r["solves per minute"] for r in rows], color=["0.6", "tab:blue", "tab:green"])
    for bar, row in zip(bars, rows):
        ax.text(
            bar.get_width(),
            bar.get_y() + bar.get_height() / 2,
            f"  ×{row['speed-up [-]']:.2f}",
            va="center",
            fontsize=8,
        )
    ax.set_xlabel("full solves per minute [1/min]")
    ax.invert_yaxis()
    ax.set_title(title, fontsize=9)
    ax.margins(x=0.15)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
