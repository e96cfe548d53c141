"""The speed–accuracy trade of reduced-order models (lungmech.rom), measured.

    python benchmarks/rom.py                 # lung (>= 50k dofs) + hyperelastic beams
    python benchmarks/rom.py --quick         # bundled 6.5k-dof lung mesh, coarse beam (< 3 min)
    python benchmarks/rom.py --ranks 2       # the same under mpiexec -n 2 (re-launches itself)
    mpiexec -n 2 python benchmarks/rom.py    # equivalent

Two cases: the breathing lung of lungmech/scenes/lung_breathing.toml (mixed (u, Φs)
poromechanics, unloaded reference found first, breaths of different tidal depth), and a
neo-Hookean cantilever under body force (displacement only). For each basis kind (POD,
polynomial, modal, modal + modal derivatives) and size k, on test loads that are NOT in the
training set: relative error in the energy norm and in deformed volume, the best-approximation
(projection) error in the same norm, online time (warm, median of repeats), full-model time on
the same ranks, speed-up, offline time split, and where the online time goes (assembly of the
full residual and tangent vs the projections and the k × k solve). Writes
benchmarks/results/rom.{md,csv}, rom_pareto.png and raw/rom-<case>.json (--quick: rom_quick.*).
See benchmarks/README.md.
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
    say,
    tic,
    toc,
)  # benchmarks/ is the script folder, first on sys.path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = machine.RESULTS
RAW = RESULTS / "raw"
SIZES = (2, 5, 10, 20, 40, 80)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="smoke run: bundled lung mesh, coarse beam, k in {2, 5, 20}")
    p.add_argument("--ranks", type=int, default=1, help="re-launch under mpiexec -n RANKS (default 1)")
    p.add_argument("--cases", default=None, help="comma list of lung, beam, beam-large (default: lung,beam,beam-large)")
    p.add_argument("--sizes", default=None, help="basis sizes k (default 2,5,10,20,40,80)")
    p.add_argument(
        "--lung-mesh-size",
        type=float,
        default=0.007,
        help="gmsh size of lung_phantom (0.007: 53k dofs); ignored with --quick (bundled scene mesh)",
    )
    p.add_argument("--lung-train", default="0.5,1.5", help="tidal depths of the training breaths")
    p.add_argument(
        "--lung-test", default="1.25,1.75", help="tidal depths of the test breaths (> max train: extrapolation)"
    )
    p.add_argument(
        "--lung-step",
        type=float,
        default=0.125,
        help="initial and largest load step of every lung breath, full and reduced (the scene's is 0.1; see README)",
    )
    p.add_argument(
        "--lung-easy",
        type=int,
        default=20,
        help="Stepping.easy_iterations of the lung: a step that took at most this many Newton iterations "
        "(summed over the balanced-gravity fixed point, ~12-16 per step) lets the next one grow",
    )
    p.add_argument(
        "--line-search",
        default="cp",
        help="NewtonOptions.line_search of the full model (reduced: backtracking "
        "unless none/basic); the lung scene's default bt cuts the lung's steps, see README",
    )
    p.add_argument("--beam-cells", default="60,6,6", help="cells of the 10 x 1 x 1 beam (60,6,6: 9k dofs)")
    p.add_argument(
        "--repeats",
        type=int,
        default=None,
        help="timed runs at the timing load (median), full and reduced (default 3; --quick: 2)",
    )
    p.add_argument(
        "--budget",
        type=float,
        default=1.5,
        help="a reduced run is stopped after BUDGET x the full model's time for the same load",
    )
    p.add_argument("--min-budget", type=float, default=10.0, help="... but never before MIN_BUDGET seconds")
    p.add_argument(
        "--replot",
        action="store_true",
        help="run nothing: rebuild PREFIX.md, .csv and _pareto.png from results/raw/PREFIX-<case>.json",
    )
    p.add_argument("--prefix", default=None, help="output file stem (default rom, --quick: rom_quick)")
    return p.parse_args(argv)


ARGS = parse_args()
relaunch(ARGS.ranks, __file__, "ROM_BENCH_COMMAND")
# One BLAS thread per process: NumPy's OpenBLAS otherwise spins threads that fight MPI ranks and
# other work for the cores (measured: reduced_jacobian at k = 20 became 2-10x slower on a busy machine).
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

# --- heavy imports only in the process that does the work -------------------------------------
import csv  # noqa: E402
import dataclasses  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402

from mpi4py import MPI  # noqa: E402  (first: it loads the MPI library dolfinx links to)
from petsc4py import PETSc  # noqa: E402

import numpy as np  # noqa: E402
from dolfinx import fem, la  # noqa: E402
from dolfinx.fem.petsc import assemble_matrix, create_matrix  # noqa: E402

from lungmech import rom  # noqa: E402
from lungmech.app.run import build_model  # noqa: E402
from lungmech.app.scene import load as load_scene  # noqa: E402
from lungmech.errors import LungmechError, SolverError  # noqa: E402
from lungmech.fem.constraints import clamp  # noqa: E402
from lungmech.fem.loads import BodyForce  # noqa: E402
from lungmech.fem.materials import NeoHookean  # noqa: E402
from lungmech.fem.model import Model  # noqa: E402
from lungmech.fem.quantities import deformed_volume  # noqa: E402
from lungmech.fem.solver import NewtonOptions, NewtonSolver, Stepping, solve  # noqa: E402
from lungmech.lung.inverse import unloaded_reference  # noqa: E402
from lungmech.mesh import box, lung_phantom  # noqa: E402
from lungmech.parallel.linalg import apply, gram  # noqa: E402

COMM = MPI.COMM_WORLD
RANK0 = COMM.rank == 0
logging.getLogger("lungmech").setLevel(logging.WARNING)


# --- cases -------------------------------------------------------------------------------------


@dataclasses.dataclass
class Test:
    scale: tuple[float, ...]
    label: str  # "interp", "extrap", "direction"
    timing: bool = False  # the load whose runs are repeated and timed (median)

    @property
    def name(self) -> str:
        return "(" + ", ".join(f"{s:g}" for s in self.scale) + ")"


@dataclasses.dataclass
class Case:
    name: str
    title: str
    model: Model
    options: NewtonOptions
    stepping: Stepping  # times include the output times and the ramps' breakpoints
    outputs: tuple[float, ...]
    train: list[tuple[float, ...]]
    tests: list[Test]
    kinds: tuple[str, ...]
    about: float = 0.0
    offline: dict = dataclasses.field(default_factory=dict)
    notes: list[str] = dataclasses.field(default_factory=list)
    start: np.ndarray | None = None
    full: NewtonSolver | None = None
    description: dict = dataclasses.field(default_factory=dict)


def dofs(model) -> int:
    return model.space.dofmap.index_map.size_global * model.space.dofmap.index_map_bs


def owned(model) -> int:
    return model.space.dofmap.index_map.size_local * model.space.dofmap.index_map_bs


def cells(model) -> int:
    mesh = model.geometry.mesh
    return mesh.topology.index_map(mesh.topology.dim).size_global


def lung_case(args) -> Case:
    scene = load_scene(ROOT / "lungmech" / "scenes" / "lung_breathing.toml")
    t0 = tic()
    if args.quick:
        model = build_model(scene, COMM)  # the scene's own mesh: lung_phantom at its default size (6.5k dofs)
        mesh_note = "lung_phantom(side='right') at its default size, as the scene builds it (= lungmech/meshes/lung_phantom_right.msh)"
    else:
        geometry = lung_phantom(COMM, mesh_size=args.lung_mesh_size, side=scene.geometry.get("side", "right"))
        model = Model(
            geometry,
            scene.material,
            degree=scene.degree,
            formulation=scene.formulation,
            loads=scene.loads,
            constraints=scene.constraints,
        )
        mesh_note = f"lung_phantom(side='right', mesh_size={args.lung_mesh_size})"
    build = toc(t0)
    outputs = (0.5, 1.0, 1.5, 2.0)
    step = args.lung_step
    stepping = dataclasses.replace(
        scene.stepping,
        initial_step=step,
        max_step=step,
        min_step=1e-3,
        easy_iterations=args.lung_easy,
        times=tuple(
            sorted(
                t
                for t in {*scene.stepping.times, *outputs, *model.breakpoints}
                if scene.stepping.start < t <= scene.stepping.end
            )
        ),
    )
    train = [(float(s), 1.0) for s in args.lung_train.split(",")]
    top = max(s for s, _ in train)
    tests = []
    for s in (float(x) for x in args.lung_test.split(",")):
        tests.append(Test((s, 1.0), "extrap" if s > top or s < min(x for x, _ in train) else "interp"))
    interp = [t for t in tests if t.label == "interp"] or tests
    interp[len(interp) // 2].timing = True
    case = Case(
        "lung",
        "Breathing right lung (lung_breathing.toml), mixed (u P1, Φs DG0) poromechanics",
        model,
        dataclasses.replace(scene.newton, line_search=args.line_search),
        stepping,
        outputs,
        train,
        tests,
        ("pod", "polynomial", "modal", "modal+derivatives"),
        about=scene.stepping.start,
    )
    case.offline["build"] = build
    case.description = {
        "mesh": mesh_note,
        "load": "pleural follower pressure −500 Pa at t = 0, ramp 1 → 2 → 1 on t ∈ [0, 2], "
        "scaled about t = 0 by the tidal depth s; balanced gravity (state-dependent) constant",
        "scales": "(s, 1): s scales the pleural pressure's change since t = 0, gravity stays",
        "stepping": f"initial = max step {step}, min step 1e-3, growth {stepping.growth} after steps of at most "
        f"{args.lung_easy} Newton iterations (summed over the gravity fixed point), halved after a failure; the same for full "
        "and reduced; outputs at t = " + ", ".join(f"{t:g}" for t in outputs),
    }
    return case


def beam_case(args, large: bool) -> Case:
    nx, ny, nz = (int(n) for n in ("20,2,2" if args.quick else args.beam_cells).split(","))
    t0 = tic()
    geometry = box(COMM, lengths=(10.0, 1.0, 1.0), cells=(nx, ny, nz))
    model = Model(
        geometry,
        NeoHookean.from_young(100.0, 0.3),
        loads=[BodyForce((0.0, 0.0, -1.0)), BodyForce((0.0, -1.0, 0.0))],
        constraints=[clamp("x0")],
    )
    build = toc(t0)
    outputs = (0.25, 0.5, 0.75, 1.0)
    stepping = Stepping(end=1.0, initial_step=0.1, max_step=0.1, min_step=1e-3, times=outputs)
    f = 0.1 if large else 0.01
    train = [(f, 0.0), (2 * f, 0.0), (3 * f, 0.0)]
    tests = [
        Test((1.5 * f, 0.0), "interp"),
        Test((2.5 * f, 0.0), "interp", timing=True),
        Test((3.5 * f, 0.0), "extrap"),
        Test((2 * f, f), "direction"),
    ]
    name = "beam-large" if large else "beam"
    span = (
        "0.1–0.35: the beam hangs (tip drop 70–95 % of its length)"
        if large
        else "0.01–0.035: tip deflection 10–35 % of the length"
    )
    case = Case(
        name,
        f"Neo-Hookean cantilever 10 × 1 × 1 (E = 100, ν = 0.3), clamped at x = 0, body force {span}",
        model,
        NewtonOptions(line_search=args.line_search),
        stepping,
        outputs,
        train,
        tests,
        ("pod", "polynomial", "modal", "modal+derivatives"),
    )
    case.offline["build"] = build
    case.description = {
        "mesh": f"box(lengths=(10, 1, 1), cells=({nx}, {ny}, {nz})), P1 tetrahedra",
        "load": "body forces (0, 0, −1) and (0, −1, 0) per unit volume, default ramp 0 → 1 on t ∈ [0, 1]",
        "scales": "(f_z, f_y)",
        "stepping": "initial = max step 0.1, min step 1e-3, growth 1.5; outputs at t = 0.25, 0.5, 0.75, 1",
    }
    return case


# --- solves ------------------------------------------------------------------------------------


class OverBudget(Exception):
    pass


class Counted:
    """Delegates solve() to a Newton or reduced solver; counts iterations; stops at a deadline."""

    def __init__(self, inner, deadline: float | None = None):
        self.inner, self.deadline = inner, deadline
        self.iterations = self.calls = 0
        self.last_reason = ""

    def __getattr__(self, name):  # the rest of the Solver protocol: the inner solver's
        return getattr(self.inner, name)

    def solve(self):
        if self.deadline is not None and COMM.bcast(time.perf_counter() > self.deadline, root=0):
            raise OverBudget()
        result = self.inner.solve()
        self.calls += 1
        self.iterations += result.iterations
        self.last_reason = result.reason
        return result


def breath(case: Case, solver, scale, budget: float | None = None) -> dict:
    """One load history from the start state; the states at the output times, time, counts."""
    model = case.model
    model.state.x.array[:] = case.start
    model.state.x.scatter_forward()
    states: dict[float, np.ndarray] = {}

    def record(step) -> None:
        for t in case.outputs:
            if abs(model.time - t) < 1e-9:
                states[t] = model.state.x.array.copy()

    t0 = tic()
    counted = Counted(solver, None if budget is None else time.perf_counter() + budget)
    status, reason, steps, failed = "ok", "", 0, 0
    try:
        report = solve(
            model,
            case.stepping,
            solver=counted,
            drive=lambda t: model.set_time(t, load_factor=scale, about=case.about),
            on_step=record,
        )
        steps, failed = len(report.accepted), report.failures
    except SolverError:
        status, reason = "did not converge", f"stopped at t = {model.time:.4g} ({counted.last_reason})"
    except OverBudget:
        status, reason = "stopped", f"over the time budget ({budget:.0f} s) at t = {model.time:.4g}"
    seconds = toc(t0)
    return {
        "status": status,
        "reason": reason,
        "seconds": seconds,
        "states": states,
        "newton": counted.iterations,
        "newton_calls": counted.calls,
        "steps": steps,
        "failed_steps": failed,
    }


def knorm(K, x: np.ndarray) -> float:
    return float(np.sqrt(max(gram(x[:, None], apply(K, x[:, None], COMM), COMM)[0, 0], 0.0)))


class Metrics:
    """Energy norm, volume and projection errors against the full model at the output times."""

    def __init__(self, case: Case, K: PETSc.Mat):
        self.case, self.K = case, K
        self.n = owned(case.model)
        space = case.model.space
        self.u_dofs = np.arange(self.n) if not case.model.mixed else np.asarray(space.sub(0).collapse()[1])
        self.u_dofs = self.u_dofs[self.u_dofs < self.n]
        self.volume = deformed_volume(case.model)
        self.reference: dict[str, dict] = {}  # per test: full states, |d|_K, volumes
        case.model.state.x.array[:] = case.start
        self.v0 = self.volume()

    def vol(self, x: np.ndarray) -> float:
        self.case.model.state.x.array[:] = x
        self.case.model.state.x.scatter_forward()
        return self.volume()

    def add_full(self, test: Test, states: dict[float, np.ndarray]) -> None:
        d = {t: (x - self.case.start)[: self.n] for t, x in states.items()}
        self.reference[test.name] = {
            "states": states,
            "d": d,
            "dnorm": {t: knorm(self.K, v) for t, v in d.items()},
            "volume": {t: self.vol(x) for t, x in states.items()},
        }

    def umax(self, x: np.ndarray) -> float:
        return COMM.allreduce(float(np.abs(x[self.u_dofs]).max(initial=0.0)), op=MPI.MAX)

    def errors(self, test: Test, states: dict[float, np.ndarray]) -> dict:
        ref = self.reference[test.name]
        if set(states) != set(ref["states"]):
            return {}
        umax = max(self.umax(d) for d in ref["d"].values())
        disp = max(self.umax(states[t] - ref["states"][t]) for t in states) / umax
        energy = {t: knorm(self.K, (states[t] - ref["states"][t])[: self.n]) for t in states}
        volume = {t: self.vol(states[t]) for t in states}
        dv = {t: abs(volume[t] - ref["volume"][t]) for t in states}
        tidal = max(abs(ref["volume"][t] - self.v0) for t in states)
        return {
            "energy_err": max(energy.values()) / max(ref["dnorm"].values()),
            "disp_err": disp,
            "volume_err_rel": max(dv[t] / ref["volume"][t] for t in states),
            "volume_err_tidal": max(dv.values()) / tidal if tidal > 0 else float("nan"),
            "energy_err_by_time": ";".join(
                f"{t:g}:{energy[t] / max(ref['dnorm'].values()):.3e}" for t in sorted(states)
            ),
        }

    def projection(self, test: Test, V: np.ndarray, KV: np.ndarray) -> float:
        ref = self.reference[test.name]
        G = gram(V, KV, COMM)
        worst = 0.0
        for d in ref["d"].values():
            c = np.linalg.lstsq(G, gram(KV, d[:, None], COMM)[:, 0], rcond=None)[0]
            worst = max(worst, knorm(self.K, d - V @ c))
        return worst / max(ref["dnorm"].values())


# --- where the online time goes ----------------------------------------------------------------


def median_time(f, repeats: int = 5) -> float:
    samples = []
    for _ in range(repeats):
        t0 = tic()
        f()
        samples.append(toc(t0))
    return float(np.median(samples))


def reduced_cost_split(solver: rom.ReducedSolver) -> dict:
    """Seconds of each part of a reduced Newton iteration, at the model's current state."""
    q = solver.project()
    # the solver's own compiled forms, into a vector and a matrix of this function's (the same work)
    vec, A = fem.Function(solver.model.space).x, create_matrix(solver.jacobian_form)

    def residual_assembly():
        vec.array[:] = 0.0
        fem.assemble_vector(vec.array, solver.residual_form)
        vec.scatter_reverse(la.InsertMode.add)

    def jacobian_assembly():
        A.zeroEntries()
        assemble_matrix(A, solver.jacobian_form)
        A.assemble()

    residual_assembly()
    jacobian_assembly()
    Kr = gram(solver.V, apply(A, solver.V, COMM), COMM)
    r = gram(solver.V, vec.array[: solver.owned, None], COMM)[:, 0]
    out = {
        "res_assembly": median_time(residual_assembly),
        "res_projection": median_time(lambda: gram(solver.V, vec.array[: solver.owned, None], COMM)),
        "reconstruct": median_time(lambda: solver.reconstruct(q)),
        "jac_assembly": median_time(jacobian_assembly),
        "jac_projection": median_time(lambda: gram(solver.V, apply(A, solver.V, COMM), COMM)),
        "small_solve": median_time(lambda: np.linalg.solve(Kr, -r), 20),
    }
    solver.reconstruct(q)
    A.destroy()
    return out


