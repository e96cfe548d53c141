"""Shape registration (lungmech.registration.sobolev.register): time and iterations against
reference-mesh size and image resolution, measured.

    python benchmarks/registration.py            # 4 meshes (3.7k-50k cells) x 3 spacings (2.5, 1.5, 1 mm)
    python benchmarks/registration.py --quick    # the bundled mesh x 2 spacings (3, 2.5 mm), seconds
    python benchmarks/registration.py --ranks 2  # the same under mpiexec -n 2 (re-launches itself)

The generic right lung (lung_phantom, the reference Ω) is registered onto a synthetic patient
segmentation with exact ground truth (a LungShape of other proportions, moved, voxelised at CT
spacing). For every (mesh size, image spacing, Sobolev-solver) case: registration wall time,
iterations per stage, time per iteration, where the time goes (Sobolev-gradient solves,
derivative assembly, image sampling, ...), min det F, Dice, mean surface distance (mm and
voxels), hd95, volume error against the exact shape, voxelisation and metrics time, image size
and the case's peak RSS. The Sobolev-gradient solver is lungmech's default (``Options().solver``);
``--solvers default,petsc`` adds PETSc's own sparse LU for comparison (``mumps``: MUMPS explicitly).
Writes benchmarks/results/registration.{md,csv,png} (--quick: registration_quick.*).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import machine
from machine import (
    STARTED,
    cpu_and_memory,
    relaunch,
    reset_peak,
    say,
    status_kb,
    tic,
    toc,
)  # benchmarks/ is the script folder, first on sys.path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = machine.RESULTS

MESH_SIZES = (0.0176, 0.012, 0.008, 0.006)  # lung_phantom mesh_size [m]: 3,656 / 8,658 / 22,927 / 49,955 cells
SPACINGS = (2.5, 1.5, 1.0)  # image spacing [mm]
QUICK_MESH_SIZES = (0.0176,)
QUICK_SPACINGS = (3.0, 2.5)
SOLVERS = {
    "default": None,  # Options().solver as it is (MUMPS LU since 42b17cf; PETSc's own LU before)
    "petsc": {"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "petsc"},
    "mumps": {"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"},
}
# The synthetic patient: another lung shape than the reference's, moved in its image.
TARGET = {"height": 0.26, "width": 0.10, "depth": 0.16, "apex": 0.27, "dome": 0.22}
OFFSET = (0.01, 0.02, -0.03)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="smoke run: the bundled mesh size x 2 spacings (3, 2.5 mm)")
    p.add_argument("--ranks", type=int, default=1, help="re-launch under mpiexec -n RANKS (default 1)")
    p.add_argument(
        "--mesh-sizes",
        default=None,
        help=f"lung_phantom mesh_size values in metres, comma list (default {','.join(map(str, MESH_SIZES))})",
    )
    p.add_argument("--spacings", default=None, help=f"image spacings in mm (default {','.join(map(str, SPACINGS))})")
    p.add_argument(
        "--solvers",
        default="default",
        help="comma list of Sobolev-gradient (and elastic-extension) solvers: default (Options().solver), "
        "petsc (PETSc's own LU), mumps (MUMPS LU); default: default",
    )
    p.add_argument(
        "--budget",
        type=float,
        default=300.0,
        help="do not run a case when a smaller case of the same solver (coarser mesh at the same "
        "spacing, or the same mesh at a coarser spacing) already took more than BUDGET s",
    )
    p.add_argument(
        "--prefix", default=None, help="output file stem (default registration, --quick: registration_quick)"
    )
    p.add_argument("--no-plot", action="store_true", help="skip the PNG")
    return p.parse_args(argv)


ARGS = parse_args()
relaunch(ARGS.ranks, __file__, "REGISTRATION_BENCH_COMMAND")
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

# --- heavy imports only in the process that does the work -------------------------------------
import collections  # noqa: E402
import csv  # noqa: E402
import dataclasses  # noqa: E402
import datetime  # noqa: E402
import functools  # noqa: E402
import logging  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402

from mpi4py import MPI  # noqa: E402  (first: it loads the MPI library dolfinx links to)
from petsc4py import PETSc  # noqa: E402

import numpy as np  # noqa: E402

import lungmech.registration.sobolev as sobolev  # noqa: E402
from lungmech.mesh import (
    lung_phantom,  # noqa: E402
    nodes,  # noqa: E402
)
from lungmech.mesh.lung_shape import LungShape  # noqa: E402
from lungmech.registration import field as image_field  # noqa: E402
from lungmech.registration import metrics  # noqa: E402
from lungmech.registration.phantom import voxelise  # noqa: E402
from lungmech.registration.sobolev import Options, register  # noqa: E402

COMM = MPI.COMM_WORLD
RANK0 = COMM.rank == 0
logging.getLogger("lungmech").setLevel(logging.WARNING)


# --- memory: the peak of each case -------------------------------------------------------------


def peak_mb(per_case: bool) -> tuple[float, float]:
    """(max over ranks, sum over ranks) of the peak RSS in MB: VmHWM since the last reset, or the
    process's whole-life peak (getrusage ru_maxrss) where /proc is not available."""
    kb = status_kb("VmHWM") if per_case else None
    if kb is None:
        kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    mb = kb / 1024
    return COMM.allreduce(mb, op=MPI.MAX), COMM.allreduce(mb, op=MPI.SUM)


