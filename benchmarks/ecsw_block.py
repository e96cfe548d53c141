"""ECSW hyper-reduction against the Galerkin ROM and the full model, at three mesh sizes.

    python benchmarks/ecsw_block.py            # meshes 12×4×4, 24×8×8, 36×12×12 (about 4 minutes)
    python benchmarks/ecsw_block.py --quick    # meshes 6×2×2, 9×3×3 (seconds): results/ecsw_block_quick.*

A clamped neo-Hookean block (3 × 1 × 1 m, E = 10 Pa, ν = 0.3) under a shear traction on x = 3,
its weight and a follower pressure on its top, P1. Training: the load paths at load factors
0.2, 0.4, 0.6 (every converged step); a 6-vector POD basis in the energy inner product; ECSW
at τ = 1e-4, trained on the converged steps, and again on every Newton iterate of a second
pass over the training paths. Online: the unseen load factor 0.3, the same load stepping for all three, best
of three runs (warm: forms compiled, the solver reused). The error is the relative distance of
the final state to the full model's, in the Euclidean norm of the state vector.

Writes results/ecsw_block.md, results/ecsw_block.csv and results/ecsw_block.png.
"""

from __future__ import annotations

import argparse
import time

from mpi4py import MPI

import machine
import numpy as np
from machine import provenance, time_against_dofs, write_results  # noqa: E402

from lungmech import rom
from lungmech.fem.constraints import clamp
from lungmech.fem.loads import BodyForce, FollowerPressure, Traction
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.solver import NewtonSolver, Stepping, solve
from lungmech.mesh import box
from lungmech.rom.ecsw import FAMILIES, Training
from lungmech.rom.hyper_reduced import HyperReducedSolver

TRAINING, UNSEEN, TOLERANCE, SIZE = (0.2, 0.4, 0.6), 0.3, 1e-4, 6
MESHES = (4, 8, 12)  # n: 3n × n × n boxes of 6 tetrahedra each
QUICK_MESHES = (2, 3)
RESULTS = machine.RESULTS
READING = (
    "Times are for the whole load path (several load steps and their Newton iterations), as the load "
    "stepping reports it. The ECSW solver iterates on q and assembles on a reduced mesh of the sampled "
    "cells (a DOLFINx submesh, the basis restricted to its dofs): no online operation touches the full "
    "mesh. Writing the full state x₀ + V q, needed here for the error only, is not timed."
)


def block(n: int) -> Model:
    return Model(
        box(MPI.COMM_WORLD, lengths=(3.0, 1.0, 1.0), cells=(3 * n, n, n)),
        NeoHookean.from_young(10.0, 0.3),
        constraints=[clamp("x0")],
        loads=[Traction("x1", (0.0, 0.0, -0.5)), BodyForce((0.0, 0.1, 0.0)), FollowerPressure("z1", 0.3)],
    )


def path(model: Model, scale: float, solver=None, on_step=None):
    """The load path at ``scale`` from rest (the solver's state too)."""
    model.reset()
    if isinstance(solver, HyperReducedSolver):
        solver.set_state(solver.project())
    return solve(
        model,
        Stepping(max_step=0.25),
        solver=solver,
        drive=lambda t: model.set_time(t, load_factor=scale),
        on_step=on_step,
        monitor=lambda step: None,
    )