def full_cost_split(case: Case) -> dict:
    """Residual and tangent assembly and one MUMPS LU factorisation + solve of the full model."""
    model, problem = case.model, case.full.problem
    residual, jacobian = fem.form(model.residual), fem.form(model.jacobian)
    vec = fem.Function(model.space).x
    A = problem.A

    def residual_assembly():
        vec.array[:] = 0.0
        fem.assemble_vector(vec.array, residual)
        vec.scatter_reverse(la.InsertMode.add)

    def jacobian_assembly():
        A.zeroEntries()
        assemble_matrix(A, jacobian, bcs=model.bcs)
        A.assemble()

    out = {"res_assembly": median_time(residual_assembly), "jac_assembly": median_time(jacobian_assembly)}
    b, x = A.createVecRight(), A.createVecRight()
    b.set(1.0)

    def factor_solve():
        ksp = PETSc.KSP().create(COMM)
        ksp.setOperators(A)
        ksp.setType("preonly")
        pc = ksp.getPC()
        pc.setType("lu")
        pc.setFactorSolverType("mumps")
        pc.setFactorSetUpSolverType()
        pc.getFactorMatrix().setMumpsIcntl(14, 200)
        ksp.setUp()
        ksp.solve(b, x)
        ksp.destroy()

    out["lu_factor_solve"] = median_time(factor_solve, 3)
    b.destroy()
    x.destroy()
    return out


