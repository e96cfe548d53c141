"""The PGD, a priori and fitted to full solves, beside the full model and a hyper-reduced model
of the same scene.

    python benchmarks/pgd.py                 # both cases at full size (a few minutes)
    python benchmarks/pgd.py --ranks 2       # the same on two ranks (rows kept beside one rank's)
    python benchmarks/pgd.py --quick         # coarse meshes, few points, no hyper-reduced shape or breath (the suite's case)
    python benchmarks/pgd.py --replot        # the plot drawn again from the results (no solve)
    python benchmarks/pgd.py --cases breath balanced   # those cases again, the others' rows kept

Seven cases, each a scene built here:

* **anchor**: the configuration of NeuROM's NN-PGD (Daby-Seesaram, Škardová, Genet): a 10 × 10
  plate with three holes, clamped on its top and bottom edges, plane strain, ν = 0.3, under its
  own weight ρg = 9.81e-6 turned in the plane by θ ∈ [0°, 360°), its stiffness E ∈ [1e-3, 1e-2]
  (log). Published: 8.7e-4 to 9.3e-3 relative nodal error at 8 test points on 14,230 dofs, after
  ≈ 58 s of training on a CPU.
* **lung**: a linear elastic lung phantom clamped on its mediastinal face under its own weight,
  E over a factor 10 (log), the pitch over a full turn and the roll over ±90°.
* **jump**: the seed's heterogeneous case: the linear lung phantom with E₁ below a plane and E₂
  above it, joined over two cells by a tanh, E₁, E₂ each over a factor 10 (log), the plane's
  position α (a value the residual is not affine in: the a priori PGD takes its operators'
  Chebyshev series in α) and gravity's pitch (±45°) and roll (±30°); its PGD a priori and fitted
  to 128 full solves.
* **shape**: the linear lung phantom of **lung** over a population: its template moved by two
  shape modes (a library of 8 smooth changes of a few mm, mixed at random, made here), the two
  coefficients over ±2 standard deviations (values the residual is not affine in: det G and G⁻¹;
  the a priori PGD takes their operators' tensor Chebyshev series) and E over a factor 10, under
  its weight.
* **balanced**: the breath's lung under its weight, carried by a pleural pressure gradient whose
  coefficients move with the state (``balanced_on``, :mod:`lungmech.lung.gravity`), its posture
  over −90°–0° a fourth parameter: its PGD a priori (the Newton–PGD taking each point's tangent
  at its state on the modes' span; full size only, the suite tests it) beside its PGD fitted
  to 32 and 64 full solves (its hyper-reduced model is ``rom_real_time.py``'s).
* **imaged**: the bundled breathing lung as imaged at end-expiration (``[inverse]``), breathing
  in from the image, its weight balanced, over its stiffness, the breath's depth and its
  posture (−90°–0°):
  its PGD a priori (:mod:`lungmech.pgd.imaged_newton`: its unloaded reference ξ(μ) by the
  inverse problem's Newton–PGD, then the breath's from the image on it; full size only, the
  suite tests it) beside its PGD fitted to 32 and 64 full solves; the full model on its image
  (``start="inverse_motion"``), as its reduced models are.
* **breath**: the nonlinear lung: the lung phantom's poromechanics with the lung skeleton's
  law, a follower pleural pressure ramped from rest, α and c1 over log ranges and the breath's
  depth. Its PGD a priori (:mod:`lungmech.pgd.newton`: Newton on the parameters' Gauss grid,
  residual assemblies, no full solve) beside its PGD fitted to full solves
  (:mod:`lungmech.pgd.fitted`) at several sample sizes; the fitted one's held-out error
  against the number of terms is the plot's third panel.

For the linear cases: the PGD built a priori (no full solve; seconds for its terms, greedy and outputs),
and a POD–ECSW hyper-reduced model (τ = 1e-4) trained on 8 full solves, both measured at the
same random points against the full model: the relative nodal error ‖u − u_FE‖₂/‖u_FE‖₂ (NeuROM's
measure) and the relative energy-norm error (the energy product at the defaults), max and
median; online milliseconds per point (``solve(μ, times=[T])``: volume, strain energy, probes),
median. Also the anchor's error over its whole box, on a grid (the plot's map).

Writes results/pgd.md, results/pgd.csv and results/pgd.png, and what the plot needs beside the
table in results/pgd_plot.json (for --replot).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from mpi4py import MPI

import machine
import matplotlib
import matplotlib.ticker
import numpy as np

from lungmech.app import reduce
from lungmech.app import scene as scenes
from lungmech.app.pgd import build as build_pgd
from lungmech.app.run import full_order_model
from lungmech.errors import ParameterError
from lungmech.parallel.linalg import norms
from lungmech.rom.basis import inner_product

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from machine import provenance, read_results, say, write_results  # noqa: E402

RESULTS = machine.RESULTS
COMMAND = "LUNGMECH_PGD_COMMAND"
PUBLISHED = {"error": (8.7e-4, 9.3e-3), "seconds": 58.0, "dofs": 14230}  # NeuROM's anchor

ANCHOR = """
title = "NeuROM's plate with three holes under its own weight, turned in its plane"
[geometry]
builder = "plate_with_holes"
mesh_size = {h}
[material]
law = "linear"
E = 3e-3
nu = 0.3
[formulation]
plane = "strain"
[[constraints]]
type = "clamp"
boundary = "y0"
[[constraints]]
type = "clamp"
boundary = "y1"
[[loads]]
type = "gravity"
name = "gravity"
density = 1.0
acceleration = [0.0, -9.81e-6]
[stepping]
end = 1.0
initial_step = 1.0
[parameters.E]
target = "material.E"
range = [1e-3, 1e-2]
scale = "log"
[parameters.theta]
target = "loads.gravity.angle"
range = [0.0, 360.0]
[output]
probes = [[5.0, 5.0], [9.0, 5.0]]
"""

LUNG = """
title = "a linear elastic lung phantom under its own weight, turned"
[geometry]
builder = "lung_phantom"
mesh_size = {h}
[material]
law = "linear"
E = 3e3
nu = 0.3
[[constraints]]
type = "clamp"
boundary = "mediastinum"
[[loads]]
type = "gravity"
name = "gravity"
density = 300.0
acceleration = [0.0, 0.0, -9.81]
[stepping]
end = 1.0
initial_step = 1.0
[parameters.E]
target = "material.E"
range = [1e3, 1e4]
scale = "log"
[parameters.pitch]
target = "loads.gravity.pitch"
range = [-180.0, 180.0]
[parameters.roll]
target = "loads.gravity.roll"
range = [-90.0, 90.0]
[output]
probes = [[0.06, 0.0, 0.12]]
"""

SHAPE = (
    LUNG.replace('builder = "lung_phantom"', 'builder = "lung_phantom"\nshape_modes = "modes.npz"').split(
        "[parameters.pitch]"
    )[0]
    + """[parameters.a1]
