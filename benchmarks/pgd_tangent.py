"""Why the a priori PGD of a lung balanced under its weight takes each point's tangent at its
state: Newton at single points of the box, with the tangents a Newton–PGD could hold fixed.

    python benchmarks/pgd_tangent.py           # mesh 0.03, 16 load steps, three points (a minute)
    python benchmarks/pgd_tangent.py --quick   # mesh 0.04, 4 load steps, the softest point (the suite's case)

The Newton–PGD (:mod:`lungmech.pgd.newton`) iterates with one tangent for the whole box: the
residual's at rest, separated in μ like a linear operator (a tangent at the state u(μ) is no
separated operator). Its iterations can only converge where a modified Newton with that tangent
converges at each point of the box, and this measures that modified Newton point by point,
along the load path in equal steps, on two scenes:

* **breath**: ``pgd.py``'s nonlinear lung (poromechanics, the lung skeleton's law, a follower
  pleural pressure of depth 0.6–1.4 × −300 Pa; α over 100–300 Pa and c1 over 100–400 Pa), whose
  Newton–PGD converges;
* **balanced**: the same lung under its weight, carried by a pleural pressure gradient (gravity
  ``balanced_on`` the lung's surface, :mod:`lungmech.lung.gravity`), the posture over −90°–0°:
  a load whose coefficients θ = Θ(u) move with the state, the tangent K + U Vᵀ.

Four tangents: **exact**, the tangent at every iterate (full Newton, with the balance's coupling
U Vᵀ, :mod:`lungmech.fem.state_dependent`); **rest**, the material's at rest with the loads off
(the Newton–PGD's); **rest, coupled**, that one with the balance's coupling at rest under the
step's loads; **rest + loads**, the whole tangent at rest under the step's loads. A step
ends when Newton's step is below 1e-9 of the state; it fails when the residual is not finite or
after 100 iterations, and the path stops there. Serial (a point's Newton, not a parallel code).

Writes results/pgd_tangent.md, .csv and .png (``_quick`` with --quick).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import cast

from mpi4py import MPI
from petsc4py import PETSc

import machine
import matplotlib
import numpy as np
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix

from lungmech import jit
from lungmech.app import scene as scenes
from lungmech.app.run import full_order_model
from lungmech.fem.linear import factorised
from lungmech.fem.model import Model
from lungmech.fem.quantities import assemble_owned
from lungmech.fem.state_dependent import StateDependent
from lungmech.parallel.owned import owned_size

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from machine import provenance, write_results  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from pgd import BREATH, WEIGHT  # noqa: E402  (the nonlinear lung of the PGD benchmark, and its weight)

RESULTS = machine.RESULTS
POINTS = {  # the points of the box (a parameter not named: its default)
    "default": {},
    "soft, deep": {"alpha": 100.0, "c1": 100.0, "breath": 1.4, "posture": -90.0},
    "stiff, shallow": {"alpha": 300.0, "c1": 400.0, "breath": 0.6, "posture": 0.0},
}
TANGENTS = ("exact", "rest", "rest, coupled", "rest + loads")
STEP = 1e-9  # a step has converged when Newton's step is below this fraction of the state
ITERATIONS = 100  # a step fails after this many iterations


class Pointwise:
    """``model``'s residual R(u, Θ(u)) and tangent K + U Vᵀ at a state u (owned entries, from
    rest), θ recomputed from the state at each residual."""

    def __init__(self, model: Model) -> None:
        self.model, self.owned = model, owned_size(model.space)
        self.imposed = model.constrained_dofs()
        self.coupled = StateDependent(model)
        self._residual, self._jacobian = jit.form(model.residual), jit.form(model.jacobian)
        self._work = fem.Function(model.space).x
        with model.kept_state():
            model.reset()
            self.rest = model.state.x.array.copy()

    def put(self, u: np.ndarray) -> None:
        self.model.state.x.array[:] = self.rest
        self.model.state.x.array[: self.owned] += u
        self.model.state.x.scatter_forward()
        self.coupled.update()

    def residual(self, u: np.ndarray) -> np.ndarray:
        self.put(u)
        r = assemble_owned(self._residual, self._work, self.owned)
        r[self.imposed] = 0.0
        return r

    def tangent(self, u: np.ndarray, loads: bool = True, coupled: bool = True) -> Callable[[np.ndarray], np.ndarray]:
        """r ↦ (K + U Vᵀ)⁻¹ r at the state ``u`` (Woodbury's identity on one factorisation of K):
        K with the ``loads`` at the model's time or off, U Vᵀ there or left out (``coupled``)."""
        model, t = self.model, self.model.time
        if not loads:
            model.set_time(0.0)  # (every load's ramp is 0 there)
        self.put(u)
        K = assemble_matrix(self._jacobian, bcs=model.bcs)
        K.assemble()
        model.set_time(t)
        solver = factorised(K)
        x, b = cast(tuple[PETSc.Vec, PETSc.Vec], K.createVecs())

        def solve(r: np.ndarray) -> np.ndarray:
            b.array[:] = r
            solver.solve(b, x)
            return x.array.copy()

        if not (self.coupled and coupled):
            return solve
        self.put(u)  # θ at the loads of the time
        U, V = self.coupled.low_rank()
        return lambda r: self.coupled.woodbury(solve(r), U, V, solve)


def path(pointwise: Pointwise, point: dict[str, float], tangent: str, steps: int) -> list[int]:
    """Newton's iterations at each load step t = k/steps from rest, with ``tangent`` (module
    docstring); the last entry -1 where a step failed (the path stops there)."""
    model = pointwise.model
    model.set_parameters({k: v for k, v in point.items() if k in model.parameters.names})
    u, found = np.zeros(pointwise.owned), []
    rest = np.zeros(pointwise.owned)
    fixed = pointwise.tangent(rest, loads=False, coupled=False)  # the Newton–PGD's
    for t in np.arange(1, steps + 1) / steps:
        model.set_time(float(t))
        if tangent == "rest, coupled":
            fixed = pointwise.tangent(rest, loads=False)
        elif tangent == "rest + loads":
            fixed = pointwise.tangent(rest)
        iterations = 0
        while True:
            r = pointwise.residual(u)
            if not np.isfinite(r).all() or iterations == ITERATIONS:
                return [*found, -1]
            step = (pointwise.tangent(u) if tangent == "exact" else fixed)(r)
            u, iterations = u - step, iterations + 1
            if np.linalg.norm(step) <= STEP * np.linalg.norm(u):
                break
        found.append(iterations)
    return found


def measure(quick: bool, folder: Path) -> list[dict]:
    steps, size = (4, 0.04) if quick else (16, 0.03)
    points = {"soft, deep": POINTS["soft, deep"]} if quick else POINTS
    rows = []
    for scene_name, extra in (("breath", ""), ("balanced", WEIGHT)):
        scene_file = folder / f"{scene_name}.toml"
        scene_file.write_text(BREATH.format(h=size) + extra)
        model = full_order_model(scenes.load(scene_file)).model
        pointwise = Pointwise(model)
        for point_name, point in points.items():
            for tangent in TANGENTS if pointwise.coupled else [t for t in TANGENTS if t != "rest, coupled"]:
                found = path(pointwise, point, tangent, steps)
                done = [n for n in found if n > 0]
                failed = bool(found) and found[-1] < 0
                rows.append(
                    {
                        "scene": scene_name,
                        "point": point_name,
                        "tangent": tangent,
                        "dofs": model.space.dofmap.index_map.size_global * model.space.dofmap.index_map_bs,
                        "steps": steps,
                        "converged_steps": len(done),
                        "iterations": sum(done),
                        "most_in_a_step": max(done, default=0),
                        "failed_at_t": round((len(done) + 1) / steps, 4) if failed else "",
                        "per_step": " ".join(str(n) for n in found),
                    }
                )
                machine.say(rows[-1])
    return rows


def markdown(rows: list[dict], command: str) -> str:
    lines = [
        "# Newton at points of the box, with the tangents a Newton–PGD could hold fixed",
        "",
        provenance(command) + " Newton's iterations along the load path in equal steps from rest, at single points of "
        "the box, each step converged to 1e-9 of the state (a step fails when the residual is not "
        "finite or after 100 iterations; the path stops there). **exact**: the tangent at every "
        "iterate, with the balance's coupling U Vᵀ; **rest**: the material's at rest, the loads off "
        "(the Newton–PGD's); **rest, coupled**: that one with the balance's coupling at rest under the "
        "step's loads; **rest + loads**: the whole tangent at rest under the step's loads.",
        "",
        "| scene | dofs | point | tangent | steps converged | iterations | most in a step | failed at t [s] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['dofs']} | {r['point']} | {r['tangent']} | {r['converged_steps']} of {r['steps']} "
            f"| {r['iterations']} | {r['most_in_a_step']} | {r['failed_at_t'] or '—'} |"
        )
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    scenes_drawn = list(dict.fromkeys(r["scene"] for r in rows))
    figure, axes = plt.subplots(1, len(scenes_drawn), figsize=(5.5 * len(scenes_drawn), 4.2), sharey=True)
    colours = dict(zip(TANGENTS, ("tab:green", "tab:blue", "tab:orange", "tab:red")))
    styles = dict(zip(POINTS, ("-", "--", ":")))
    for ax, scene_name in zip(np.atleast_1d(axes), scenes_drawn):
        for r in (r for r in rows if r["scene"] == scene_name):
            counts = [int(n) for n in str(r["per_step"]).split()]
            t = np.arange(1, len(counts) + 1) / r["steps"]
            done = [n for n in counts if n > 0]
            ax.plot(t[: len(done)], done, styles[r["point"]], color=colours[r["tangent"]], marker="o")
            if counts and counts[-1] < 0:  # the failed step, at the cap (each tangent a little higher)
                cap = ITERATIONS * 1.15 ** TANGENTS.index(r["tangent"])
                ax.plot([t[len(done)]], [cap], "x", color=colours[r["tangent"]], markersize=10, mew=2)
        ax.set_yscale("log")
        ax.set_xlim(0.0, 1.05)
        ax.set_xlabel("load step's end t [s] (the loads' ramp: t)")
        ax.set_title(f"{scene_name}: Newton's iterations a step (× failed)")
        ax.grid(True, which="both", alpha=0.3)
    np.atleast_1d(axes)[0].set_ylabel("Newton iterations in the step")
    drawn_points = list(dict.fromkeys(r["point"] for r in rows))
    handles = [Line2D([], [], color=colour, marker="o", label=f"tangent: {name}") for name, colour in colours.items()]
    handles += [Line2D([], [], color="grey", linestyle=styles[name], label=f"point: {name}") for name in drawn_points]
    np.atleast_1d(axes)[0].legend(handles=handles, fontsize=7, loc="upper right", ncols=2)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="mesh 0.04, 4 load steps, the softest point")
    args = parser.parse_args()
    if MPI.COMM_WORLD.size > 1:
        sys.exit("pgd_tangent.py: a point's Newton, on one rank: run it without mpiexec")
    stem = "pgd_tangent_quick" if args.quick else "pgd_tangent"
    command = "python benchmarks/pgd_tangent.py" + " --quick" * args.quick
    with tempfile.TemporaryDirectory() as work:
        rows = measure(args.quick, Path(work))
    write_results(RESULTS, stem, rows, markdown(rows, command))
    plot(rows, RESULTS / f"{stem}.png")
    print((RESULTS / f"{stem}.md").read_text())


if __name__ == "__main__":
    main()