# --- bases -------------------------------------------------------------------------------------


def instrument(solver: rom.ReducedSolver) -> dict:
    """Count and time reduced_residual / reduced_jacobian calls (instance attributes shadow the methods)."""
    tally = {"residual_evals": 0, "jacobian_evals": 0, "seconds_residual": 0.0, "seconds_jacobian": 0.0}
    residual, jacobian = solver.reduced_residual, solver.reduced_jacobian

    def timed_residual(q):
        t0 = time.perf_counter()
        out = residual(q)
        tally["residual_evals"] += 1
        tally["seconds_residual"] += time.perf_counter() - t0
        return out

    def timed_jacobian():
        t0 = time.perf_counter()
        out = jacobian()
        tally["jacobian_evals"] += 1
        tally["seconds_jacobian"] += time.perf_counter() - t0
        return out

    solver.reduced_residual, solver.reduced_jacobian = timed_residual, timed_jacobian
    return tally


def derivative_modes(k: int) -> int:
    """The most modes m whose basis with all m(m+1)/2 modal derivatives has at most k vectors."""
    m = 1
    while (m + 1) + (m + 1) * (m + 2) // 2 <= k:
        m += 1
    return m


def polynomial_order(components: int, k: int) -> int:
    order = 1
    while (
        components * len([p for p in np.ndindex(order + 1, order + 1, order + 1) if sum(p) <= order]) < k and order < 6
    ):
        order += 1
    return order