target = "shape.mode_1"
range = [-2.0, 2.0]
[parameters.a2]
target = "shape.mode_2"
range = [-2.0, 2.0]
[output]
probes = [[0.06, 0.0, 0.12]]
"""
)
BREATH = """
title = "a gentle breath of the lung phantom over three parameters (poromechanics)"
[geometry]
builder = "lung_phantom"
side = "right"
mesh_size = {h}
[material]
law = "lung_skeleton"
alpha = 160.0
gamma = 0.5
c1 = 200.0
c2 = 400.0
[formulation]
type = "poromechanics"
kappa = 1.0e4
phi_s0 = 0.3
[[constraints]]
type = "clamp"
boundary = "hilum"
[[loads]]
type = "follower_pressure"
name = "pleural"
boundary = ["pleura", "diaphragm", "mediastinum"]
value = -300.0
ramp = {{ times = [0.0, 1.0], values = [0.0, 1.0] }}
[stepping]
end = 1.0
max_step = 0.25
times = [0.5]
[output]
probes = [[0.05, 0.0, 0.1]]
[parameters.alpha]
target = "material.alpha"
range = [100.0, 300.0]
scale = "log"
[parameters.c1]
target = "material.c1"
range = [100.0, 400.0]
scale = "log"
[parameters.breath]
target = "loads.pleural.amplitude"
range = [0.6, 1.4]
"""

JUMP = """
title = "a lung phantom with a stiffness jump that moves, under its weight turned"
[geometry]
builder = "lung_phantom"
mesh_size = {h}
[material]
law = "linear"
E = 3e3
nu = 0.3
[[constraints]]
type = "clamp"
boundary = "mediastinum"
[[loads]]
type = "gravity"
name = "gravity"
density = 300.0
acceleration = [0.0, 0.0, -9.81]
[stepping]
end = 1.0
initial_step = 1.0
[parameters.E1]
target = "material.E"
range = [1e3, 1e4]
scale = "log"
[parameters.E2]
target = "material.E"
range = [1e3, 1e4]
scale = "log"
region = {{ normal = [0, 0, -1], position = "alpha", width = {w} }}
[parameters.alpha]
target = "interface"
default = -0.12
range = [-0.16, -0.08]
[parameters.pitch]
target = "loads.gravity.pitch"
range = [-45.0, 45.0]
[parameters.roll]
target = "loads.gravity.roll"
range = [-30.0, 30.0]
[output]
probes = [[0.06, 0.0, 0.2]]
"""

# the breath's lung under its weight, carried by a pleural pressure gradient whose coefficients
# move with the state (lungmech.lung.gravity), its posture over −90°–0°
WEIGHT = """
[[loads]]
type = "gravity"
name = "gravity"
density = 315.0
acceleration = [0.0, 0.0, -9.81]
balanced_on = ["pleura", "diaphragm", "mediastinum"]
ramp = { times = [0.0, 1.0], values = [0.0, 1.0] }
[parameters.posture]
target = "loads.gravity.pitch"
range = [-90.0, 0.0]
"""

# the bundled breathing lung as imaged at end-expiration (lung_breathing_parameters.toml): its
# unloaded reference found at every μ ([inverse]), the breath in from the image, its weight
# balanced, lying on its back to upright
IMAGED = """
title = "the imaged lung phantom breathing in, over its stiffness, the breath's depth and its posture"
[geometry]
builder = "lung_phantom"
side = "right"
mesh_size = {h}
[material]
law = "lung_skeleton"
alpha = 160.0
gamma = 0.5
c1 = 200.0
c2 = 400.0
[formulation]
type = "poromechanics"
kappa = 1.0e4
phi_s0 = 0.3
[[constraints]]
type = "clamp"
boundary = "hilum"
[[loads]]
type = "follower_pressure"
name = "pleural"
boundary = ["pleura", "diaphragm", "mediastinum"]
value = -500.0
ramp = {{ times = [0.0, 1.0], values = [1.0, 2.0] }}
[[loads]]
type = "gravity"
name = "gravity"
density = 315.0
acceleration = [0.0, 0.0, -9.81]
balanced_on = ["pleura", "diaphragm", "mediastinum"]
ramp = {{ times = [0.0, 1.0], values = [1.0, 1.0] }}
[inverse]
tolerance = 1e-9
[stepping]
end = 1.0
max_step = 0.25
times = [0.5]
[output]
probes = [[0.05, 0.0, 0.1]]
[parameters.stiffness]
target = "material.c1"
range = [100.0, 400.0]
scale = "log"
[parameters.breath]
target = "loads.pleural.amplitude"
range = [0.6, 1.4]
[parameters.posture]
target = "loads.gravity.pitch"
range = [-90.0, 0.0]
"""

CASES = {  # scene, mesh size, --quick's
    "anchor": (ANCHOR, 0.12, 0.5),
    "lung": (LUNG, 0.012, 0.04),
    "jump": (JUMP, 0.02, 0.04),
    "shape": (SHAPE, 0.02, 0.04),
    "breath": (BREATH, 0.02, 0.04),
    "balanced": (BREATH + WEIGHT.replace("{", "{{").replace("}", "}}"), 0.02, 0.04),
    "imaged": (IMAGED, 0.02, 0.04),
}
QUICK_CASES = (
    "anchor",
    "lung",
    "jump",
    "shape",
    "breath",
)  # --quick: the balanced and imaged lungs are the suite's own tests
A_PRIORI = {  # the a priori PGD's terms at most and splines' intervals (None: lungmech's default): full size, --quick
    "anchor": ((10, None), (10, None)),
    "lung": ((10, None), (10, None)),
    "jump": ((50, 4), (8, 4)),
    "shape": ((20, 8), (8, 4)),
    "breath": ((20, 2), (12, 1)),  # nonlinear: Newton on the axes' Gauss grid, 8³ (4³) points
    "balanced": ((40, 1), (20, 1)),  # the tangents at the points' states: 4⁴ points
    "imaged": ((40, 1), (12, 1)),  # its reference and its breath, each by Newton: 4³ points
}
FITTED = {
    "jump": ((128,), ()),
    "breath": ((32, 64, 128), (8,)),
    "balanced": ((32, 64), ()),
    "imaged": ((32, 64), ()),
}  # the fitted PGD's sample sizes: full size, --quick


def scene_of(folder: Path, name: str, quick: bool) -> scenes.Scene:
    text, h, coarse = CASES[name]
    path = folder / f"{name}.toml"
    size = coarse if quick else h
    if name == "shape":  # its library, on the scene's own mesh
        library(scenes.load(scene_file(path, LUNG.format(h=size))), folder / "modes.npz")
    return scenes.load(scene_file(path, text.format(h=size, w=2 * size)))  # a jump's width: two cells


def scene_file(path: Path, text: str) -> Path:
    """``text`` written to ``path`` by rank 0, every rank waiting."""
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(text)
    MPI.COMM_WORLD.barrier()
    return path


def library(scene: scenes.Scene, path: Path) -> None:
    """Two shape modes of ``scene``'s mesh into ``path``: the mass-weighted POD of 8 members, each
    two smooth changes of a few mm (a bulge of the base, a lateral sway growing with height)
    mixed at random."""
    from lungmech.mesh import nodes
    from lungmech.registration.library import shape_modes

    comm = MPI.COMM_WORLD
    mesh = scenes.build_geometry(scene.geometry, comm).mesh
    space, where = nodes.displacement_space(mesh)
    X, weights = comm.bcast(nodes.positions(space, where)), comm.bcast(nodes.masses(space, where))
    top = X[:, 2] - X[:, 2].min()
    changes = [
        0.02 * np.column_stack([np.zeros(len(X)), np.zeros(len(X)), -np.exp(-top / 0.05) * 0.2]),
        0.02 * np.column_stack([(top / 0.24) ** 2 * 0.3, np.zeros(len(X)), np.zeros(len(X))]),
    ]
    latent = np.random.default_rng(5).normal(size=(8, 2))
    members = [np.einsum("k,knd->nd", z, np.array(changes)) for z in latent]
    modes = shape_modes(X, members, weights, where.fingerprint, tuple(f"lung{i}" for i in range(8)))
    if comm.rank == 0:
        modes.save(path)
    comm.barrier()


def errors(model, states: list[np.ndarray], exact: list[np.ndarray], W) -> tuple[np.ndarray, np.ndarray]:
    """Each point's relative nodal (ℓ2) and energy-norm error."""
    comm = MPI.COMM_WORLD
    nodal, energy = [], []
    for u, e in zip(states, exact):
        d = u - e
        nodal.append(np.sqrt(comm.allreduce(float(d @ d)) / comm.allreduce(float(e @ e))))
        energy.append(float(norms(d[:, None], W, comm)[0] / norms(e[:, None], W, comm)[0]))
    return np.array(nodal), np.array(energy)