def rss_mb() -> float:
    kb = status_kb("VmRSS") or 0
    return COMM.allreduce(kb / 1024, op=MPI.MAX)


# --- where the registration time goes: exclusive timers around ShapeEnergy's parts --------------


class Timers:
    """Exclusive wall time and call counts of wrapped functions (a nested call's time is its own)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = collections.defaultdict(float)
        self.calls: dict[str, int] = collections.defaultdict(int)
        self._children: list[float] = []

    def reset(self) -> None:
        self.seconds.clear()
        self.calls.clear()

    def wrap(self, name, function):
        """``name``: a label, or a function of the call's arguments giving one."""

        @functools.wraps(function)
        def timed(*args, **kwargs):
            label = name(*args, **kwargs) if callable(name) else name
            start = time.perf_counter()
            self._children.append(0.0)
            try:
                return function(*args, **kwargs)
            finally:
                children = self._children.pop()
                elapsed = time.perf_counter() - start
                self.seconds[label] += elapsed - children
                self.calls[label] += 1
                if self._children:
                    self._children[-1] += elapsed

        return timed


TIMERS = Timers()
_FRESH_MATRIX: set[int] = set()  # ShapeEnergy objects whose Sobolev matrix was reassembled since the last solve


def _solve_label(energy, *_args) -> str:
    """The first Sobolev solve after derivative() reassembled the matrix factorises it; later ones reuse the LU."""
    if id(energy) in _FRESH_MATRIX:
        _FRESH_MATRIX.discard(id(energy))
        return "sobolev factor+solve"
    return "sobolev solve"


def _derivative_label(energy, *_args) -> str:
    _FRESH_MATRIX.add(id(energy))
    return "derivative"


# (label in the tables, object, attribute); sobolev calls moments_fit and image_field.* by these names.
PARTS = [
    ("setup", sobolev.ShapeEnergy, "__init__"),  # forms (JIT, warm here), matrices, KSPs
    ("similarity", sobolev, "moments_fit"),
    ("image function", image_field, "signed_distance"),  # EDT + Gaussian smoothing, once per stage
    ("image function", image_field, "binary"),
    (_solve_label, sobolev.ShapeEnergy, "riesz"),  # LU factorisation (when the matrix changed) + solve
    (_derivative_label, sobolev.ShapeEnergy, "derivative"),  # assembly of DΨ and of the Sobolev matrix
    ("psi", sobolev.ShapeEnergy, "value"),  # Ψ (line-search trials)
    ("image sampling", sobolev.ShapeEnergy, "_sample"),  # quadrature points, trilinear I and ∇I
    ("det F", sobolev.ShapeEnergy, "min_jacobian"),
    ("relax", sobolev.ShapeEnergy, "relax"),  # elastic extension of the boundary displacement
]
for _label, _owner, _name in PARTS:
    setattr(_owner, _name, TIMERS.wrap(_label, getattr(_owner, _name)))


def key(label: str) -> str:
    return label.replace(" ", "_").replace("+", "_")


def sobolev_seconds(r: dict) -> float:
    """Time of all Sobolev-gradient solves of a case (factorising ones and those reusing the LU)."""
    return r["t_sobolev_factor_solve"] + r["t_sobolev_solve"]