def bases_for(case: Case, kind: str, sizes: list[int], snapshots: np.ndarray | None) -> dict:
    """{k: (Basis or None, note, offline dict)} for one kind."""
    model = case.model
    out = {}
    if kind == "pod":
        t0 = tic()
        basis = rom.pod(model, snapshots, inner="energy")
        seconds = toc(t0)
        case.offline["pod_seconds"] = seconds
        case.offline["pod_significant"] = basis.size
        case.offline["singular_values"] = basis.source["singular_values"]
        for k in sizes:
            offline = {"snapshots": case.offline["snapshots_seconds"], "eigen": seconds, "build": 0.0}
            if k <= basis.size:
                out[k] = (basis.truncate(k), "", offline)
            else:
                out[k] = (None, f"n/a (only {basis.size} significant directions)", offline)
        return out
    if kind == "polynomial":
        components = 4 if model.mixed else 3
        order = polynomial_order(components, max(sizes))
        t0 = tic()
        basis = rom.polynomial_basis(model, order, inner="energy")
        seconds = toc(t0)
        for k in sizes:
            offline = {"snapshots": 0.0, "eigen": 0.0, "build": seconds}
            out[k] = (
                (basis.truncate(k), f"order {order}, truncated", offline)
                if k <= basis.size
                else (None, f"n/a (order-{order} basis has {basis.size} vectors)", offline)
            )
        return out
    # modal and modal + derivatives: displacement-only models
    model.reset()
    model.set_time(case.stepping.start)
    for k in sizes:
        try:
            if kind == "modal":
                t0 = tic()
                basis = rom.modal_basis(model, k)
                out[k] = (basis, "", {"snapshots": 0.0, "eigen": toc(t0), "build": 0.0})
            else:
                m = derivative_modes(k)
                t0 = tic()
                modes = rom.modal_basis(model, m)
                eigen = toc(t0)
                t0 = tic()
                basis = rom.with_modal_derivatives(model, modes)
                out[k] = (
                    basis,
                    f"{m} modes + {m * (m + 1) // 2} derivatives",
                    {"snapshots": 0.0, "eigen": eigen, "build": toc(t0)},
                )
        except LungmechError as error:
            out[k] = (None, f"n/a ({error})", {})
    model.state.x.array[:] = case.start
    return out


# --- one case ----------------------------------------------------------------------------------


