"""A large lung: one breathing step of the P1 poromechanical lung, iterative against direct.

    python benchmarks/large_lung.py                       # h = 8, 5, 3.2 mm on 2 ranks (about 20 min)
    python benchmarks/large_lung.py --sizes 8 --ranks 1   # one small case
    python benchmarks/large_lung.py --quick               # h = 14 mm on 1 rank (seconds): large_lung_quick.*

The right lung phantom (`lung_phantom`, mesh size h), P1 displacement and cellwise Φs, the hilum
clamped, from its reference: a pleural pressure of −50 Pa (0.5 cmH2O, a breathing step) on the
pleura, diaphragm and mediastinum, and the weight balanced by the pleural pressure gradient —
the forms of the bundled breathing scene. Each (h, linear solver) runs in its own process under
``mpiexec -n ranks``: the direct solver (MUMPS LU) and the iterative one (the Schur split that
condenses Φs cell by cell, AMG on the displacement, inexact Newton). Per case: dofs, Newton and
Krylov iterations, the time to build the solver and to solve the step, and the peak memory per
rank (the largest rank's high-water mark). Each row is kept in results/raw/large_lung.jsonl (a
case run again replaces its row), and results/large_lung.{md,csv,png} show them all.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import machine  # benchmarks/ is the script folder, first on sys.path

RESULTS = machine.RESULTS
SURROUNDING = ("pleura", "diaphragm", "mediastinum")


def case(mesh_mm: float, solver: str) -> dict:
    """One case, on the ranks of this process's MPI world (prints JSON on rank 0)."""
    from mpi4py import MPI

    from lungmech.fem.constraints import clamp
    from lungmech.fem.loads import FollowerPressure
    from lungmech.fem.model import Model
    from lungmech.fem.solver import NewtonOptions, NewtonSolver, Stepping, solve
    from lungmech.lung import Gravity, Poromechanics, skeleton
    from lungmech.mesh import lung_phantom

    sys.path.insert(0, str(Path(__file__).parent))
    from machine import reset_peak, status_kb

    comm = MPI.COMM_WORLD
    tic = time.perf_counter()
    geometry = lung_phantom(comm, mesh_size=mesh_mm / 1e3)
    model = Model(
        geometry,
        skeleton(160.0, 0.5, 200.0, 400.0),
        formulation=Poromechanics(1e4, 0.3),
        constraints=[clamp("hilum")],
        loads=[FollowerPressure(SURROUNDING, -50.0), Gravity(315.0, (0.0, 0.0, -9.81), balanced_on=SURROUNDING)],
    )
    mesh_seconds = time.perf_counter() - tic
    reset_peak()
    tic = time.perf_counter()
    newton = NewtonSolver(model, NewtonOptions(linear_solver=solver))
    setup_seconds = time.perf_counter() - tic
    tic = time.perf_counter()
    row = {"mesh_mm": mesh_mm, "solver": solver, "ranks": comm.size}
    try:
        report = solve(model, Stepping(initial_step=1.0), solver=newton, monitor=lambda step: None)
        row |= {
            "newton_iterations": report.newton_iterations,
            "krylov_iterations": newton.problem.solver.getLinearSolveIterations(),
            "failures": report.failures,
        }
    except Exception as error:  # noqa: BLE001 - a case that fails (memory, say) is a row that says so
        row |= {"error": str(error).splitlines()[0][:200]}
    solve_seconds = time.perf_counter() - tic
    space = model.space.dofmap
    peak = comm.allreduce((status_kb("VmHWM") or 0) / 1024, op=MPI.MAX)
    volume = comm.allreduce(float(_volume(model)), op=MPI.SUM) if "error" not in row else None
    row |= {
        "dofs": space.index_map.size_global * space.index_map_bs,
        "cells": geometry.mesh.topology.index_map(3).size_global,
        "mesh_seconds": mesh_seconds,
        "setup_seconds": setup_seconds,
        "solve_seconds": solve_seconds,
        "peak_rss_mib_per_rank": peak,
        "volume_m3": volume,
    }
    return row


def _volume(model) -> float:
    """This rank's part of the deformed volume."""
    import ufl
    from dolfinx import fem

    return fem.assemble_scalar(fem.form(ufl.det(model.F) * model.dx))