PART_LABELS = [
    "setup",
    "similarity",
    "image function",
    "sobolev factor+solve",
    "sobolev solve",
    "derivative",
    "psi",
    "image sampling",
    "det F",
    "relax",
]


def factor_package(solver: dict | None) -> str:
    """Which LU package PETSc picks for these options on this communicator (a tiny probe matrix)."""
    options = dict(Options().solver if solver is None else solver)
    A = PETSc.Mat().createAIJ([8 * COMM.size, 8 * COMM.size], nnz=1, comm=COMM)
    A.setUp()
    for i in range(*A.getOwnershipRange()):
        A[i, i] = 2.0
    A.assemble()
    ksp = PETSc.KSP().create(COMM)
    ksp.setOperators(A)
    prefix = "registration_bench_probe_"
    ksp.setOptionsPrefix(prefix)
    opts = PETSc.Options()
    for key, value in options.items():
        opts[prefix + key] = value
    ksp.setFromOptions()
    ksp.setUp()
    name = ksp.getPC().getFactorSolverType() if ksp.getPC().getType() == "lu" else ksp.getPC().getType()
    for key in options:
        del opts[prefix + key]
    ksp.destroy()
    A.destroy()
    return name


# --- one case ----------------------------------------------------------------------------------


@dataclasses.dataclass
class Reference:
    mesh_size: float
    mesh: object
    cells: int
    nodes: int
    mesh_seconds: float


def reference_mesh(mesh_size: float) -> Reference:
    t0 = tic()
    mesh = lung_phantom(COMM, mesh_size=mesh_size, side="right").mesh
    seconds = toc(t0)
    cells = mesh.topology.index_map(mesh.topology.dim).size_global
    nodes_ = mesh.geometry.index_map().size_global
    return Reference(mesh_size, mesh, cells, nodes_, seconds)


def run_case(ref: Reference, spacing_mm: float, solver_name: str, shape: LungShape) -> dict:
    per_case = reset_peak()
    COMM.Barrier()
    rss_start = rss_mb()
    t0 = tic()
    image = voxelise(shape, spacing_mm * 1e-3, offset=OFFSET)
    voxelise_seconds = toc(t0)
    solver = SOLVERS[solver_name]
    options = Options() if solver is None else Options(solver=solver)
    TIMERS.reset()
    t0 = tic()
    result = register(ref.mesh, image, options)
    seconds = toc(t0)
    parts = {label: COMM.bcast(TIMERS.seconds.get(label, 0.0), root=0) for label in PART_LABELS}
    calls = {label: COMM.bcast(TIMERS.calls.get(label, 0), root=0) for label in PART_LABELS}
    register_max, register_sum = peak_mb(per_case)
    per_case = per_case and reset_peak()
    t0 = tic()
    with nodes.deformed(result.displacement) as mesh:
        report = metrics.report(mesh, image)
    metrics_seconds = toc(t0)
    metrics_max, metrics_sum = peak_mb(per_case)
    stages = result.stages
    row = {
        "mesh_size": ref.mesh_size,
        "cells": ref.cells,
        "nodes": ref.nodes,
        "dofs": 3 * ref.nodes,
        "spacing_mm": spacing_mm,
        "image_shape": "x".join(map(str, image.shape)),
        "voxels": int(np.prod(image.shape)),
        "mask_voxels": int(np.count_nonzero(image.mask)),
        "solver": solver_name,
        "ranks": COMM.size,
        "status": "ok",
        "registration_seconds": seconds,
        "register_reported_seconds": COMM.bcast(result.seconds, root=0),
        "iterations": result.iterations,
        "seconds_per_iteration": seconds / result.iterations if result.iterations else "",
        "converged": result.converged,
        "stage_smoothing": ";".join(f"{s['smoothing']:g}" for s in stages),
        "stage_iterations": ";".join(str(s["iterations"]) for s in stages),
        "stage_reasons": ";".join(s["reason"] for s in stages),
        "stage_min_det_F": ";".join(f"{s['min_det_F']:.4f}" for s in stages),
        "psi": result.psi,
        "min_det_F": result.min_jacobian,
        "dice": report["dice"],
        "msd_mm": 1e3 * report["mean_surface_distance"],
        "msd_voxels": report["mean_surface_distance_voxels"],
        "hd95_mm": 1e3 * report["hd95"],
        "hausdorff_mm": 1e3 * report["hausdorff"],
        "volume_mesh": report["volume_mesh"],
        "volume_image": report["volume_image"],
        "volume_exact": shape.volume(),
        "volume_err_exact_pct": 100 * (report["volume_mesh"] / shape.volume() - 1),
        "voxelise_seconds": voxelise_seconds,
        "metrics_seconds": metrics_seconds,
        "mesh_seconds": ref.mesh_seconds,
        "peak_rss_mb": max(register_max, metrics_max),
        "peak_rss_mb_sum": max(register_sum, metrics_sum),
        "peak_rss_register_mb": register_max,
        "peak_rss_metrics_mb": metrics_max,
        "rss_start_mb": rss_start,
        "peak_per_case": per_case,
        "load_average": os.getloadavg()[0],
    }
    accounted = sum(parts.values())
    for label in PART_LABELS:
        row[f"t_{key(label)}"] = parts[label]
        row[f"n_{key(label)}"] = calls[label]
    row["t_other"] = seconds - accounted  # L-BFGS vector algebra, set_state, Python, MPI
    return row