def run_case(case: Case, args, sizes: list[int]) -> tuple[list[dict], dict]:
    model = case.model
    say(f"{case.name}: {dofs(model)} dofs, {cells(model)} cells, {COMM.size} rank(s)")
    t0 = tic()
    case.full = NewtonSolver(model, case.options)
    case.offline["compile"] = toc(t0)
    if case.name == "lung":
        scene = load_scene(ROOT / "lungmech" / "scenes" / "lung_breathing.toml")
        t0 = tic()
        # The scene's own solver settings (bt) for the inverse: with cp, a direct solve on a corrected reference
        # stalled at DIVERGED_MAX_IT on the 53k-dof mesh.
        inverse_solver = NewtonSolver(model, scene.newton)
        report = unloaded_reference(model, scene.stepping.start, scene.inverse, solver=inverse_solver)
        inverse_solver.destroy()
        case.offline["inverse"] = toc(t0)
        case.offline["inverse_iterations"] = report.iterations
        case.offline["inverse_newton"] = report.newton_iterations
        say(
            f"  inverse: {report.iterations} fixed-point iterations, {report.newton_iterations} Newton its, "
            f"{case.offline['inverse']:.1f} s"
        )
    else:
        model.reset()
        case.offline["inverse"] = 0.0
    model.set_time(case.stepping.start)
    case.start = model.state.x.array.copy()

    # Offline: training snapshots with the full model (this also warms its forms).
    t0 = tic()
    S = rom.snapshots(model, case.stepping, case.train, solver=case.full, start=case.start)
    case.offline["snapshots_seconds"] = toc(t0)
    case.offline["snapshots"] = S.shape[1]
    say(f"  snapshots: {S.shape[1]} from {len(case.train)} runs, {case.offline['snapshots_seconds']:.1f} s")

    t0 = tic()
    K = rom.inner_product(model, "energy")
    case.offline["energy_matrix_seconds"] = toc(t0)
    metrics = Metrics(case, K)

    # Full model on the test loads: reference states and timing.
    full_runs: dict[str, dict] = {}
    for test in case.tests:
        runs = [breath(case, case.full, test.scale) for _ in range(args.repeats if test.timing else 1)]
        if runs[0]["status"] != "ok":
            raise SystemExit(f"{case.name}: the full model failed on the test load {test.name}: {runs[0]['reason']}")
        metrics.add_full(test, runs[0]["states"])
        full_runs[test.name] = {
            "seconds": [r["seconds"] for r in runs],
            "newton": runs[0]["newton"],
            "newton_calls": runs[0]["newton_calls"],
            "steps": runs[0]["steps"],
            "failed_steps": runs[0]["failed_steps"],
            "volume": metrics.reference[test.name]["volume"],
        }
        say(
            f"  full {test.name} [{test.label}]: {', '.join(f'{s:.2f}' for s in full_runs[test.name]['seconds'])} s, "
            f"{runs[0]['newton']} Newton its, {runs[0]['steps']} steps (+{runs[0]['failed_steps']} failed)"
        )
    model.state.x.array[:] = metrics.reference[next(t.name for t in case.tests if t.timing)]["states"][case.outputs[1]]
    case.offline["full_split"] = full_cost_split(case)
    say(f"  full model per Newton iteration: {fmt_split(case.offline['full_split'])}")

    rows = []
    for test in case.tests:
        fr = full_runs[test.name]
        rows.append(
            base_row(case)
            | {
                "kind": "full",
                "k": dofs(model),
                "size": dofs(model),
                "status": "ok",
                "scale": test.name,
                "label": test.label,
                "timing_load": test.timing,
                "runs": len(fr["seconds"]),
                "online_seconds": float(np.median(fr["seconds"])),
                "online_seconds_first": fr["seconds"][0],
                "online_seconds_all": ";".join(f"{s:.4f}" for s in fr["seconds"]),
                "full_seconds": float(np.median(fr["seconds"])),
                "speedup": 1.0,
                "newton_iterations": fr["newton"],
                "newton_calls": fr["newton_calls"],
                "steps": fr["steps"],
                "failed_steps": fr["failed_steps"],
                "energy_err": 0.0,
                "projection_err": 0.0,
                "disp_err": 0.0,
                "volume_err_rel": 0.0,
                "volume_err_tidal": 0.0,
                "volume_max": max(fr["volume"].values()),
                "volume_start": metrics.v0,
                **{f"split_{k}": v for k, v in case.offline["full_split"].items()},
            }
        )

    for kind in case.kinds:
        bases = bases_for(case, kind, sizes, S)
        KV_cache = None
        for k in sizes:
            basis, note, offline = bases[k]
            common = base_row(case) | {
                "kind": kind,
                "k": k,
                "note": note,
                **{f"offline_{n}": v for n, v in offline.items()},
            }
            if offline:
                common["offline_total"] = case.offline["inverse"] + sum(offline.values())
            if basis is None:
                rows.append(common | {"status": note or "n/a", "size": "", "label": "all", "timing_load": False})
                say(f"  {kind} k={k}: {note}")
                continue
            if kind in ("pod", "polynomial"):  # nested bases: K·V once for the largest size
                if KV_cache is None or KV_cache.shape[1] < basis.size:
                    KV_cache = apply(
                        K,
                        np.ascontiguousarray(bases[max(s for s in sizes if bases[s][0] is not None)][0].vectors),
                        COMM,
                    )
                KV = KV_cache[:, : basis.size]
            else:
                KV = apply(K, np.ascontiguousarray(basis.vectors), COMM)
            t0 = tic()
            reduced = rom.ReducedSolver(model, basis, case.options, start=case.start)
            setup = toc(t0)
            tally = instrument(reduced)
            split = None
            for test in case.tests:
                fr = full_runs[test.name]
                full_seconds = float(np.median(fr["seconds"]))
                budget = max(args.budget * full_seconds, args.min_budget)
                for key in tally:
                    tally[key] = 0 if isinstance(tally[key], int) else 0.0
                runs = [breath(case, reduced, test.scale, budget)]
                counts = dict(tally)
                if runs[0]["status"] == "ok" and test.timing:
                    runs += [breath(case, reduced, test.scale, budget) for _ in range(args.repeats - 1)]
                    if split is None:
                        model.state.x.array[:] = runs[0]["states"][case.outputs[1]]
                        split = reduced_cost_split(reduced)
                first = runs[0]
                ok = all(r["status"] == "ok" for r in runs)
                seconds = [r["seconds"] for r in runs]
                errors = metrics.errors(test, first["states"]) if first["status"] == "ok" else {}
                row = common | {
                    "size": basis.size,
                    "status": "ok" if ok else next(r["status"] for r in runs if r["status"] != "ok"),
                    "reason": "" if ok else next(r["reason"] for r in runs if r["status"] != "ok"),
                    "scale": test.name,
                    "label": test.label,
                    "timing_load": test.timing,
                    "runs": len(runs),
                    "online_seconds": float(np.median(seconds)) if ok else "",
                    "online_seconds_first": seconds[0],
                    "online_seconds_all": ";".join(f"{s:.4f}" for s in seconds),
                    "full_seconds": full_seconds,
                    "speedup": full_seconds / float(np.median(seconds)) if ok else "",
                    "setup_seconds": setup,
                    "newton_iterations": first["newton"],
                    "newton_calls": first["newton_calls"],
                    "steps": first["steps"],
                    "failed_steps": first["failed_steps"],
                    **counts,
                    "projection_err": metrics.projection(test, np.ascontiguousarray(basis.vectors), KV),
                    "volume_start": metrics.v0,
                    **errors,
                }
                if counts["jacobian_evals"] and first["status"] == "ok":
                    row["measured_share_res_jac"] = (counts["seconds_residual"] + counts["seconds_jacobian"]) / first[
                        "seconds"
                    ]
                if split is not None and test.timing:
                    row |= {f"split_{n}": v for n, v in split.items()}
                    per_it = residuals_per_jacobian(counts)
                    assembly = split["jac_assembly"] + per_it * split["res_assembly"]
                    total = (
                        assembly
                        + split["jac_projection"]
                        + split["small_solve"]
                        + per_it * (split["res_projection"] + split["reconstruct"])
                    )
                    row |= {
                        "split_residuals_per_jacobian": per_it,
                        "split_iteration_seconds": total,
                        "split_assembly_share": assembly / total,
                    }
                rows.append(row)
                err = (
                    f"energy err {row['energy_err']:.2e}, proj {row['projection_err']:.2e}, vol {row['volume_err_rel']:.1e}"
                    if errors
                    else f"proj {row['projection_err']:.2e}"
                )
                say(
                    f"  {kind} k={k} (size {basis.size}) {test.name}: {row['status']} {row.get('reason', '')}  "
                    f"{', '.join(f'{s:.2f}' for s in seconds)} s (full {full_seconds:.2f} s), {first['newton']} its; {err}"
                )
            reduced.destroy()
    K.destroy()
    raw = {
        "case": case.name,
        "title": case.title,
        "description": case.description,
        "dofs": dofs(model),
        "cells": cells(model),
        "ranks": COMM.size,
        "offline": case.offline,
        "notes": case.notes,
        "train": case.train,
        "tests": [dataclasses.asdict(t) for t in case.tests],
        "outputs": case.outputs,
        "full_runs": {k: {**v, "volume": {str(t): x for t, x in v["volume"].items()}} for k, v in full_runs.items()},
    }
    return rows, raw


def residuals_per_jacobian(counts: dict) -> float:
    return counts["residual_evals"] / counts["jacobian_evals"] if counts["jacobian_evals"] else 1.0


def base_row(case: Case) -> dict:
    return {"case": case.name, "dofs": dofs(case.model), "cells": cells(case.model), "ranks": COMM.size}


def fmt_split(s: dict) -> str:
    return ", ".join(f"{k} {v:.3g} s" for k, v in s.items())


# --- output ------------------------------------------------------------------------------------

COLUMNS = [
    "case",
    "dofs",
    "cells",
    "ranks",
    "kind",
    "k",
    "size",
    "status",
    "reason",
    "note",
    "scale",
    "label",
    "timing_load",
    "runs",
    "online_seconds",
    "online_seconds_first",
    "online_seconds_all",
    "full_seconds",
    "speedup",
    "setup_seconds",
    "newton_iterations",
    "newton_calls",
    "steps",
    "failed_steps",
    "residual_evals",
    "jacobian_evals",
    "seconds_residual",
    "seconds_jacobian",
    "measured_share_res_jac",
    "energy_err",
    "projection_err",
    "disp_err",
    "volume_err_rel",
    "volume_err_tidal",
    "volume_max",
    "volume_start",
    "energy_err_by_time",
    "offline_snapshots",
    "offline_eigen",
    "offline_build",
    "offline_total",
    "split_res_assembly",
    "split_res_projection",
    "split_reconstruct",
    "split_jac_assembly",
    "split_jac_projection",
    "split_small_solve",
    "split_lu_factor_solve",
    "split_residuals_per_jacobian",
    "split_iteration_seconds",
    "split_assembly_share",
]


def f(value, spec: str = ".2e") -> str:
    if value in ("", None) or (isinstance(value, float) and not np.isfinite(value)):
        return "–"
    return format(value, spec)


def sname(scale) -> str:
    return "(" + ", ".join(f"{x:g}" for x in scale) + ")"