def answers(model, points: list[dict]) -> tuple[list[np.ndarray], float]:
    """Each point's full state (owned entries) and the median online milliseconds (after one
    solve at the first point, untimed: the first assembly's and caches' warm-up)."""
    states, seconds = [], []
    model.solve(points[0], times=[model.stepping.end])
    for point in points:
        tic = time.perf_counter()
        solution = model.solve(point, times=[model.stepping.end])
        seconds.append(time.perf_counter() - tic)
        states.append(model_state(model, solution))
    return states, 1e3 * float(np.median(seconds))


def model_state(model, solution) -> np.ndarray:
    """The full owned state of a solution's last row: a full model's own, a reduced or PGD one's made."""
    return model.reconstruct(solution, -1) if hasattr(model, "reconstruct") else solution.states[-1]


def measured(base: dict, model: str, offline: float, online: float, solves: int, errors: tuple) -> dict:
    """A table row: a model's offline seconds, online milliseconds, full solves offline and its
    (nodal, energy) errors at the points, max and median."""
    nodal, energy = errors
    return base | {
        "model": model,
        "offline [s]": offline,
        "online [ms]": online,
        "full solves offline": solves,
        "nodal error max": nodal.max(),
        "nodal error median": float(np.median(nodal)),
        "energy error max": energy.max(),
        "energy error median": float(np.median(energy)),
    }