# --- output --------------------------------------------------------------------------------------

COLUMNS = [
    "mesh_size",
    "cells",
    "nodes",
    "dofs",
    "spacing_mm",
    "image_shape",
    "voxels",
    "mask_voxels",
    "solver",
    "ranks",
    "status",
    "registration_seconds",
    "register_reported_seconds",
    "iterations",
    "seconds_per_iteration",
    "converged",
    "stage_smoothing",
    "stage_iterations",
    "stage_reasons",
    "stage_min_det_F",
    "psi",
    "min_det_F",
    "dice",
    "msd_mm",
    "msd_voxels",
    "hd95_mm",
    "hausdorff_mm",
    "volume_mesh",
    "volume_image",
    "volume_exact",
    "volume_err_exact_pct",
    "voxelise_seconds",
    "metrics_seconds",
    "mesh_seconds",
    "peak_rss_mb",
    "peak_rss_mb_sum",
    "peak_rss_register_mb",
    "peak_rss_metrics_mb",
    "rss_start_mb",
    "peak_per_case",
    "load_average",
    *[f"{p}_{key(label)}" for label in PART_LABELS for p in ("t", "n")],
    "t_other",
    "skip_reason",
]


def f(x, spec: str = ".3g") -> str:
    if x in ("", None):
        return ""
    if isinstance(x, float) and not np.isfinite(x):
        return "nan"
    return format(x, spec)


def memory(r: dict) -> str:
    text = f"{f(r['peak_rss_register_mb'], '.0f')} / {f(r['peak_rss_metrics_mb'], '.0f')}"
    if r["ranks"] > 1:
        text += f" (sum {f(r['peak_rss_mb_sum'], '.0f')})"
    return text