def group(rows: list[dict], case: str, kind: str, k, label: str) -> list[dict]:
    return [r for r in rows if r["case"] == case and r["kind"] == kind and r["k"] == k and r.get("label") == label]


def worst(rs: list[dict], key: str):
    values = [r.get(key) for r in rs]
    if not values or any(v in ("", None) for v in values):
        return ""
    return max(values)


def status_of(rs: list[dict]) -> str:
    bad = [r for r in rs if r["status"] != "ok"]
    if not bad:
        return "ok"
    return "; ".join(f"{r['status']} at {r['scale']}" + (f" ({r['reason']})" if r.get("reason") else "") for r in bad)


def markdown(rows: list[dict], raws: list[dict], header: list[str], sizes: list[int]) -> str:
    lines = [*header]
    for raw in raws:
        name = raw["case"]
        off = raw["offline"]
        full = [r for r in rows if r["case"] == name and r["kind"] == "full"]
        timing = next(r for r in full if r["timing_load"])
        lines += ["", f"## {raw['title']}", ""]
        d = raw["description"]
        lines += [
            f"- {raw['dofs']} dofs, {raw['cells']} cells, {raw['ranks']} MPI rank(s). Mesh: {d['mesh']}.",
            f"- Loads: {d['load']}. Scales: {d['scales']}.",
            f"- Training loads: {', '.join(sname(s) for s in raw['train'])} → "
            f"{off['snapshots']} snapshots. Test loads (none in the training set): "
            + ", ".join(f"{sname(t['scale'])} [{t['label']}]" for t in raw["tests"])
            + f". Timing load (repeated): {timing['scale']}.",
            f"- Stepping: {d['stepping']}.",
            f"- Full model (NewtonSolver, MUMPS LU) on the timing load: {f(timing['online_seconds'], '.2f')} s median of "
            f"{timing['runs']} ({timing['online_seconds_all'].replace(';', ', ')} s), {timing['newton_iterations']} Newton "
            f"iterations in {timing['newton_calls']} Newton solves, {timing['steps']} steps (+{timing['failed_steps']} failed), "
            f"{f(per_iteration(timing), '.3g')} s per Newton iteration. Per Newton iteration: residual "
            f"assembly {f(timing.get('split_res_assembly'), '.3f')} s, tangent assembly {f(timing.get('split_jac_assembly'), '.3f')} s, "
            f"LU factorisation + solve {f(timing.get('split_lu_factor_solve'), '.3f')} s (a fresh one, incl. the symbolic analysis).",
            "- Offline (shared): "
            + ", ".join(
                [f"model build {off['build']:.1f} s"]
                + (
                    [
                        f"inverse (unloaded reference) {off['inverse']:.1f} s ({off.get('inverse_iterations')} fixed-point its)"
                    ]
                    if off.get("inverse")
                    else []
                )
                + [
                    f"snapshots {off['snapshots_seconds']:.1f} s",
                    f"POD {off.get('pod_seconds', float('nan')):.2f} s "
                    f"({off.get('pod_significant')} significant directions, σ/σ₁ > 1e-7)",
                ]
            )
            + ".",
        ]
        if off.get("singular_values"):
            s = np.array(off["singular_values"])
            lines.append(
                "- POD singular values σ_i/σ_1: "
                + ", ".join(f"{v:.1e}" for v in (s / s[0])[:12])
                + (" …" if len(s) > 12 else "")
                + "."
            )
        labels = [lab for lab in ("interp", "extrap", "direction") if any(t["label"] == lab for t in raw["tests"])]
        lines += [
            "",
            "Errors are the worst over the interpolating test loads; energy err. = max_t ‖x_r − x_f‖_K / max_t ‖x_f − x_start‖_K "
            "over the output times, projection = the same for the K-orthogonal projection of x_f − x_start on the basis "
            "(the best the basis can do), max-norm u err. = max_t max_i |u_r − u_f|_i / max_t max_i |u_f − u_start|_i over the "
            "displacement dofs, volume = max_t |V_r − V_f| / V_f (and / the largest volume change |V_f − V_start| of the full run). "
            "Online = the whole load-stepped reduced solve on the timing load, median of the repeats; speed-up = full / reduced "
            "on that load. Offline = inverse + snapshots + eigensolve/SVD + build of this basis.",
            "",
            "| basis | k | size | status | energy err. | projection err. | max-norm u err. | vol. err. / V | vol. err. / ΔV | "
            "online [s] | speed-up | reduced Newton its (steps) | s / Newton it | assembly share of an iteration | "
            "offline [s] (snapshots / eig-SVD / build) |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        kinds = list(dict.fromkeys(r["kind"] for r in rows if r["case"] == name and r["kind"] != "full"))
        for kind in kinds:
            for k in sizes:
                rs = group(rows, name, kind, k, "interp") or group(rows, name, kind, k, "all")
                if not rs:
                    continue
                r0 = rs[0]
                if r0["size"] == "":
                    lines.append(f"| {kind} | {k} | – | {r0['status']} | | | | | | | | | | | |")
                    continue
                tr = next((r for r in rs if r["timing_load"]), r0)
                offline = (
                    (
                        f"{r0.get('offline_total', 0):.1f} ({r0.get('offline_snapshots', 0):.1f} / "
                        f"{r0.get('offline_eigen', 0):.2f} / {r0.get('offline_build', 0):.2f})"
                    )
                    if "offline_total" in r0
                    else "–"
                )
                lines.append(
                    f"| {kind} | {k} | {r0['size']} | {status_of(rs)} | {f(worst(rs, 'energy_err'))} | {f(worst(rs, 'projection_err'))} | "
                    f"{f(worst(rs, 'disp_err'))} | {f(worst(rs, 'volume_err_rel'))} | {f(worst(rs, 'volume_err_tidal'))} | "
                    f"{f(tr['online_seconds'], '.3g')} | {f(tr['speedup'], '.1f')}"
                    f"{' (0 its: q stays 0)' if tr['newton_iterations'] == 0 else ''} | {tr['newton_iterations']} ({tr['steps']}"
                    f"{' + ' + str(tr['failed_steps']) + ' failed' if tr['failed_steps'] else ''}) | "
                    f"{f(per_iteration(tr), '.3g')} | {f(tr.get('split_assembly_share'), '.0%')} | {offline} |"
                )
        others = [lab for lab in labels if lab != "interp"]
        if others:
            names = {"extrap": "extrapolation", "direction": "unseen load direction"}
            head = (
                "| basis | k | "
                + " | ".join(
                    f"{names[lab]} {x}"
                    for lab in others
                    for x in ("status", "energy err.", "projection err.", "max-norm u err.", "vol. err. / V")
                )
                + " |"
            )
            lines += [
                "",
                "Loads outside the training range: "
                + "; ".join(
                    f"{names[lab]}: " + ", ".join(sname(t_["scale"]) for t_ in raw["tests"] if t_["label"] == lab)
                    for lab in others
                )
                + ".",
                "",
                head,
                "|" + "---|" * (head.count("|") - 1),
            ]
            for kind in kinds:
                for k in sizes:
                    cellsx = []
                    if (
                        not group(rows, name, kind, k, "interp")
                        or group(rows, name, kind, k, "interp")[0]["size"] == ""
                    ):
                        continue
                    for lab in others:
                        rs = group(rows, name, kind, k, lab)
                        cellsx += [
                            status_of(rs),
                            f(worst(rs, "energy_err")),
                            f(worst(rs, "projection_err")),
                            f(worst(rs, "disp_err")),
                            f(worst(rs, "volume_err_rel")),
                        ]
                    lines.append(f"| {kind} | {k} | " + " | ".join(cellsx) + " |")
        lines += ["", cost_sentence(rows, name)]
    return "\n".join(lines) + "\n"


def per_iteration(r: dict):
    if r.get("online_seconds") in ("", None) or not r.get("newton_iterations"):
        return ""
    return float(r["online_seconds"]) / int(r["newton_iterations"])


def cost_sentence(rows: list[dict], name: str) -> str:
    full = next(r for r in rows if r["case"] == name and r["kind"] == "full" and r["timing_load"])
    split = [
        r for r in rows if r["case"] == name and r["kind"] != "full" and r.get("split_assembly_share") not in ("", None)
    ]
    if not split:
        return "**Online cost:** no reduced run converged on the timing load, so it was not measured."
    shares = [r["split_assembly_share"] for r in split]
    measured = [r["measured_share_res_jac"] for r in split if r.get("measured_share_res_jac") not in ("", None)]
    small = [r for r in split]
    big = max(small, key=lambda r: r["size"])
    little = min(small, key=lambda r: r["size"])
    useful = [
        r
        for r in split
        if r.get("speedup") not in ("", None)
        and worst(group(rows, name, r["kind"], r["k"], "interp"), "energy_err") not in ("", None)
        and worst(group(rows, name, r["kind"], r["k"], "interp"), "energy_err") <= 1e-2
    ]
    speed = [r["speedup"] for r in useful]
    full_it = per_iteration(full)
    decomposition = "; ".join(
        f"{r['kind']} k = {r['size']}: {r['speedup']:.1f}× = {full_it / per_iteration(r):.1f}× per Newton iteration × "
        f"{int(full['newton_iterations']) / int(r['newton_iterations']):.2g} (ratio of Newton iterations, full "
        f"{full['newton_iterations']} / reduced {r['newton_iterations']}; steps {full['steps']} + {full['failed_steps']} failed "
        f"/ {r['steps']} + {r['failed_steps']} failed)"
        for r in useful
        if per_iteration(r)
    )
    lu = full.get("split_lu_factor_solve")
    jac = full.get("split_jac_assembly")
    res = full.get("split_res_assembly")
    return (
        f"**What the online time is (no hyper-reduction):** one reduced Newton iteration assembles the full tangent "
        f"({f(little['split_jac_assembly'], '.3g')} s) and the full residual ({f(little['split_res_assembly'], '.3g')} s, "
        f"{f(little['split_residuals_per_jacobian'], '.2g')} times per iteration with the line search), then projects "
        f"(K·V and Vᵀ(K V): {f(little['split_jac_projection'], '.2g')} s at k = {little['size']}, "
        f"{f(big['split_jac_projection'], '.2g')} s at k = {big['size']}) and solves a k × k system "
        f"({f(little['split_small_solve'], '.1e')}–{f(big['split_small_solve'], '.1e')} s). Assembling the full residual "
        f"and tangent is {min(shares):.0%}–{max(shares):.0%} of an iteration over all bases and sizes that converged; "
        f"measured over whole reduced solves, reduced_residual + reduced_jacobian (assembly + projection) take "
        f"{min(measured):.0%}–{max(measured):.0%} of the online time (the rest: load stepping"
        f"{', the balanced-gravity fixed point' if name == 'lung' else ''}, predictor, reconstruction x₀ + V q, Python). A full Newton iteration costs {f(full_it, '.3g')} s in the "
        f"load stepping: the same assembly ({f(jac, '.3g')} + {f(res, '.3g')} s) plus the MUMPS LU factorisation and solve "
        f"({f(lu, '.3g')} s for a fresh factorisation incl. the symbolic analysis, which the Newton loop reuses). Without "
        f"hyper-reduction a reduced iteration cannot cost less than the assembly, so per iteration the speed-up is bounded "
        f"by about {full_it / (jac + res):.1f}× (full s per iteration / assembly); the rest of a speed-up is the ratio of "
        f"Newton iteration counts. Measured speed-ups of the reduced "
        f"models with energy error ≤ 1e-2 on the interpolating loads: {min(speed):.1f}–{max(speed):.1f}× ({decomposition}). "
        "This is the baseline hyper-reduction must beat: it removes the full assembly, not the k × k solve."
        if speed
        else f"**Online cost:** assembly share {min(shares):.0%}–{max(shares):.0%} of an iteration; no reduced model reached "
        "energy error ≤ 1e-2."
    )


def pareto(rows: list[dict], raws: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    names = [raw["case"] for raw in raws]
    fig, axes = plt.subplots(2, len(names), figsize=(5.4 * len(names), 8.6), squeeze=False)
    markers = {"pod": "o", "polynomial": "s", "modal": "^", "modal+derivatives": "D"}
    colours = dict(zip(markers, ("C0", "C1", "C2", "C3")))
    for j, name in enumerate(names):
        full = next(r for r in rows if r["case"] == name and r["kind"] == "full" and r["timing_load"])
        for i, (key, label) in enumerate(
            (("energy_err", "rel. energy-norm error"), ("volume_err_rel", "rel. volume error |V_r − V_f| / V_f"))
        ):
            ax = axes[i, j]
            failed = []
            for kind, marker in markers.items():
                pts = []
                for r in rows:
                    if not (r["case"] == name and r["kind"] == kind and r.get("timing_load")):
                        continue
                    ks = group(rows, name, kind, r["k"], "interp")
                    e, p = worst(ks, key), worst(ks, "projection_err")
                    if r["status"] == "ok" and e not in ("", None) and e > 0:
                        pts.append((r["online_seconds"], e, r["size"], p))
                    elif r["status"] != "ok":
                        failed.append((float(r["online_seconds_first"]), kind, r["size"]))
                if not pts:
                    continue
                pts.sort(key=lambda q: q[2])
                x, y, k, proj = zip(*pts)
                ax.loglog(x, y, marker=marker, ls="-", color=colours[kind], label=kind)
                if key == "energy_err" and all(v not in ("", None) and v > 0 for v in proj):
                    ax.loglog(
                        x,
                        proj,
                        marker=marker,
                        ls=":",
                        color=colours[kind],
                        mfc="none",
                        alpha=0.6,
                        label=f"{kind}: projection (best in span)",
                    )
                for xi, yi, ki, _ in pts:
                    ax.annotate(str(ki), (xi, yi), textcoords="offset points", xytext=(4, 3), fontsize=7)
            for xi, kind, ki in failed:  # runs that did not converge or were stopped: at the top, time until then
                ax.plot(
                    [xi],
                    [1.0],
                    marker="x",
                    color=colours[kind],
                    ms=8,
                    transform=ax.get_xaxis_transform(),
                    clip_on=False,
                )
                ax.annotate(
                    f"{ki}✗",
                    (xi, 1.0),
                    xycoords=("data", "axes fraction"),
                    textcoords="offset points",
                    xytext=(3, -10),
                    fontsize=7,
                    color=colours[kind],
                )
            ax.axvline(full["online_seconds"], color="k", ls="--", lw=1)
            ax.annotate(
                "full model",
                (full["online_seconds"], 0.5),
                xycoords=("data", "axes fraction"),
                rotation=90,
                fontsize=8,
                ha="right",
                va="center",
            )
            ax.set_xscale("log")
            ax.xaxis.set_minor_formatter(NullFormatter())
            ax.set(
                xlabel="online time [s] (median, timing load)",
                ylabel=label,
                title=f"{name}: {full['dofs']} dofs, {full['ranks']} rank(s)",
            )
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=6)
    fig.suptitle(
        "Reduced models: worst error on unseen interpolating loads vs online time (numbers: basis size; "
        "dotted: projection error; ✗ at the top: did not converge / stopped)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def versions() -> dict:
    import dolfinx
    import slepc4py

    cpu, memory = cpu_and_memory()
    commit = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    dirty = subprocess.run(
        ["git", "-C", str(ROOT), "status", "--porcelain", "--", "lungmech"], capture_output=True, text=True
    ).stdout.strip()
    return {
        "dolfinx": dolfinx.__version__,
        "petsc": ".".join(map(str, PETSc.Sys.getVersion())),
        "slepc": slepc4py.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory": memory,
        "commit": commit + (" (lungmech/ has uncommitted changes)" if dirty else ""),
    }


def header(args, v: dict, total: float, done: bool, load: tuple) -> list[str]:
    status = "" if done else " — RUN IN PROGRESS, partial table"
    return [
        f"# Reduced-order models: speed against accuracy{status}",
        "",
        f"- Date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}; machine: {v['cores']} cores "
        f"({v['cpu']}), {v['memory']}; 1-min load average at start {load[0]:.2f}, at the end {os.getloadavg()[0]:.2f} "
        "(this run's own ranks count; above the number of ranks, other work shared the machine).",
        f"- DOLFINx {v['dolfinx']}, PETSc {v['petsc']}, slepc4py {v['slepc']}, NumPy {v['numpy']}, Python {v['python']}; "
        f"lungmech at {v['commit']}; {COMM.size} MPI rank(s); OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}.",
        f"- Command: `python benchmarks/rom.py {os.environ.get('ROM_BENCH_COMMAND', ' '.join(sys.argv[1:]))}`"
        f"{f' (= mpiexec -n {COMM.size} python benchmarks/rom.py ...)' if COMM.size > 1 else ''}; "
        f"total wall time {total / 60:.1f} min.",
        f"- Full model: `lungmech.fem.solver.NewtonSolver` (SNES newtonls, line search {args.line_search}, rtol 1e-10, atol 1e-12, "
        "MUMPS LU); the lung's inverse problem (offline) uses the scene's own solver settings (line search bt).",
        "- Reduced model: `lungmech.rom.ReducedSolver` (Galerkin, Newton on Vᵀ R(x₀ + V q) = 0 with the same NewtonOptions "
        "as the full model, bt-type backtracking on the reduced residual), driven by the same `lungmech.fem.solver.solve` "
        "stepping and loads as the full model. No hyper-reduction. A reduced run that needs more than "
        f'{args.budget:g} × the full model\'s time for the same load is stopped ("stopped"); one whose steps fail down to the '
        'minimum step is "did not converge".',
        '- Bases: pod = `rom.pod(inner="energy")` of the training snapshots, truncated to k (n/a above the number of '
        "significant directions); polynomial = `rom.polynomial_basis` (monomials of the coordinates × field components, "
        "lowest order first) truncated to k; modal = `rom.modal_basis(k)` (lowest k modes at the unloaded state); "
        "modal+derivatives = m modes + all m(m+1)/2 static modal derivatives with the largest m that fits k (size column: "
        "what is left after re-orthonormalisation). Modal bases need a displacement-only model.",
        "- Timings are wall times (MPI barriers around each), warm: the forms are compiled and the solvers used before "
        'any timed run. K = the energy inner product `rom.inner_product(model, "energy")` (second variation of the stored '
        "energy at the unloaded state).",
    ]


def write(rows, raws, args, v, done, load, sizes, prefix, lines=None) -> None:
    if not RANK0:
        return
    RESULTS.mkdir(parents=True, exist_ok=True)
    RAW.mkdir(parents=True, exist_ok=True)
    lines = lines or header(args, v, time.perf_counter() - STARTED, done, load)
    for raw in raws:
        raw["header"] = lines
    text = markdown(rows, raws, lines, sizes)
    (RESULTS / f"{prefix}.md").write_text(text)
    with open(RESULTS / f"{prefix}.csv", "w", newline="") as stream:
        writer = csv.DictWriter(stream, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    for raw in raws:
        (RAW / f"{prefix}-{raw['case']}.json").write_text(
            json.dumps(raw | {"rows": [r for r in rows if r["case"] == raw["case"]]}, indent=1, default=str) + "\n"
        )
    pareto(rows, raws, RESULTS / f"{prefix}_pareto.png")


def replot(args, prefix: str, names: list[str], sizes: list[int]) -> None:
    """Rebuild the outputs from the raw JSON of an earlier run (its header is kept)."""
    raws = [
        json.loads((RAW / f"{prefix}-{name}.json").read_text())
        for name in names
        if (RAW / f"{prefix}-{name}.json").exists()
    ]
    lines = raws[0].get("header") if raws else None
    if lines is None:  # raw files written before headers were stored: keep the header of the existing table
        old = (RESULTS / f"{prefix}.md").read_text().split("\n## ")[0].rstrip("\n").split("\n")
        lines = old
    rows = [r for raw in raws for r in raw["rows"]]
    for raw in raws:
        raw.pop("rows")
    write(rows, raws, args, {}, True, (0.0,), sizes, prefix, lines=lines)


def main() -> None:
    args = ARGS
    load = os.getloadavg()
    prefix = args.prefix or ("rom_quick" if args.quick else "rom")
    sizes = [int(k) for k in (args.sizes or ("2,5,20" if args.quick else ",".join(map(str, SIZES)))).split(",")]
    names = (args.cases or "lung,beam,beam-large").split(",")
    if args.repeats is None:
        args.repeats = 2 if args.quick else 3
    if args.replot:
        replot(args, prefix, names, sizes)
        return
    v = versions()
    rows, raws = [], []
    for name in names:
        case = lung_case(args) if name == "lung" else beam_case(args, large=name == "beam-large")
        case_rows, raw = run_case(case, args, sizes)
        rows += case_rows
        raws.append(raw)
        write(rows, raws, args, v, False, load, sizes, prefix)
        case.full.destroy()
    write(rows, raws, args, v, True, load, sizes, prefix)
    if RANK0:
        print((RESULTS / f"{prefix}.md").read_text())


if __name__ == "__main__":
    main()