def measure(
    name: str, quick: bool, folder: Path, grid: tuple[int, int] | None, curves: dict
) -> tuple[list[dict], dict | None]:
    comm = MPI.COMM_WORLD
    scene = scene_of(folder, name, quick)
    # an imaged body's on its image, as its reduced models (their states are its motion from the image)
    full = full_order_model(scene, comm, start="inverse_motion" if scene.inverse else "imaged")
    box = full.parameters
    points = box.sample(8 if quick else 50, seed=11)
    say(f"{name}: {len(points)} full solves at the test points")
    exact, full_ms = answers(full, points)
    W = inner_product(full.model, "energy")
    dofs = full.model.space.dofmap.index_map.size_global * full.model.space.dofmap.index_map_bs
    base = {"case": name, "dofs": dofs, "ranks": comm.size, "points": len(points)}
    rows = [base | {"model": "full", "offline [s]": 0.0, "online [ms]": full_ms, "full solves offline": 0}]

    for samples in FITTED.get(name, ((), ()))[quick]:
        say(f"{name}: the PGD fitted to {samples} full solves")
        file = folder / f"{name}-pgd-{samples}.npz"
        tic = time.perf_counter()  # its own cache: every solve is made and timed
        summary = build_pgd(scene, file, modes=40, comm=comm, samples=samples, cache=folder / str(samples))
        offline = time.perf_counter() - tic
        pgd = reduce.load(file, comm, fields=True)
        states, online = answers(pgd, points)
        named = f"PGD fitted ({summary['terms']} terms, {summary['modes']} modes)"
        rows.append(measured(base, named, offline, online, samples, errors(full.model, states, exact, W)))
        for intervals, curve in pgd.built["held_out_by_intervals"].items():
            curves[f"{name}, {samples} solves, intervals {intervals}, {comm.size} rank(s)"] = curve
    if name in A_PRIORI:
        modes, intervals = A_PRIORI[name][quick]
        say(f"{name}: the PGD built a priori ({modes} terms at most)")
        tic = time.perf_counter()
        try:
            summary = build_pgd(scene, folder / f"{name}-pgd.npz", modes=modes, intervals=intervals, comm=comm)
        except ParameterError as error:  # a refusal is a result too: a row of its own, its line said
            say(f"{name}: the a priori PGD was refused: {error}")
            refused = {"model": "PGD a priori: refused", "offline [s]": time.perf_counter() - tic}
            rows.append(base | refused | {"online [ms]": float("nan"), "full solves offline": 0})
        else:
            offline = time.perf_counter() - tic
            pgd = reduce.load(folder / f"{name}-pgd.npz", comm, fields=True)
            states, online = answers(pgd, points)
            named = f"PGD ({summary['terms']} terms, {summary['modes']} modes)"
            rows.append(measured(base, named, offline, online, 0, errors(full.model, states, exact, W)))
            seconds = summary["offline_seconds"]
            rows[-1]["offline terms+greedy [s]"] = seconds["terms"] + seconds.get("greedy", seconds.get("newton", 0.0))

    # --quick leaves out the breath's nonlinear hyper-reduction (47 s) and the shape's (the suite tests
    # it); the balanced lung's is the real-time lung's benchmark's (rom_real_time.py): here its NNLS
    # ran more than 20 minutes
    if not (quick and name in ("shape", "breath")) and name not in ("balanced", "imaged"):
        say(f"{name}: the hyper-reduced model (8 full solves)")
        tic = time.perf_counter()
        reduce.build(
            scene, folder / f"{name}-ecsw.npz", size=10, samples=8, hyper="ecsw", comm=comm, cache=folder / "cache"
        )
        offline = time.perf_counter() - tic
        hyper = reduce.load(folder / f"{name}-ecsw.npz", comm, fields=True)
        states, online = answers(hyper, points)
        named = f"POD ECSW τ=1e-4 ({hyper.size} vectors)"
        rows.append(measured(base, named, offline, online, 8, errors(full.model, states, exact, W)))
    mapped = None
    if grid is not None:
        say(f"{name}: the error map, {grid[0]} × {grid[1]} points")
        names = box.names
        first, second = box.named(names[0]), box.named(names[1])
        a = [first.from_unit(s) for s in (np.arange(grid[0]) + 0.5) / grid[0]]
        b = [second.from_unit(s) for s in (np.arange(grid[1]) + 0.5) / grid[1]]
        at = [{names[0]: x, names[1]: y} for x in a for y in b]
        truth, _ = answers(full, at)
        found, _ = answers(pgd, at)
        _, map_errors = errors(full.model, found, truth, W)
        mapped = {"x": a, "y": b, "errors": map_errors.reshape(grid), "names": (names[0], names[1])}
    W.destroy()
    return rows, mapped