def markdown(rows: list[dict], lines: list[str]) -> str:
    done = [r for r in rows if r["status"] == "ok"]
    skipped = [r for r in rows if r["status"] != "ok"]
    out = list(lines) + ["", "## Results", ""]
    head = (
        "| mesh size [m] | cells | nodes | spacing [mm] | image [voxels] | solver | registration [s] | iterations "
        "(stage 1 + 2) | s / it | min det F | Dice | MSD [mm] | MSD [vox] | hd95 [mm] | vol. err. vs exact | "
        "voxelise + metrics [s] | peak RSS [MB] register / metrics |"
    )
    out += [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        base = (
            f"| {r['mesh_size']:g} | {r['cells']:,} | {r['nodes']:,} | {r['spacing_mm']:g} | "
            f"{r['image_shape'].replace('x', '×')} ({r['voxels'] / 1e6:.2g} M) | {r['solver']} |"
        )
        if r["status"] != "ok":
            out.append(base + f" not run ({r['skip_reason']}) |" + " |" * 10)
            continue
        its = " + ".join(r["stage_iterations"].split(";"))
        out.append(
            base
            + f" {f(r['registration_seconds'], '.1f')} | {r['iterations']} ({its}) | {f(r['seconds_per_iteration'], '.3f')} | "
            f"{f(r['min_det_F'], '.2f')} | {f(r['dice'], '.4f')} | {f(r['msd_mm'], '.2f')} | {f(r['msd_voxels'], '.2f')} | "
            f"{f(r['hd95_mm'], '.2f')} | {f(r['volume_err_exact_pct'], '+.2f')} % | "
            f"{f(r['voxelise_seconds'], '.2f')} + {f(r['metrics_seconds'], '.2f')} | {memory(r)} |"
        )
    if done:
        out += [
            "",
            "### Where the registration time goes",
            "",
            "Exclusive wall time of each part (rank 0), as a share of the registration time. Sobolev factor+solve = "
            "the first Sobolev-gradient solve after the matrix was reassembled (LU factorisation + triangular solves, "
            "once per derivative, i.e. per iteration), Sobolev solve = further solves with the same LU (L-BFGS "
            "scaling); derivative = assembly of DΨ and of the Sobolev matrix; ψ = line-search evaluations of Ψ; "
            "image sampling = I and ∇I at the quadrature points (inside derivative and ψ); relax = the elastic "
            "extensions of the boundary displacement (lifting + solve; since 42b17cf their LU is factorised once, "
            "in setup); other = L-BFGS vector algebra, state updates, Python.",
            "",
        ]
        labels = PART_LABELS + ["other"]
        head = (
            "| mesh size [m] | spacing [mm] | solver | registration [s] | "
            + " | ".join(labels)
            + " | s per factor+solve | s per solve |"
        )
        out += [head, "|" + "---|" * (head.count("|") - 1)]
        for r in done:
            shares = [r[f"t_{key(label)}"] / r["registration_seconds"] for label in labels]
            per = [r[f"t_{k}"] / r[f"n_{k}"] if r[f"n_{k}"] else "" for k in ("sobolev_factor_solve", "sobolev_solve")]
            out.append(
                f"| {r['mesh_size']:g} | {r['spacing_mm']:g} | {r['solver']} | {f(r['registration_seconds'], '.1f')} | "
                + " | ".join(f"{s:.0%}" for s in shares)
                + f" | {f(per[0], '.3g')} ({r['n_sobolev_factor_solve']}×) | {f(per[1], '.3g')} ({r['n_sobolev_solve']}×) |"
            )
        out += ["", "### Notes (from the measured numbers above)", ""]
        out += [f"- {note}" for note in notes(done, skipped)]
    return "\n".join(out) + "\n"


def span(values, spec: str = ".0%", unit: str = "") -> str:
    lo, hi = format(min(values), spec), format(max(values), spec)
    return f"{lo}{unit}" if lo == hi else f"{lo}–{hi}{unit}"


def notes(done: list[dict], skipped: list[dict]) -> list[str]:
    items = []
    by = {(r["mesh_size"], r["spacing_mm"], r["solver"]): r for r in done}
    for solver in dict.fromkeys(r["solver"] for r in done):
        rs = [r for r in done if r["solver"] == solver]
        share = [sobolev_seconds(r) / r["registration_seconds"] for r in rs]
        biggest = max(rs, key=lambda r: r["registration_seconds"])
        items.append(
            f"Solver {solver}: the Sobolev-gradient solves take {span(share)} of the registration time; "
            f"the longest case ({biggest['mesh_size']:g} m, {biggest['spacing_mm']:g} mm) took "
            f"{biggest['registration_seconds']:.1f} s, {biggest['seconds_per_iteration']:.3f} s per iteration."
        )
    for other in dict.fromkeys(r["solver"] for r in done if r["solver"] != "default"):
        pairs = [(by[k], by[(k[0], k[1], "default")]) for k in by if k[2] == other and (k[0], k[1], "default") in by]
        if not pairs:
            continue
        ratio = [o["registration_seconds"] / d["registration_seconds"] for o, d in pairs]
        per_it = [o["seconds_per_iteration"] / d["seconds_per_iteration"] for o, d in pairs]
        solve = [
            (o["t_sobolev_factor_solve"] / o["n_sobolev_factor_solve"])
            / (d["t_sobolev_factor_solve"] / d["n_sobolev_factor_solve"])
            for o, d in pairs
        ]
        worst = max(pairs, key=lambda p: p[0]["registration_seconds"] / p[1]["registration_seconds"])
        ddice = max(abs(o["dice"] - d["dice"]) for o, d in pairs)
        its = [abs(o["iterations"] - d["iterations"]) for o, d in pairs]
        items.append(
            f"{other} / default registration time: {span(ratio, '.1f', '×')} over {len(pairs)} case(s) "
            f"({span(per_it, '.1f', '×')} per iteration, {span(solve, '.1f', '×')} per factorising Sobolev solve; "
            f"largest at {worst[0]['mesh_size']:g} m, {worst[0]['spacing_mm']:g} mm). The iteration counts differ by "
            f"{span(its, 'd')} (round-off in the line search), Dice by at most {ddice:.1e}."
        )
    solvers = list(dict.fromkeys(r["solver"] for r in done))
    first = "default" if "default" in solvers else solvers[0]
    for h in dict.fromkeys(r["mesh_size"] for r in done):
        rs = sorted((r for r in done if r["solver"] == first and r["mesh_size"] == h), key=lambda r: -r["spacing_mm"])
        if len(rs) > 1:
            items.append(
                f"{first}, mesh {h:g} m: spacing "
                + " → ".join(f"{r['spacing_mm']:g}" for r in rs)
                + " mm: iterations "
                + " → ".join(str(r["iterations"]) for r in rs)
                + ", registration "
                + " → ".join(f"{r['registration_seconds']:.1f}" for r in rs)
                + " s, s / it "
                + " → ".join(f"{r['seconds_per_iteration']:.3f}" for r in rs)
                + ", image-function builds (EDT + smoothing) "
                + " → ".join(f"{r['t_image_function']:.2f}" for r in rs)
                + " s, MSD "
                + " → ".join(f"{r['msd_voxels']:.2f}" for r in rs)
                + " voxels."
            )
    for r in skipped:
        items.append(
            f"Not run: {r['solver']} at mesh {r['mesh_size']:g} m, spacing {r['spacing_mm']:g} mm — {r['skip_reason']}."
        )
    unconverged = [r for r in done if not r["converged"]]
    if unconverged:
        items.append(
            "Not converged (a stage hit max_iterations): "
            + ", ".join(f"{r['solver']} {r['mesh_size']:g} m {r['spacing_mm']:g} mm" for r in unconverged)
            + "."
        )
    return items


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    done = [r for r in rows if r["status"] == "ok"]
    if not done:
        return
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.4))
    spacings = sorted(dict.fromkeys(r["spacing_mm"] for r in done), reverse=True)
    styles = {"default": ("-", "o"), "petsc": (":", "^"), "mumps": ("--", "s")}
    for i, s in enumerate(spacings):
        for solver, (ls, marker) in styles.items():
            rs = sorted((r for r in done if r["spacing_mm"] == s and r["solver"] == solver), key=lambda r: r["nodes"])
            if rs:
                left.loglog(
                    [r["nodes"] for r in rs],
                    [r["registration_seconds"] for r in rs],
                    ls=ls,
                    marker=marker,
                    color=f"C{i}",
                    label=f"{s:g} mm, {solver}",
                )
    left.set(
        xlabel="reference mesh nodes",
        ylabel="registration wall time [s]",
        title=f"register(): time vs mesh size ({done[0]['ranks']} rank(s))",
    )
    left.grid(True, which="both", alpha=0.3)
    left.legend(fontsize=7)
    meshes = sorted(dict.fromkeys(r["mesh_size"] for r in done), reverse=True)
    for i, h in enumerate(meshes):
        for solver, (ls, marker) in styles.items():
            rs = sorted(
                (r for r in done if r["mesh_size"] == h and r["solver"] == solver), key=lambda r: r["spacing_mm"]
            )
            if rs:
                right.plot(
                    [r["spacing_mm"] for r in rs],
                    [r["dice"] for r in rs],
                    ls=ls,
                    marker=marker,
                    color=f"C{i}",
                    label=f"{rs[0]['cells']:,} cells, {solver}",
                )
    right.set(xlabel="image spacing [mm]", ylabel="Dice (mapped mesh vs mask)", title="fit vs image resolution")
    right.invert_xaxis()
    right.grid(True, alpha=0.3)
    right.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def versions() -> dict:
    import dolfinx

    cpu, mem = cpu_and_memory()
    commit = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    dirty = subprocess.run(
        ["git", "-C", str(ROOT), "status", "--porcelain", "--", "lungmech"], capture_output=True, text=True
    ).stdout.split("\n")
    changed = [line[3:].strip() for line in dirty if line.strip()]
    note = f" (uncommitted changes in {', '.join(f'`{c}`' for c in changed)})" if changed else ""
    return {
        "dolfinx": dolfinx.__version__,
        "petsc": ".".join(map(str, PETSc.Sys.getVersion())),
        "numpy": np.__version__,
        "python": platform.python_version(),
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory": mem,
        "commit": commit + note,
    }