def case(n: int) -> dict:
    model = block(n)
    owned = model.space.dofmap.index_map.size_local * model.space.dofmap.index_map_bs
    tic = time.perf_counter()
    states = []
    for scale in TRAINING:
        path(model, scale, on_step=lambda step, s=scale: states.append((model.state.x.array.copy(), model.time, s)))
    snapshots = time.perf_counter() - tic
    tic = time.perf_counter()
    basis = rom.pod(model, np.column_stack([x[:owned] for x, _, _ in states]), inner="energy", size=SIZE)
    pod = time.perf_counter() - tic
    tic = time.perf_counter()
    training = Training(model, basis.vectors)
    for x, t, scale in states:
        training.add_state(x, t, scale)
    sample = training.sample(TOLERANCE)
    ecsw = time.perf_counter() - tic
    tic = time.perf_counter()  # a second pass: every Newton iterate of the training paths
    iterates = Training(model, basis.vectors)
    solver = NewtonSolver(model)
    with iterates.watching(solver):
        for scale in TRAINING:
            path(model, scale, solver=solver)
    sample_iterates = iterates.sample(TOLERANCE)
    ecsw_iterates = time.perf_counter() - tic
    row = {
        "dofs": model.space.dofmap.index_map.size_global * model.space.dofmap.index_map_bs,
        "cells": model.geometry.mesh.topology.index_map(3).size_global,
        **{f"sampled_{family}": count for family, count in sample.count(MPI.COMM_WORLD).items()},
        **{f"iterates_sampled_{family}": n for family, n in sample_iterates.count(MPI.COMM_WORLD).items()},
        "offline_snapshots_s": snapshots,
        "offline_pod_s": pod,
        "offline_ecsw_s": ecsw,
        "offline_ecsw_iterates_s": ecsw_iterates,
    }
    finals = {}
    for name, make in (
        ("full", lambda m: None),
        ("galerkin", lambda m: rom.ReducedSolver(m, basis)),
        ("ecsw", lambda m: HyperReducedSolver(m, basis, sample)),
        ("ecsw_iterates", lambda m: HyperReducedSolver(m, basis, sample_iterates)),
    ):
        online = block(n)
        solver = make(online)
        best = np.inf
        for _ in range(3):
            report = path(online, UNSEEN, solver=solver)
            best = min(best, report.seconds)
        if solver is not None:
            solver.update_model()  # the full state, for the error (not timed: online work is in q)
        finals[name] = online.state.x.array.copy()
        row[f"{name}_ms"] = 1e3 * best
        row[f"{name}_newton"] = report.newton_iterations
    scale = np.linalg.norm(finals["full"])
    for name in ("galerkin", "ecsw", "ecsw_iterates"):
        row[f"{name}_error"] = float(np.linalg.norm(finals[name] - finals["full"]) / scale)
    return row


def sampled(row: dict, prefix: str) -> str:
    """The sample sizes of the three families, "internal / weight / boundary"."""
    return " / ".join(str(int(row.get(f"{prefix}{family}", 0))) for family in FAMILIES)


def markdown(rows: list[dict], command: str) -> str:
    lines = [
        "# ECSW against the Galerkin ROM and the full model (neo-Hookean block)",
        "",
        f"{provenance(command)} POD of {SIZE} vectors, ECSW at τ = {TOLERANCE:g}; online: "
        f"the unseen load factor {UNSEEN} along the same steps, best of three warm runs.",
        "",
        "| dofs | cells | full [ms] | Galerkin [ms] | ECSW: sampled cells (internal / weight / boundary) | [ms] | "
        "speed-up over full, Galerkin | ECSW on iterates: sampled | [ms] | error: Galerkin, ECSW, ECSW on iterates | "
        "offline: snapshots, POD, ECSW, ECSW on iterates [s] |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['dofs']} | {r['cells']} | {r['full_ms']:.0f} | {r['galerkin_ms']:.0f} | "
            f"{sampled(r, 'sampled_')} | {r['ecsw_ms']:.1f} | "
            f"{r['full_ms'] / r['ecsw_ms']:.0f}×, {r['galerkin_ms'] / r['ecsw_ms']:.0f}× | "
            f"{sampled(r, 'iterates_sampled_')} | {r['ecsw_iterates_ms']:.1f} | "
            f"{r['galerkin_error']:.1e}, {r['ecsw_error']:.1e}, {r['ecsw_iterates_error']:.1e} | "
            f"{r['offline_snapshots_s']:.1f}, {r['offline_pod_s']:.2f}, {r['offline_ecsw_s']:.2f}, "
            f"{r['offline_ecsw_iterates_s']:.1f} |"
        )
    return "\n".join([*lines, "", READING]) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two coarse meshes (the suite's case)")
    quick = parser.parse_args().quick
    stem, command = (
        ("ecsw_block_quick", "python benchmarks/ecsw_block.py --quick")
        if quick
        else ("ecsw_block", "python benchmarks/ecsw_block.py")
    )
    rows = []
    for n in QUICK_MESHES if quick else MESHES:
        rows.append(case(n))
        r = rows[-1]
        print(
            f"{r['dofs']} dofs: full {r['full_ms']:.0f} ms, Galerkin {r['galerkin_ms']:.0f} ms, ECSW {r['ecsw_ms']:.1f} ms"
        )
    write_results(RESULTS, stem, rows, markdown(rows, command))
    time_against_dofs(
        rows,
        [
            ("full_ms", "full model"),
            ("galerkin_ms", "Galerkin ROM"),
            ("ecsw_ms", f"ECSW on converged states, τ = {TOLERANCE:g}"),
            ("ecsw_iterates_ms", f"ECSW on Newton iterates, τ = {TOLERANCE:g}"),
        ],
        "online time for the load path [ms]",
        "Neo-Hookean block, unseen load: online time",
        RESULTS / f"{stem}.png",
    )
    print((RESULTS / f"{stem}.md").read_text())


if __name__ == "__main__":
    main()
