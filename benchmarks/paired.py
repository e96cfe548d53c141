"""lungmech's overhead measured in one process: lungmech and the hand-written script alternate.

    python benchmarks/paired.py                       # P1 h=0.1, P2 h=0.2, mixed h=0.2, 5 pairs each
    python benchmarks/paired.py --cases P2:0.15 --pairs 3
    python benchmarks/paired.py --quick               # P1 h=0.25, 2 pairs of 2 steps: overhead_paired_quick.*

run.py times each code in a process of its own (so that peak memory is per case); on a shared VM
the speed of a process drifts by ~10 % or more, which is as large as the overhead being measured.
Here both codes are set up on the same mesh in one process and their solves alternate (lungmech,
hand-written, lungmech, ...), each from the undeformed state, so drift hits both alike. Writes
benchmarks/results/overhead_paired.{md,csv,png} (the plot: each case's pair ratios) and prints the table.
"""

from __future__ import annotations

import argparse
import datetime
import statistics
import time

from mpi4py import MPI

import machine
from case import FORMULATIONS, lame
from handwritten import Problem

import lungmech  # noqa: F401
from lungmech.fem.constraints import symmetry
from lungmech.fem.loads import FollowerPressure
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.solver import NewtonOptions, NewtonSolver, Stepping, solve
from lungmech.mesh import sphere

RESULTS = machine.RESULTS


def measure(formulation: str, h: float, pairs: int, steps: int, line_search: str, nu: float, pressure: float) -> dict:
    comm = MPI.COMM_WORLD
    degree, mixed = FORMULATIONS[formulation]
    geometry = sphere(comm, 1.0, 2.0, mesh_size=h, octant=True, order=1 if degree == 1 else 2)
    model = Model(
        geometry,
        NeoHookean.from_young(2 * (1 + nu), nu),
        degree=degree,
        mixed=mixed,
        loads=[FollowerPressure("inner", pressure)],
        constraints=[symmetry("x0", "x"), symmetry("y0", "y"), symmetry("z0", "z")],
    )
    solver = NewtonSolver(model, NewtonOptions(linear_solver="direct", line_search=line_search))
    stepping = Stepping(initial_step=1.0 / steps, growth=1.0)
    hand = Problem(geometry, formulation, 1.0, lame(nu), pressure, line_search=line_search)
    lm, hw, its = [], [], set()
    for _ in range(pairs):
        model.state.x.array[:] = 0.0
        tic = time.perf_counter()
        report = solve(model, stepping, solver=solver)
        lm.append(comm.allreduce(time.perf_counter() - tic, op=MPI.MAX))
        hand.state.x.array[:] = 0.0
        tic = time.perf_counter()
        result = hand.solve(steps)
        hw.append(comm.allreduce(time.perf_counter() - tic, op=MPI.MAX))
        its.add((report.newton_iterations, len(report.accepted), result["iterations"]))
    space = model.space
    return {
        "formulation": formulation,
        "h": h,
        "dofs": space.dofmap.index_map.size_global * space.dofmap.index_map_bs,
        "iterations": sorted(its),
        "lm": lm,
        "hw": hw,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", default="P1:0.1,P2:0.2,mixed:0.2", help="formulation:h,...")
    parser.add_argument("--pairs", type=int, default=5)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--line-search", default="cp")
    parser.add_argument("--nu", type=float, default=0.4999)
    parser.add_argument("--pressure", type=float, default=0.2)
    parser.add_argument("--quick", action="store_true", help="P1 h=0.25, 2 pairs of 2 load steps (the suite's case)")
    args = parser.parse_args()
    if args.quick:
        args.cases, args.pairs, args.steps = "P1:0.25", 2, 2
    stem = "overhead_paired_quick" if args.quick else "overhead_paired"
    started = time.perf_counter()
    rows, table = [], []
    for case in args.cases.split(","):
        formulation, h = case.split(":")
        r = measure(formulation, float(h), args.pairs, args.steps, args.line_search, args.nu, args.pressure)
        ratios = [a / b for a, b in zip(r["lm"], r["hw"])]
        rows.append(
            f"| {formulation} | {h} | {r['dofs']} | {', '.join('/'.join(map(str, i)) for i in r['iterations'])} | "
            f"{min(r['lm']):.3f} | {min(r['hw']):.3f} | {min(r['lm']) / min(r['hw']):.3f} | "
            f"{statistics.median(r['lm']):.3f} | {statistics.median(r['hw']):.3f} | {statistics.median(ratios):.3f} | "
            f"{min(ratios):.3f}–{max(ratios):.3f} |"
        )
        print(rows[-1], flush=True)
        table.append(
            {"formulation": formulation, "h": float(h), "dofs": r["dofs"], "lungmech_min_s": min(r["lm"])}
            | {"handwritten_min_s": min(r["hw"]), "median_pair_ratio": statistics.median(ratios)}
            | {"pair_ratios": " ".join(f"{x:.4f}" for x in ratios)}
        )
    text = "\n".join(
        [
            "# lungmech overhead, paired in one process",
            "",
            f"- Date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}; {MPI.COMM_WORLD.size} rank(s); "
            f"{args.pairs} alternating solves per code (lungmech first), each from the undeformed state; "
            f"{args.steps} load steps, line search {args.line_search}; wall time {(time.perf_counter() - started) / 60:.1f} min.",
            "- its = lungmech Newton iterations / accepted load steps / hand-written Newton iterations.",
            "",
            "| formulation | h | dofs | its | lungmech min [s] | hand-written min [s] | ratio of mins | "
            "lungmech median [s] | hand-written median [s] | median of pair ratios | pair ratios, range |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
            *rows,
        ]
    )
    if MPI.COMM_WORLD.rank == 0:
        machine.write_results(RESULTS, stem, table, text + "\n")
        plot(table, RESULTS / f"{stem}.png")
        print()
        print(text)


def plot(table: list[dict], path) -> None:
    """Each case's pair ratios (lungmech / hand-written), and 1 (no overhead)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    for i, row in enumerate(table):
        ratios = [float(x) for x in row["pair_ratios"].split()]
        ax.plot([i] * len(ratios), ratios, "o", alpha=0.6)
        ax.plot([i - 0.2, i + 0.2], [row["median_pair_ratio"]] * 2, "k-")
    ax.axhline(1.0, color="grey", linestyle=":")
    ax.set_xticks(range(len(table)), [f"{r['formulation']}, h = {r['h']:g} m\n{r['dofs']} dofs" for r in table])
    ax.set_ylabel("lungmech / hand-written solve time [1]")
    ax.set_title("lungmech's overhead, paired solves in one process")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