def header(v: dict, load: tuple, done: bool, warmup: float, packages: dict, per_case: bool) -> list[str]:
    o = Options()
    status = "" if done else " — RUN IN PROGRESS, partial table"
    return [
        f"# Shape registration: time and iterations against mesh size and image resolution{status}",
        "",
        f"- Date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}; machine: {v['cores']} cores "
        f"({v['cpu']}), {v['memory']}; 1-min load average at start {load[0]:.2f}, at the end {os.getloadavg()[0]:.2f} "
        "(this run's own ranks count; above the number of ranks, other work shared the machine; per case in the CSV).",
        f"- DOLFINx {v['dolfinx']}, PETSc {v['petsc']}, NumPy {v['numpy']}, Python {v['python']}; lungmech at {v['commit']}; "
        f"{COMM.size} MPI rank(s); OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}.",
        f"- Command: `{' '.join(['python benchmarks/registration.py', os.environ.get('REGISTRATION_BENCH_COMMAND', ' '.join(sys.argv[1:]))]).strip()}`"
        f"{f' (= mpiexec -n {COMM.size} python benchmarks/registration.py ...)' if COMM.size > 1 else ''}; "
        f"total wall time {(time.perf_counter() - STARTED) / 60:.1f} min.",
        '- Reference Ω: `lung_phantom(comm, mesh_size=h, side="right")` (P1 tetrahedra; h = 0.0176 is the bundled '
        "`lungmech/meshes/lung_phantom_right.msh`). Target: `voxelise(LungShape("
        + ", ".join(f"{k}={val:g}" for k, val in TARGET.items())
        + f"), spacing, offset={OFFSET})` — exact ground truth, "
        "another shape than the reference's (taller, narrower, shallower, other apex and dome), moved by the offset.",
        f"- `register(mesh, image, Options())` with lungmech's defaults: stages {tuple(o.stages)} voxels of smoothing, "
        f"{o.image_function} image function, L-BFGS memory {o.memory}, step_tolerance {o.step_tolerance} voxel, "
        f"stagnation {o.stagnation}, min_jacobian {o.min_jacobian}, max_iterations {o.max_iterations} per stage. "
        f"Solver `default` = `Options().solver` as it is ({dict(o.solver)}: LU package `{packages.get('default', '?')}` "
        f"on {COMM.size} rank(s))"
        + "".join(
            f"; `{name}` = {SOLVERS[name]} (`{packages.get(name, '?')}`)" for name in packages if name != "default"
        )
        + ". The solver serves the Sobolev-gradient solves and the elastic extension (relax); nothing else differs.",
        f"- Registration [s]: wall time of `register()` (MPI barriers around it), warm JIT: a 2-iteration warm-up "
        f"registration ran first ({warmup:.1f} s, not in the table). s / it = registration / total iterations (all "
        "stages; the time includes the similarity fit, the image-function builds and the final elastic extension). "
        "Metrics: `lungmech.registration.metrics.report` on the mesh moved by the mapping (`nodes.deformed`): Dice of "
        "the voxelised mesh against the mask, MSD = mean symmetric surface distance, hd95; vol. err. vs exact = "
        "enclosed volume of the mapped mesh / `LungShape.volume()` − 1 (the mask's own volume is in the CSV). "
        "voxelise = `phantom.voxelise` of the target; metrics = `metrics.report`.",
        "- Peak RSS: "
        + (
            "the process's VmHWM during voxelise + register, and during metrics (reset through "
            "/proc/self/clear_refs before each, so it includes the resident baseline — libraries, the "
            "reference mesh — `rss_start_mb` in the CSV)"
            if per_case
            else "getrusage ru_maxrss (the process's peak so far, not per case)"
        )
        + ("; max over ranks (sum over ranks in brackets)." if COMM.size > 1 else "."),
    ]