def markdown(rows: list[dict], command: str) -> str:
    sys.path.insert(0, str(Path(__file__).parent))
    from machine import cpu_and_memory

    cpu, memory = cpu_and_memory()
    lines = [
        "# A large lung: one breathing step, iterative against direct",
        "",
        f"`{command}` — {time.strftime('%Y-%m-%d')}, {cpu}, {memory}. P1 poromechanics on the right lung "
        "phantom, −50 Pa of pleural pressure with the weight balanced, from the reference; one load step.",
        "",
        "| h [mm] | dofs | ranks | solver | Newton its | Krylov its | set-up [s] | solve [s] | peak RSS per rank [MiB] | volume [L] |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(
                f"| {r['mesh_mm']:g} | {r['dofs']} | {r['ranks']} | {r['solver']} | failed: {r['error']} | | "
                f"{r['setup_seconds']:.1f} | {r['solve_seconds']:.1f} | {r['peak_rss_mib_per_rank']:.0f} | |"
            )
            continue
        krylov = r["krylov_iterations"] if r["solver"] == "iterative" else "—"
        lines.append(
            f"| {r['mesh_mm']:g} | {r['dofs']} | {r['ranks']} | {r['solver']} | {r['newton_iterations']} | {krylov} | "
            f"{r['setup_seconds']:.1f} | {r['solve_seconds']:.1f} | {r['peak_rss_mib_per_rank']:.0f} | "
            f"{1e3 * r['volume_m3']:.6f} |"
        )
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    for solver, marker in (("direct", "s-"), ("iterative", "o-")):
        mine = [r for r in rows if r["solver"] == solver and "error" not in r]
        if not mine:
            continue
        dofs = [r["dofs"] for r in mine]
        left.loglog(dofs, [r["solve_seconds"] for r in mine], marker, label=solver)
        right.loglog(dofs, [r["peak_rss_mib_per_rank"] for r in mine], marker, label=solver)
    left.set_ylabel("solve of one step [s]")
    right.set_ylabel("peak memory per rank [MiB]")
    for ax in (left, right):
        ax.set_xlabel("degrees of freedom [-]")
        ax.grid(alpha=0.3, which="both")
        ax.legend()
    fig.suptitle("P1 lung poromechanics, one breathing step")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="8,5,3.2", help="mesh sizes h in mm (comma-separated)")
    parser.add_argument("--ranks", type=int, default=2)
    parser.add_argument("--solvers", default="direct,iterative")
    parser.add_argument("--case", nargs=2, metavar=("H", "SOLVER"), help=argparse.SUPPRESS)
    parser.add_argument("--timeout", type=float, default=3600, help="seconds per case")
    parser.add_argument("--quick", action="store_true", help="h = 14 mm on 1 rank (the suite's case)")
    args = parser.parse_args()
    stem = "large_lung_quick" if args.quick else "large_lung"
    if args.quick:
        args.sizes, args.ranks, args.timeout = "14", 1, 120
    if args.case:
        row = case(float(args.case[0]), args.case[1])
        from mpi4py import MPI

        if MPI.COMM_WORLD.rank == 0:
            print("ROW " + json.dumps(row), flush=True)
        return
    mpiexec = Path(sys.executable).parent / "mpiexec"
    raw = RESULTS / "raw" / f"{stem}.jsonl"
    raw.parent.mkdir(parents=True, exist_ok=True)
    for size in (float(h) for h in args.sizes.split(",")):
        for solver in args.solvers.split(","):
            command = [str(mpiexec if mpiexec.exists() else "mpiexec"), "-n", str(args.ranks), sys.executable, __file__]
            command += ["--case", str(size), solver]
            try:
                done = subprocess.run(command, capture_output=True, text=True, timeout=args.timeout, env=os.environ)
                found = [line[4:] for line in done.stdout.splitlines() if line.startswith("ROW ")]
                row = json.loads(found[0]) if found else None
            except subprocess.TimeoutExpired:
                row, done = None, None
            if row is None:
                reason = "timed out" if done is None else (done.stderr.strip().splitlines() or ["no output"])[-1][:200]
                print(f"h = {size:g} mm, {solver}: {reason}", flush=True)
                continue
            with open(raw, "a") as stream:
                stream.write(json.dumps(row) + "\n")
            print(json.dumps(row), flush=True)
    latest = {}
    for line in raw.read_text().splitlines():
        row = json.loads(line)
        latest[(row["mesh_mm"], row["solver"], row["ranks"])] = row
    rows = sorted(latest.values(), key=lambda r: (r["ranks"], -r["mesh_mm"], r["solver"]))
    from machine import write_results

    command = "python benchmarks/large_lung.py " + " ".join(sys.argv[1:])
    write_results(RESULTS, stem, rows, markdown(rows, command.strip()))
    plot(rows, RESULTS / f"{stem}.png")
    print((RESULTS / f"{stem}.md").read_text())


if __name__ == "__main__":
    main()
