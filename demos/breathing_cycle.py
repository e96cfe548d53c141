"""Breathing of the bundled left lung: spontaneous breathing against mechanical ventilation.

The mesh plays the lung imaged at end-expiration (pleural pressure −500 Pa). The inverse
problem first finds its unloaded reference. Then two cycles start from the imaged state:

* spontaneous: the pleural pressure goes −500 → −1000 → −500 Pa, the alveolar pressure stays 0;
* ventilator: the pleural pressure stays −500 Pa, the alveolar pressure goes 0 → 500 → 0 Pa.

Both raise the transpulmonary pressure p_f − p_pleural from 500 to 1000 Pa. Without the
porosity barrier the displacement equation sees p_f and the pleural pressure only through
that difference (Φs alone feels p_f), so the two P–V loops coincide to round-off: the demo
prints their difference. Writes breathing_cycle.png (both loops) and the deformed lung at
end-inspiration for each mode into the output folder (default demos/output/breathing_cycle).

    python demos/breathing_cycle.py [-o FOLDER]
"""

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
from mpi4py import MPI

import matplotlib.pyplot as plt
import numpy as np

from lungmech import meshes
from lungmech.app.plot import deformed_body
from lungmech.fem.constraints import clamp
from lungmech.fem.loads import FollowerPressure
from lungmech.fem.model import Model
from lungmech.fem.quantities import deformed_volume
from lungmech.fem.ramp import Ramp
from lungmech.fem.solver import NewtonSolver, Stepping, solve
from lungmech.lung import AlveolarPressure, Poromechanics, skeleton
from lungmech.lung.inverse import unloaded_reference
from lungmech.mesh import from_file
from lungmech.parallel.destination import output_folder

MESH = meshes.reference("lung_phantom_left")
SURFACE = ("pleura", "diaphragm", "mediastinum")
CYCLE = Ramp((0.0, 1.0, 2.0), (0.0, 1.0, 0.0))  # 0 at both end-expirations, 1 at end-inspiration
SWING = 500.0  # Pa


def breathe(model: Model, pleural: Ramp, alveolar: Ramp, picture: Path) -> tuple[np.ndarray, np.ndarray]:
    """One cycle from the imaged state: transpulmonary pressure and volume after every step."""
    volume = deformed_volume(model)
    curve = [(SWING, volume())]

    def record(step) -> None:
        t = step.time
        transpulmonary = SWING * alveolar(t) - (-SWING * pleural(t))
        curve.append((transpulmonary, volume()))
        if abs(t - 1.0) < 1e-12:
            deformed_body(model, picture, "left lung at end-inspiration")

    solve(model, Stepping(end=2.0, initial_step=0.1, max_step=0.1), on_step=record)
    return np.array(curve).T


def lung(pleural: Ramp, alveolar: Ramp) -> Model:
    return Model(
        from_file(MESH, MPI.COMM_WORLD),
        skeleton(160.0, 0.5, 200.0, 400.0),
        formulation=Poromechanics(1e4, 0.3),
        loads=[FollowerPressure(SURFACE, -SWING, pleural), AlveolarPressure(SWING, alveolar)],
        constraints=[clamp("hilum")],
    )


def main(output: Path) -> None:
    """Both cycles; the pictures go into the (empty) folder ``output``."""
    modes = {
        "spontaneous (pleural −500 → −1000 Pa)": (Ramp((0.0, 1.0, 2.0), (1.0, 2.0, 1.0)), Ramp((0.0, 2.0), (0.0, 0.0))),
        "ventilator (alveolar 0 → 500 Pa)": (Ramp((0.0, 2.0), (1.0, 1.0)), CYCLE),
    }
    curves = {}
    for index, (name, (pleural, alveolar)) in enumerate(modes.items()):
        model = lung(pleural, alveolar)
        imaged = model.geometry.volume()
        report = unloaded_reference(model, time=0.0, solver=NewtonSolver(model))
        unloaded = model.geometry.volume()  # collective: on every rank, not in the rank-0 block below
        if MPI.COMM_WORLD.rank == 0:
            print(
                f"{name}: imaged {imaged * 1e3:.3f} L, unloaded {unloaded * 1e3:.3f} L "
                f"({report.iterations} fixed-point iterations)"
            )
        curves[name] = breathe(model, pleural, alveolar, output / f"breathing_cycle_inspired_{index}.png")
    if MPI.COMM_WORLD.rank != 0:
        return
    fig, ax = plt.subplots(figsize=(5.5, 4))
    for (name, (pressure, volume)), style in zip(curves.items(), ("-o", "--s")):
        ax.plot(pressure, volume * 1e3, style, ms=3, label=name)
    ax.set_xlabel("transpulmonary pressure p_f − p_pleural [Pa]")
    ax.set_ylabel("lung volume [L]")
    ax.set_title("Left lung, one breath from the imaged end-expiration")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(output / "breathing_cycle.png", dpi=150)
    (spont_p, spont_v), (vent_p, vent_v) = curves.values()
    peak = (spont_v.max() - vent_v.max()) / spont_v.max()
    print(
        f"end-inspiration volumes: spontaneous {spont_v.max() * 1e3:.4f} L, ventilator {vent_v.max() * 1e3:.4f} L "
        f"(relative difference {peak:+.2e})"
    )


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "-o", "--output", type=Path, default=Path(__file__).resolve().parent / "output" / "breathing_cycle"
    )
    target = parser.parse_args().output
    # Staged, and moved into place only when the demo succeeds; a folder that is not empty and
    # not lungmech's own is refused, so no file of the user's is ever overwritten.
    with output_folder(target, MPI.COMM_WORLD, inputs=[MESH], command="python demos/breathing_cycle.py") as staging:
        main(staging)
    if MPI.COMM_WORLD.rank == 0:
        print(f"wrote {target / 'breathing_cycle.png'}")