def markdown(rows: list[dict], command: str) -> str:
    ranks = sorted({int(r["ranks"]) for r in rows})
    runs = " and ".join(str(n) for n in ranks)
    lines = [
        "# The PGD, a priori and fitted, beside the full model and a hyper-reduced model",
        "",
        f"{provenance(command, f'{runs} rank(s), each from its own run (this command: the last)')} Errors at random points of each box against the full model: relative nodal "
        "(ℓ2 over every dof, NeuROM's measure) and relative energy norm (the energy product at the defaults). "
        "Online: median milliseconds of `solve(μ, times=[T])` (volume, strain energy, probes). Offline: the "
        "whole build, in seconds (the a priori PGD's terms and greedy — a nonlinear model's Newton iterations — alone in brackets), its full solves "
        "included. The breath's a priori PGD iterates on residual assemblies at its parameters' Gauss grid; the balanced lung's "
        "(the breath under its weight, carried by a pleural pressure gradient that moves with the state, its posture a fourth "
        "parameter) also on Jacobians there, each point's tangent at its state on the modes' span; the imaged lung's "
        "(its reference found at every μ, the breath from the image) first its reference's, then its breath's. "
        "The fitted PGD are fitted to their full solves (at most 40 terms; their number and the splines' "
        "intervals chosen on a held-out quarter of the solves).",
        "",
        "| case | ranks | dofs | model | full solves offline | offline [s] | online [ms] | nodal error max (median) "
        "| energy error max (median) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        inner = r.get("offline terms+greedy [s]")
        offline = f"{r['offline [s]']:.1f}" + (f" ({inner:.1f})" if isinstance(inner, float) else "")
        nodal = (
            "—"
            if not isinstance(r.get("nodal error max"), float)
            else (f"{r['nodal error max']:.1e} ({r['nodal error median']:.1e})")
        )
        energy = (
            "—"
            if not isinstance(r.get("energy error max"), float)
            else (f"{r['energy error max']:.1e} ({r['energy error median']:.1e})")
        )
        lines.append(
            f"| {r['case']} | {r['ranks']} | {r['dofs']} | {r['model']} | {r['full solves offline']} | {offline} | "
            f"{r['online [ms]']:.2f} | {nodal} | {energy} |"
        )
    low, high = PUBLISHED["error"]
    lines += [
        "",
        f"NeuROM's NN-PGD on the anchor plate (published): {low:g} to {high:g} relative nodal error at 8 test "
        f"points on {PUBLISHED['dofs']} dofs after ≈ {PUBLISHED['seconds']:g} s of training on a CPU, no MPI.",
    ]
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], mapped: dict | None, curves: dict, path: Path) -> None:
    """Left: the anchor PGD's energy-norm error over its box. Middle: error against online time,
    a marker per case and model (filled: one rank, hollow: two). Right: the fitted PGD's held-out
    error against its number of terms, a colour per case and sample, a line per choice of
    intervals. The legends in a row of their own below, so that the axes keep their size."""
    from matplotlib.lines import Line2D

    fig = plt.figure(figsize=(17, 6.6))
    grid = fig.add_gridspec(2, 3, height_ratios=(1.0, 0.42), hspace=0.3, wspace=0.42)
    left, right, third = (fig.add_subplot(grid[0, k]) for k in range(3))
    keys_below, curves_below = fig.add_subplot(grid[1, 1]), fig.add_subplot(grid[1, 2])
    for spare in (fig.add_subplot(grid[1, 0]), keys_below, curves_below):
        spare.axis("off")
    if mapped is not None:
        image = left.pcolormesh(
            mapped["y"], mapped["x"], np.log10(np.maximum(mapped["errors"], 1e-16)), shading="nearest"
        )
        fig.colorbar(image, ax=left, label="log₁₀ relative energy-norm error [-]")
        left.set_yscale("log")
        left.set_xlabel(f"{mapped['names'][1]} [deg]")
        left.set_ylabel(f"{mapped['names'][0]} [Pa]")
        left.set_title("the anchor plate's PGD over its box", fontsize=10)
    measured = [r for r in rows if isinstance(r.get("energy error max"), float)]
    kinds = list(dict.fromkeys(_kind(r) for r in measured))  # a case's model, whatever its terms on each run
    colours = plt.get_cmap("tab20").colors
    for r in measured:
        k = kinds.index(_kind(r))
        marker, colour = "os^vD<>ph*"[k % 10], colours[k % 20]
        face = colour if int(r["ranks"]) == 1 else "none"
        right.loglog(r["online [ms]"], r["energy error max"], marker, color=colour, markerfacecolor=face, ms=7)
    right.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    right.set_xlabel("online time per point [ms]")
    right.set_ylabel("largest relative energy-norm error [-]")
    right.set_title("error against online time (filled: 1 rank, hollow: 2)", fontsize=10)
    right.grid(alpha=0.3, which="both")
    handles = [
        Line2D([], [], marker="os^vD<>ph*"[k % 10], color=colours[k % 20], ls="", label=kind)
        for k, kind in enumerate(kinds)
    ]
    keys_below.legend(handles=handles, fontsize=7.5, loc="upper center", ncol=2, frameon=False)
    # a colour per case and sample size, a line style per intervals an axis ("intervals 2,2,2": 2)
    sizes = list(dict.fromkeys(label.split(" solves")[0] for label in curves))
    choices = sorted({_intervals(label) for label in curves})
    styles = ["-", "--", ":", "-."]
    for label, curve in curves.items():
        colour = plt.get_cmap("tab10").colors[sizes.index(label.split(" solves")[0]) % 10]
        style = styles[choices.index(_intervals(label)) % 4]
        third.semilogy(np.arange(1, len(curve) + 1), curve, style, marker=".", ms=3, color=colour)
    third.set_xlabel("separated terms [-]")
    third.set_ylabel("held-out relative energy-norm error, max [-]")
    ranks = sorted({label.rsplit(", ", 1)[1] for label in curves})
    third.set_title(f"the fitted PGD: choosing its terms and intervals ({', '.join(ranks)})", fontsize=10)
    third.grid(alpha=0.3, which="both")
    if curves:
        handles = [
            Line2D([], [], color=plt.get_cmap("tab10").colors[i % 10], label=f"{size} solves")
            for i, size in enumerate(sizes)
        ]
        handles += [
            Line2D([], [], color="k", ls=styles[i % 4], label=f"{choice} interval(s) an axis (a periodic one ≥ 4)")
            for i, choice in enumerate(choices)
        ]
        curves_below.legend(handles=handles, fontsize=7.5, loc="upper center", ncol=2, frameon=False)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def _intervals(label: str) -> int:
    """The intervals an axis of a curve's label, a periodic axis's at least 4 left aside ("…,
    intervals 4,2,2, 1 rank(s)": 2): its fewest."""
    return min(int(k) for k in label.split("intervals ")[1].split(", ")[0].split(","))


