"""A reduced model of the breathing lung, built offline and used online for breaths it never saw.

Offline: the bundled default scene's lung (imaged at end-expiration, −500 Pa pleural pressure
and its balanced weight) is unloaded once; the full model then breathes at two tidal depths
(scale 0.5 and 1.5 of the scene's −500 Pa swing) and every converged state is a snapshot; POD
in the mass inner product keeps the significant directions; the reduced model is saved.
Online: the saved model is loaded and breathes at depths 0.75, 1.25 (between the training
ones) and 2.0 (beyond them); each breath is compared with the full model. Prints volumes,
errors and times, and writes reduced_lung.npz (the reduced model) and reduced_lung.png (P–V
loops, full against reduced; POD decay) into the output folder (default demos/output/reduced_lung).

    python demos/reduced_lung.py [-o FOLDER]
"""

import argparse
import time
from importlib import resources
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
from mpi4py import MPI

import matplotlib.pyplot as plt
import numpy as np

from lungmech import rom
from lungmech.app.run import build_model
from lungmech.app.scene import load
from lungmech.fem.quantities import deformed_volume
from lungmech.fem.solver import NewtonSolver, solve
from lungmech.lung.inverse import unloaded_reference
from lungmech.parallel.destination import output_folder

SCENE = resources.files("lungmech.scenes") / "lung_breathing.toml"
TRAINING, UNSEEN = (0.5, 1.5), (0.75, 1.25, 2.0)
SWING = 500.0  # Pa: the scene's pleural pressure goes −500 → −1000 → −500


def breathe(model, solver, scene, depth: float) -> tuple[np.ndarray, float]:
    """One breath at ``depth`` × the scene's swing from the imaged state: (pressure, volume) rows."""
    volume = deformed_volume(model)
    stepping = scene.stepping
    ramp = scene.loads[0].ramp
    curve = [(SWING, volume())]
    record = lambda step: curve.append((SWING * (1 + depth * (ramp(step.time) - 1)), volume()))  # noqa: E731
    tic = time.perf_counter()
    solve(
        model,
        stepping,
        solver=solver,
        on_step=record,
        drive=lambda t: model.set_time(t, load_factor=(depth, 1.0), about=stepping.start),
        breakpoints=model.breakpoints,
    )
    return np.array(curve), time.perf_counter() - tic


def main(scene_file: Path, out: Path) -> None:
    """Offline and online on the scene ``scene_file``; results go into the (empty) folder ``out``."""
    comm = MPI.COMM_WORLD
    scene = load(scene_file)

    # Offline: unload the imaged lung, train on two depths, POD, save.
    tic = time.perf_counter()
    model = build_model(scene, comm)
    full = NewtonSolver(model, scene.newton)
    unloaded_reference(model, scene.stepping.start, scene.inverse, solver=full)
    start = model.state.x.array.copy()
    snapshots = rom.snapshots(model, scene.stepping, [(s, 1.0) for s in TRAINING], solver=full, start=start)
    basis = rom.pod(model, snapshots, inner="mass", size=20)
    rom.save(out / "reduced_lung.npz", model, basis)
    offline = time.perf_counter() - tic

    # Online: load the basis (checked against this mesh) and breathe at unseen depths.
    basis, _, _ = rom.load(out / "reduced_lung.npz", model)
    reduced = rom.ReducedSolver(model, basis, scene.newton, start=start)
    if comm.rank == 0:
        print(
            f"offline: {snapshots.shape[1]} snapshots, POD basis of {basis.size} vectors "
            f"(σ/σ0 = {', '.join(f'{v:.1e}' for v in basis.values / basis.values[0])}), {offline:.0f} s"
        )
    figure, (loops, decay) = plt.subplots(1, 2, figsize=(11, 4.2))
    for depth in UNSEEN:
        model.state.x.array[:] = start
        exact, full_seconds = breathe(model, full, scene, depth)
        model.state.x.array[:] = start
        approximate, reduced_seconds = breathe(model, reduced, scene, depth)
        error = abs(approximate[:, 1].max() - exact[:, 1].max()) / exact[:, 1].max()
        if comm.rank == 0:
            print(
                f"depth {depth}: end-inspiration volume {1e3 * exact[:, 1].max():.4f} L full, "
                f"{1e3 * approximate[:, 1].max():.4f} L reduced (relative error {error:.1e}); "
                f"{full_seconds:.1f} s full, {reduced_seconds:.1f} s reduced"
            )
        (line,) = loops.plot(-exact[:, 0], 1e3 * exact[:, 1], lw=3, alpha=0.35, label=f"full, depth {depth}")
        loops.plot(
            -approximate[:, 0],
            1e3 * approximate[:, 1],
            "--",
            color=line.get_color(),
            label=f"reduced ({basis.size} POD vectors)",
        )
    loops.set(xlabel="pleural pressure [Pa]", ylabel="lung volume [L]", title="breaths not in the training set")
    loops.legend(fontsize=7)
    singular = np.array(basis.source["singular_values"])
    decay.semilogy(np.arange(1, len(singular) + 1), singular / singular[0], "o-")
    decay.axhline(1e-7, color="grey", ls=":", label="kept above 1e-7 σ₁ (below: solver tolerance and round-off)")
    decay.set(xlabel="POD index", ylabel="σ_i / σ_1", title=f"POD of {snapshots.shape[1]} snapshots", ylim=(1e-12, 2))
    decay.legend(fontsize=7)
    figure.tight_layout()
    if comm.rank == 0:
        figure.savefig(out / "reduced_lung.png", dpi=120)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "-o", "--output", type=Path, default=Path(__file__).resolve().parent / "output" / "reduced_lung"
    )
    target = parser.parse_args().output
    # Staged, and moved into place only when the demo succeeds; a folder that is not empty and
    # not lungmech's own is refused, so no file of the user's is ever overwritten.
    with (
        resources.as_file(SCENE) as scene_file,
        output_folder(target, MPI.COMM_WORLD, inputs=[scene_file], command="python demos/reduced_lung.py") as staging,
    ):
        main(scene_file, staging)
    if MPI.COMM_WORLD.rank == 0:
        print(f"wrote {target / 'reduced_lung.png'}")
