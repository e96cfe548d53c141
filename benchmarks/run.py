"""The discretisation trade, measured: P1 vs P2 vs Taylor–Hood on the pressurised thick sphere.

    python benchmarks/run.py                  # the full sequence (see MESHES)
    python benchmarks/run.py --quick          # one coarse mesh per formulation, one timed solve: a smoke run
    python benchmarks/run.py --max-dofs 100000

Every (formulation, mesh) is solved twice, each time in a fresh process (benchmarks/case.py):
once with lungmech and once with the hand-written DOLFINx script (benchmarks/handwritten.py),
on the same mesh with the same forms, quadrature, solver options and load steps. Writes
benchmarks/results/discretisation.{md,csv,png} and prints the table. See benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import machine
from machine import cpu_and_memory  # benchmarks/ is the script folder, first on sys.path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = machine.RESULTS
RAW = RESULTS / "raw"  # one JSON per case, as printed by case.py
JIT = RESULTS / "jit-cache"  # XDG_CACHE_HOME of the cases: one per (formulation, implementation)
PYTHON = sys.executable

# gmsh mesh sizes, coarse to fine; the finest reach >= 200k dofs (P1: 3 per vertex, hence finer).
MESHES = {
    "P1": (0.3, 0.15, 0.1, 0.07, 0.05, 0.034),
    "P2": (0.3, 0.2, 0.15, 0.1, 0.07),
    "mixed": (0.3, 0.2, 0.15, 0.1, 0.07),
}
QUICK = {"P1": (0.3,), "P2": (0.5,), "mixed": (0.5,)}  # one coarse mesh each, one timed solve: a smoke run
# dofs ~ C / h^3 (fitted to the meshes above), to skip a case under --max-dofs without meshing it.
DOFS_PER_H3 = {"P1": 10.0, "P2": 72.0, "mixed": 75.0}
IMPLS = ("lungmech", "handwritten")


def run_case(formulation: str, h: float, impl: str, args, ranks: int = 1) -> dict:
    raw = RAW / f"{formulation}-h{h}-{impl}-n{ranks}.json"
    if args.measured_only and not raw.exists():
        return {"skipped": True, "reason": "not measured"}
    if (args.reuse or args.measured_only) and raw.exists():
        result = json.loads(raw.read_text())
        result["reused"] = True
        return result
    result = _run_case(formulation, h, impl, args, ranks)
    raw.write_text(json.dumps(result, indent=1) + "\n")
    return result


def _run_case(formulation: str, h: float, impl: str, args, ranks: int = 1) -> dict:
    # a smoke run compiles into the caller's JIT cache (warm after its first run); a measured
    # one into its own, emptied first, to time the cold compilation too
    env = os.environ if args.quick else os.environ | {"XDG_CACHE_HOME": str(JIT / f"{formulation}-{impl}")}
    command = [
        PYTHON, str(HERE / "case.py"), "--impl", impl, "--formulation", formulation, "--h", str(h),
        "--pressure", str(args.pressure), "--nu", str(args.nu), "--steps", str(args.steps),
        "--line-search", args.line_search, "--max-dofs", str(args.max_dofs or 0),
        *(["--solves", "1"] if args.quick else []),
    ]  # fmt: skip
    if ranks > 1:
        mpiexec = Path(PYTHON).parent / "mpiexec"
        command = [str(mpiexec if mpiexec.exists() else "mpiexec"), "-n", str(ranks), *command]
    tic = time.perf_counter()
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=args.timeout)
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    if done.returncode != 0 or not lines:
        tail = (done.stderr or done.stdout).strip().splitlines()[-5:]
        print(f"  ! {impl} {formulation} h={h} failed (exit {done.returncode}): {' | '.join(tail)}", flush=True)
        return {
            "impl": impl,
            "formulation": formulation,
            "h": h,
            "ranks": ranks,
            "converged": False,
            "message": " | ".join(tail),
        }
    result = json.loads(lines[-1][len("RESULT ") :])
    result["wall_seconds"] = time.perf_counter() - tic
    return result


def describe(r: dict) -> str:
    if r.get("skipped"):
        return f"skipped ({r.get('reason') or str(r['dofs']) + ' dofs > --max-dofs'})"
    if not r.get("converged"):
        return f"NOT CONVERGED: {r.get('message', '')[:120]}"
    return (
        f"{r['dofs']} dofs, {r['newton_iterations']} its / {r['load_steps']} steps, solve {r['solve_seconds']:.2f} s, "
        f"setup {r['setup_seconds']:.2f} s ({r['jit_cache']}), RSS {r['peak_rss_mb']:.0f} MB, "
        f"err u(A) {r['err_inner']:.2e}, L2 {r['err_l2']:.2e}"
    )


# --- output ------------------------------------------------------------------------------------

COLUMNS = [  # (csv name, from which run, key)
    ("formulation", "lm", "formulation"), ("ranks", "lm", "ranks"), ("h", "lm", "h"), ("mesh_order", "lm", "mesh_order"),
    ("cells", "lm", "cells"), ("vertices", "lm", "vertices"), ("dofs", "lm", "dofs"),
    ("quadrature_degree", "lm", "quadrature_degree"), ("line_search", "lm", "line_search"),
    ("load_steps", "lm", "load_steps"), ("failed_steps", "lm", "failed_steps"),
    ("newton_iterations", "lm", "newton_iterations"), ("converged", "lm", "converged"),
    ("mesh_seconds", "lm", "mesh_seconds"), ("build_seconds", "lm", "build_seconds"),
    ("setup_seconds", "lm", "setup_seconds"), ("jit_cache", "lm", "jit_cache"),
    ("solve_seconds", "lm", "solve_seconds"), ("solve_seconds_first", "lm", "solve_seconds_first"),
    ("solves", "lm", "solves"), ("seconds_per_newton", "lm", None),
    ("peak_rss_mb", "lm", "peak_rss_mb"), ("peak_rss_mb_sum_ranks", "lm", "peak_rss_mb_sum"),
    ("peak_rss_mesh_mb", "lm", "peak_rss_mesh_mb"),
    ("hw_newton_iterations", "hw", "newton_iterations"), ("hw_converged", "hw", "converged"),
    ("hw_setup_seconds", "hw", "setup_seconds"), ("hw_jit_cache", "hw", "jit_cache"),
    ("hw_solve_seconds", "hw", "solve_seconds"), ("hw_solve_seconds_first", "hw", "solve_seconds_first"),
    ("hw_solves", "hw", "solves"), ("hw_seconds_per_newton", "hw", None),
    ("hw_peak_rss_mb", "hw", "peak_rss_mb"), ("solve_time_ratio", None, None),
    ("u_inner", "lm", "u_inner"), ("u_inner_ref", "lm", "u_inner_ref"), ("err_inner", "lm", "err_inner"),
    ("err_inner_pointwise", "lm", "err_inner_pointwise"), ("err_l2", "lm", "err_l2"),
    ("hw_u_inner", "hw", "u_inner"), ("hw_err_l2", "hw", "err_l2"),
    ("reference_fit_error", "lm", "reference_fit_error"), ("mesh_seconds_hw", "hw", "mesh_seconds"),
    ("case_wall_seconds", "lm", "wall_seconds"), ("hw_case_wall_seconds", "hw", "wall_seconds"),
    ("reused", "lm", "reused"),
]  # fmt: skip


def row(lm: dict, hw: dict | None) -> dict:
    out = {}
    for name, which, key in COLUMNS:
        source = lm if which == "lm" else hw
        out[name] = source.get(key, "") if (source and key) else ""
    for prefix, r in (("", lm), ("hw_", hw)):
        if r and r.get("converged") and r.get("newton_iterations"):
            out[f"{prefix}seconds_per_newton"] = r["solve_seconds"] / r["newton_iterations"]
    if lm.get("converged") and hw and hw.get("converged") and hw["solve_seconds"] > 0:
        out["solve_time_ratio"] = lm["solve_seconds"] / hw["solve_seconds"]
    return out


def fmt(value, spec: str) -> str:
    if value in ("", None):
        return "–"
    return format(value, spec)


def markdown(rows: list[dict], header: list[str]) -> str:
    head = (
        "| formulation | ranks | h | cells | dofs | Newton its | load steps | solve [s] | s / Newton it | "
        "JIT+setup [s] | peak RSS [MB] | hand-written solve [s] | ratio lungmech / hand-written | "
        "rel. err. inner radius | rel. L2 err. u |"
    )
    lines = [*header, "", head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        steps = (
            f"{r['load_steps']}" + (f" (+{r['failed_steps']} failed)" if r["failed_steps"] else "")
            if r["load_steps"] != ""
            else "–"
        )
        setup = f"{fmt(r['setup_seconds'], '.1f')} ({r['jit_cache']})" if r["setup_seconds"] != "" else "–"
        its = r["newton_iterations"] if r["converged"] else "did not converge"
        if r["hw_newton_iterations"] not in ("", r["newton_iterations"]):
            its = f"{its} (hw {r['hw_newton_iterations']})"
        hw = (
            fmt(r["hw_solve_seconds"], ".2f")
            if r["hw_converged"]
            else ("did not converge" if r["hw_converged"] is False else "–")
        )
        lines.append(
            f"| {r['formulation']} | {r['ranks']} | {r['h']} | {r['cells']} | {r['dofs']} | {its} | {steps} | "
            f"{fmt(r['solve_seconds'], '.2f')} | {fmt(r['seconds_per_newton'], '.3f')} | {setup} | "
            f"{fmt(r['peak_rss_mb'], '.0f')}{' (sum ' + format(r['peak_rss_mb_sum_ranks'], '.0f') + ')' if r['ranks'] not in ('', 1) else ''} | "
            f"{hw} | {fmt(r['solve_time_ratio'], '.3f')} | {fmt(r['err_inner'], '.2e')} | {fmt(r['err_l2'], '.2e')} |"
        )
    return "\n".join(lines) + "\n"


def versions() -> dict:
    code = (
        "import lungmech, dolfinx, petsc4py; from petsc4py import PETSc; "
        "print(dolfinx.__version__, '.'.join(map(str, PETSc.Sys.getVersion())))"
    )
    out = subprocess.run([PYTHON, "-c", code], capture_output=True, text=True).stdout.split()
    cpu, memory = cpu_and_memory()
    return {
        "dolfinx": out[0] if out else "?",
        "petsc": out[1] if len(out) > 1 else "?",
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory": memory,
    }


def reference_value(pressure: float, nu: float) -> float:
    sys.path.insert(0, str(ROOT / "tests"))
    import analytic

    lmbda = 2 * nu / (1 - 2 * nu)
    return analytic.thick_sphere_compressible(
        "neo_hookean", analytic.LameParams(1.0, lmbda), pressure, 1.0, 2.0
    ).u_inner


# --- main --------------------------------------------------------------------------------------


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="coarse meshes only (smoke run)")
    parser.add_argument("--max-dofs", type=int, default=None, help="skip cases with more dofs")
    parser.add_argument("--formulations", default="P1,P2,mixed")
    parser.add_argument("--mpi", type=int, default=0, metavar="N",
                        help="also run the largest P2 case under mpiexec -n N (0: skip)")  # fmt: skip
    parser.add_argument("--no-handwritten", action="store_true", help="skip the hand-written baseline")
    parser.add_argument("--pressure", type=float, default=0.2)
    parser.add_argument("--nu", type=float, default=0.4999)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument(
        "--line-search", default="cp", help="SNES line search of both codes (see README: bt fails for P2)"
    )
    parser.add_argument("--timeout", type=float, default=7200.0, help="seconds per case")
    parser.add_argument(
        "--keep-cache", action="store_true", help="do not empty the JIT caches first (then the first mesh is warm too)"
    )
    parser.add_argument(
        "--reuse", action="store_true", help="take cases already in results/raw/ instead of running them again"
    )
    parser.add_argument(
        "--measured-only", action="store_true", help="rebuild the table from results/raw/ alone; run nothing"
    )
    return parser.parse_args()


def header(args, total: float, done: bool, v: dict, u_ref: float, reused: int, cases_seconds: float = 0.0) -> list[str]:
    nu, P = args.nu, args.pressure
    if args.quick:
        cache = "- JIT cache: the caller's own (--quick: a smoke run, warm after its first run)."
    elif args.reuse:
        cache = "- JIT cache: as recorded per case (--reuse: some cases come from an earlier run); the JIT+setup column says cold or warm."
    elif args.keep_cache:
        cache = "- JIT cache: kept from earlier runs (--keep-cache); the JIT+setup column says cold or warm per case."
    else:
        cache = (
            "- JIT cache: emptied before the run, one cache directory per (formulation, code): the coarsest mesh of each "
            "formulation compiles its forms cold, the finer meshes find them warm (the JIT+setup column says which)."
        )
    status = "" if done else " — RUN IN PROGRESS, partial table"
    return [
        f"# The discretisation trade: thick-walled sphere octant under internal follower pressure{status}",
        "",
        f"- Date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}; machine: {v['cores']} cores "
        f"({v['cpu']}), {v['memory']}; DOLFINx {v['dolfinx']}, PETSc {v['petsc']}, Python {platform.python_version()}.",
        f"- Problem: A = 1, B = 2, symmetry planes x0, y0, z0; compressible neo-Hookean μ = 1, ν = {nu} "
        f"(λ = {2 * nu / (1 - 2 * nu):.6g}); follower pressure P = {P} on the inner surface. Reference u(A) = {u_ref:.10f} "
        "(radial BVP by scipy solve_bvp, tests/analytic.py).",
        "- Meshes: gmsh (lungmech.mesh.sphere), straight tetrahedra for P1, curved quadratic ones for P2 and mixed "
        "(Taylor–Hood P2–P1).",
        f"- Solver (both codes): SNES newtonls, line search {args.line_search}, rtol 1e-10, atol 1e-12, stol 1e-12, "
        f"max 25 its, KSP preonly + MUMPS LU (ICNTL(14) = 200); {args.steps} equal load steps with lungmech's linear predictor.",
        cache,
        "- solve [s]: wall time of the whole load stepping, fastest of up to 5 solves in the same process (repeated only "
        "while the total stays under 10 s); the hand-written script is timed the same way. ratio = lungmech / hand-written. "
        "Peak RSS: of the case's process (mesh generation included; ranks > 1: max per rank, sum in brackets).",
        "- Errors: inner radius = mean of |X + u| − A over the inner surface vs u_ref(A); L2 = ‖u − u_ref‖/‖u_ref‖ over "
        "the mesh, u_ref(R) X/R as a UFL expression (Chebyshev series of the reference, quadrature degree 8).",
        (
            "- Table rebuilt from results/raw/ (--measured-only); per-case wall times are in the CSV (case_wall_seconds); "
            f"the cases in this table took {cases_seconds / 60:.1f} min in total (sum of their process wall times)."
            if args.measured_only
            else f"- Total benchmark wall time: {total / 60:.1f} min{' (--quick)' if args.quick else ''}"
            f"{f' (--max-dofs {args.max_dofs})' if args.max_dofs else ''}"
            f"{f'; {reused} cases reused from an earlier run' if reused else ''}."
        ),
    ]


def write(rows: list[dict], lines: list[str]) -> str:
    table = markdown(rows, lines)
    (RESULTS / "discretisation.md").write_text(table)
    with open(RESULTS / "discretisation.csv", "w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=[name for name, _, _ in COLUMNS])
        writer.writeheader()
        writer.writerows(rows)
    return table


def main() -> None:
    args = parse_args()
    started = time.perf_counter()
    RAW.mkdir(parents=True, exist_ok=True)
    if not args.keep_cache and not args.reuse and not args.quick and JIT.exists():
        shutil.rmtree(JIT)
    meshes = QUICK if args.quick else MESHES
    formulations = [f.strip() for f in args.formulations.split(",") if f.strip()]
    v, u_ref = versions(), reference_value(args.pressure, args.nu)

    cases: list[tuple[str, float, int]] = []
    for formulation in formulations:
        for h in meshes[formulation]:
            if args.max_dofs and DOFS_PER_H3[formulation] / h**3 > 2 * args.max_dofs:
                print(f"{formulation} h={h}: skipped (about {DOFS_PER_H3[formulation] / h**3:.0f} dofs)", flush=True)
                continue
            cases.append((formulation, h, 1))
    if args.mpi > 1 and "P2" in formulations:
        sizes = [h for f, h, _ in cases if f == "P2"]
        if sizes:
            cases.append(("P2", min(sizes), args.mpi))

    rows: list[dict] = []
    reused = 0
    for formulation, h, ranks in cases:
        label = f"{formulation} h={h}" + (f" ({ranks} ranks)" if ranks > 1 else "")
        lm = run_case(formulation, h, "lungmech", args, ranks)
        print(f"{label} lungmech:    {describe(lm)}", flush=True)
        if lm.get("skipped"):
            continue
        hw = None
        if not args.no_handwritten:
            hw = run_case(formulation, h, "handwritten", args, ranks)
            print(f"{label} handwritten: {describe(hw)}", flush=True)
        reused += bool(lm.get("reused")) + bool(hw and hw.get("reused"))
        rows.append(row(lm, hw))
        write(rows, header(args, time.perf_counter() - started, False, v, u_ref, reused))

    cases_seconds = sum(float(r[k] or 0.0) for r in rows for k in ("case_wall_seconds", "hw_case_wall_seconds"))
    table = write(rows, header(args, time.perf_counter() - started, True, v, u_ref, reused, cases_seconds))
    plot(rows, RESULTS / "discretisation.png")
    print()
    print(table)


def plot(rows: list[dict], path: Path) -> None:
    """Solve time against dofs, one line per formulation and code (lungmech solid, hand-written dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(6.5, 4.2))
    for formulation in dict.fromkeys(r["formulation"] for r in rows):
        mine = sorted(
            (r for r in rows if r["formulation"] == formulation and int(r["ranks"]) == 1), key=lambda r: r["dofs"]
        )
        dofs = [r["dofs"] for r in mine]
        (line,) = axes.loglog(dofs, [r["solve_seconds"] for r in mine], "o-", label=f"{formulation}, lungmech")
        if all(r["hw_solve_seconds"] not in ("", None) for r in mine):
            axes.loglog(
                dofs,
                [r["hw_solve_seconds"] for r in mine],
                "s--",
                color=line.get_color(),
                label=f"{formulation}, hand-written",
            )
    axes.set_xlabel("degrees of freedom [1]")
    axes.set_ylabel("solve (load stepping) [s]")
    axes.set_title("Thick sphere under pressure: solve time against size", fontsize=10)
    axes.grid(alpha=0.3, which="both")
    axes.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


if __name__ == "__main__":
    main()