def write(rows: list[dict], prefix: str, lines: list[str], with_plot: bool) -> None:
    if not RANK0:
        return
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{prefix}.md").write_text(markdown(rows, lines))
    with open(RESULTS / f"{prefix}.csv", "w", newline="") as stream:
        writer = csv.DictWriter(stream, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    if with_plot:
        plot(rows, RESULTS / f"{prefix}.png")


def too_costly(rows: list[dict], h: float, spacing: float, solver: str, budget: float) -> str:
    for r in rows:
        if r["solver"] != solver or r["status"] != "ok" or r["registration_seconds"] <= budget:
            continue
        if (r["mesh_size"] == h and r["spacing_mm"] > spacing) or (r["spacing_mm"] == spacing and r["mesh_size"] > h):
            return (
                f"the smaller case {r['mesh_size']:g} m, {r['spacing_mm']:g} mm took {r['registration_seconds']:.0f} s "
                f"> --budget {budget:g} s ({r['seconds_per_iteration']:.2f} s per iteration)"
            )
    return ""


def main() -> None:
    args = ARGS
    load = os.getloadavg()
    prefix = args.prefix or ("registration_quick" if args.quick else "registration")
    mesh_sizes = (
        [float(x) for x in args.mesh_sizes.split(",")]
        if args.mesh_sizes
        else list(QUICK_MESH_SIZES if args.quick else MESH_SIZES)
    )
    spacings = (
        [float(x) for x in args.spacings.split(",")]
        if args.spacings
        else list(QUICK_SPACINGS if args.quick else SPACINGS)
    )
    solvers = args.solvers.split(",")
    if unknown := [s for s in solvers if s not in SOLVERS]:
        raise SystemExit(f"unknown solver(s) {unknown}; choose from {list(SOLVERS)}")
    mesh_sizes.sort(reverse=True)
    spacings.sort(reverse=True)
    v = versions()
    packages = {name: factor_package(SOLVERS[name]) for name in solvers}
    shape = LungShape(side="right", **TARGET)
    rows: list[dict] = []
    warmup = None
    per_case = False
    for h in mesh_sizes:
        ref = reference_mesh(h)
        say(f"mesh_size {h:g} m: {ref.cells:,} cells, {ref.nodes:,} nodes ({ref.mesh_seconds:.1f} s to mesh)")
        if warmup is None:  # compile the forms once, untimed (the JIT cache is then warm for every case)
            t0 = tic()
            register(ref.mesh, voxelise(shape, spacings[0] * 1e-3, offset=OFFSET), Options(max_iterations=2))
            warmup = toc(t0)
            say(f"warm-up registration: {warmup:.1f} s")
        for spacing in spacings:
            for solver in solvers:
                reason = too_costly(rows, h, spacing, solver, args.budget)
                if reason:
                    rows.append(
                        {
                            "mesh_size": h,
                            "cells": ref.cells,
                            "nodes": ref.nodes,
                            "dofs": 3 * ref.nodes,
                            "spacing_mm": spacing,
                            "image_shape": "",
                            "voxels": 0,
                            "solver": solver,
                            "ranks": COMM.size,
                            "status": "skipped",
                            "skip_reason": reason,
                        }
                    )
                    say(f"  {spacing:g} mm, {solver}: skipped: {reason}")
                    rows[-1]["image_shape"] = "x".join(map(str, voxelise(shape, spacing * 1e-3, offset=OFFSET).shape))
                    rows[-1]["voxels"] = int(np.prod([int(n) for n in rows[-1]["image_shape"].split("x")]))
                    continue
                row = run_case(ref, spacing, solver, shape)
                per_case = per_case or row["peak_per_case"]
                rows.append(row)
                say(
                    f"  {spacing:g} mm, {solver}: {row['registration_seconds']:.1f} s, {row['iterations']} its "
                    f"({row['stage_iterations'].replace(';', ' + ')}), {row['seconds_per_iteration']:.3f} s/it, "
                    f"Sobolev solves {sobolev_seconds(row) / row['registration_seconds']:.0%}, "
                    f"Dice {row['dice']:.4f}, MSD {row['msd_mm']:.2f} mm ({row['msd_voxels']:.2f} vox), "
                    f"min det F {row['min_det_F']:.2f}, peak {row['peak_rss_mb']:.0f} MB"
                )
                write(rows, prefix, header(v, load, False, warmup, packages, per_case), False)
        del ref
    write(rows, prefix, header(v, load, True, warmup, packages, per_case), not args.no_plot)
    if RANK0:
        print((RESULTS / f"{prefix}.md").read_text())


if __name__ == "__main__":
    main()