def _kind(row: dict) -> str:
    """A row's case and model without its terms ("breath: PGD fitted, 32 solves")."""
    model = str(row["model"]).split(" (")[0]
    solves = int(float(row["full solves offline"])) if row.get("full solves offline") not in (None, "") else 0
    return f"{row['case']}: {model}" + (f", {solves} solves" if model.startswith("PGD fitted") else "")


def _mapped(saved: dict | None) -> dict | None:
    """The anchor's error map as :func:`plot` takes it, from its JSON (lists)."""
    return None if saved is None else {k: v if k == "names" else np.asarray(v) for k, v in saved.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="coarse meshes, 8 points, a 3 × 4 map")
    parser.add_argument("--ranks", type=int, default=1, help="run on this many ranks (mpiexec)")
    parser.add_argument("--replot", action="store_true", help="draw the plot again from the results (no solve)")
    parser.add_argument(
        "--cases", nargs="+", choices=list(CASES), help="only these cases (the results' other rows are kept)"
    )
    args = parser.parse_args()
    stem = "pgd_quick" if args.quick else "pgd"
    if args.replot:
        saved = RESULTS / f"{stem}_plot.json"
        if not saved.is_file():
            sys.exit(
                f"pgd.py: --replot: {saved} not found: a run writes it (python benchmarks/pgd.py{' --quick' * args.quick})"
            )
        drawn = json.loads(saved.read_text())
        plot(read_results(RESULTS / f"{stem}.csv"), _mapped(drawn["map"]), drawn["curves"], RESULTS / f"{stem}.png")
        return
    machine.relaunch(args.ranks, __file__, COMMAND)
    comm = MPI.COMM_WORLD
    command = "python benchmarks/pgd.py " + os.environ.get(COMMAND, " ".join(sys.argv[1:]))
    cases = [n for n in args.cases or CASES if n in QUICK_CASES or not args.quick]
    saved = RESULTS / f"{stem}_plot.json"
    drawn = json.loads(saved.read_text()) if args.cases and saved.is_file() else {"map": None, "curves": {}}
    with tempfile.TemporaryDirectory() as work:
        folder = Path(comm.bcast(work if comm.rank == 0 else None))
        curves: dict = {}
        rows, mapped = [], _mapped(drawn["map"])
        for name in cases:
            grid = ((3, 4) if args.quick else (12, 24)) if name == "anchor" else None
            found, drawn_map = measure(name, args.quick, folder, grid, curves)
            rows += found
            mapped = drawn_map if name == "anchor" else mapped
    if comm.rank == 0:
        path = RESULTS / f"{stem}.csv"
        kept = [
            r
            for r in (read_results(path) if path.exists() else [])
            if r.get("ranks") != comm.size or r.get("case") not in cases
        ]
        order = list(CASES)
        rows = kept + [r | {"command": command.strip()} for r in rows]
        rows.sort(key=lambda r: (int(r["ranks"]), order.index(r["case"])))
        write_results(RESULTS, stem, rows, markdown(rows, command.strip()))
        # what the plot needs beside the table, for --replot
        curves = drawn["curves"] | curves
        drawn = {"map": None if mapped is None else {k: np.asarray(v).tolist() for k, v in mapped.items()}}
        saved.write_text(json.dumps(drawn | {"curves": curves}))
        plot(rows, mapped, curves, RESULTS / f"{stem}.png")
        print((RESULTS / f"{stem}.md").read_text())


if __name__ == "__main__":
    main()
