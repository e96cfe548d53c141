# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # A reduced model of the breathing lung
#
# A reduced-order model is built once, offline, from a few solves of the full model, and then
# answers new loads online in a space of a few vectors. This demo runs that chain from
# Python on the bundled default scene: the right lung imaged at end-expiration under a
# pleural pressure of −500 Pa, with its weight balanced.
#
# * **Offline**: the imaged lung is unloaded once; the full model then breathes at two tidal
#   depths, 0.5 and 1.5 times the scene's swing (−500 → −1000 → −500 Pa), and every converged
#   state is a snapshot; POD in the mass inner product keeps the significant directions; the
#   reduced model is saved.
# * **Online**: the saved model is loaded and breathes at depths 0.75 and 1.25 (between the
#   training ones) and 2.0 (beyond them), each breath compared with the full model's.
#
# Run it as `python demos/reduced_lung.py [-o FOLDER]`. The command line does the same with
# `lungmech rom build` and `lungmech rom solve` ([reduced-order models](../guide/reduced.md)).

# %%
import time
from importlib import resources

import matplotlib

matplotlib.use("Agg")
from mpi4py import MPI

import matplotlib.pyplot as plt
import numpy as np

from lungmech import rom
from lungmech.app.demo import Demo
from lungmech.app.run import build_model
from lungmech.app.scene import load
from lungmech.fem.quantities import deformed_volume
from lungmech.fem.solver import NewtonSolver, solve
from lungmech.lung.inverse import unloaded_reference

comm = MPI.COMM_WORLD
scene_file = resources.files("lungmech.scenes") / "lung_breathing.toml"
with resources.as_file(scene_file) as path:
    scene = load(path)
    demo = Demo("reduced_lung", inputs=[path])
TRAINING, UNSEEN = (0.5, 1.5), (0.75, 1.25, 2.0)
SWING = 500.0  # Pa: the scene's pleural pressure goes −500 → −1000 → −500


def breathe(model, solver, depth: float) -> tuple[np.ndarray, float]:
    """One breath at ``depth`` × the scene's swing from the imaged state: (pressure, volume) rows and seconds."""
    volume = deformed_volume(model)
    stepping, ramp = scene.stepping, scene.loads[0].ramp
    curve = [(SWING, volume())]
    tic = time.perf_counter()
    solve(
        model,
        stepping,
        solver=solver,
        on_step=lambda step: curve.append((SWING * (1 + depth * (ramp(step.time) - 1)), volume())),
        drive=lambda t: model.set_time(t, load_factor=(depth, 1.0), about=stepping.start),
        breakpoints=model.breakpoints,
    )
    return np.array(curve), time.perf_counter() - tic


# %% [markdown]
# ## Offline
#
# `rom.snapshots` runs the full model along each training breath and keeps every converged
# state; `rom.pod` keeps the directions whose singular values stand above the solver's
# tolerance and round-off; `rom.save` writes the basis with the mesh's fingerprint, which
# `rom.load` checks.

# %%
tic = time.perf_counter()
model = build_model(scene, comm)
full = NewtonSolver(model, scene.newton)
unloaded_reference(model, scene.stepping.start, scene.inverse, solver=full)
start = model.state.x.array.copy()
snapshots = rom.snapshots(model, scene.stepping, [(s, 1.0) for s in TRAINING], solver=full, start=start)
basis = rom.pod(model, snapshots, inner="mass", size=20)
rom.save(demo.folder / "reduced_lung.npz", model, basis)
offline = time.perf_counter() - tic
demo.report("snapshots", snapshots.shape[1])
demo.report(
    "basis",
    basis.size,
    f"offline: {snapshots.shape[1]} snapshots, POD basis of {basis.size} vectors "
    f"(σ/σ0 = {', '.join(f'{v:.1e}' for v in basis.values / basis.values[0])}), {offline:.0f} s",
)

# %% [markdown]
# The {glue:text}`snapshots:.0f` snapshots of the two training breaths give a POD basis of
# {glue:text}`basis:.0f` vectors.
#
# ## Online
#
# The reduced solver is Newton's method on the basis coefficients: the full residual and
# tangent are assembled and projected at every iteration (hyper-reduction removes that
# assembly: see the guide). Each breath starts from the imaged state.

# %%
reduced_basis, _, _ = rom.load(demo.folder / "reduced_lung.npz", model)
reduced = rom.ReducedSolver(model, reduced_basis, scene.newton, start=start)
breaths = {}
for index, depth in enumerate(UNSEEN):
    model.state.x.array[:] = start
    exact, full_seconds = breathe(model, full, depth)
    model.state.x.array[:] = start
    approximate, reduced_seconds = breathe(model, reduced, depth)
    breaths[depth] = exact, approximate
    error = abs(approximate[:, 1].max() - exact[:, 1].max()) / exact[:, 1].max()
    demo.report(f"full_{index}", 1e3 * exact[:, 1].max())
    demo.report(f"reduced_{index}", 1e3 * approximate[:, 1].max())
    demo.report(
        f"error_{index}",
        error,
        f"depth {depth}: end-inspiration volume {1e3 * exact[:, 1].max():.4f} L full, "
        f"{1e3 * approximate[:, 1].max():.4f} L reduced (relative error {error:.1e}); "
        f"{full_seconds:.1f} s full, {reduced_seconds:.1f} s reduced",
    )
    # Between the training depths the family of states is spanned to solver tolerance; beyond
    # them the basis extrapolates.
    assert error < (1e-8 if depth < max(TRAINING) else 1e-6), f"depth {depth}: relative error {error:.1e}"

# %% [markdown]
# | depth | end-inspiration volume, full | reduced | relative error |
# |---|---|---|---|
# | 0.75 (between) | {glue:text}`full_0:.4f` L | {glue:text}`reduced_0:.4f` L | {glue:text}`error_0:.1e` |
# | 1.25 (between) | {glue:text}`full_1:.4f` L | {glue:text}`reduced_1:.4f` L | {glue:text}`error_1:.1e` |
# | 2.0 (beyond) | {glue:text}`full_2:.4f` L | {glue:text}`reduced_2:.4f` L | {glue:text}`error_2:.1e` |
#
# The quasi-static breath with balanced gravity is a one-parameter family of states, so a
# handful of POD vectors is exact to the solver's tolerance between the training depths (the
# demo requires 1e-8) and nearly so beyond them (1e-6). Below 1e-7 σ₁ the singular values are
# the snapshots' noise, and POD drops them.

# %%
figure, (loops, decay) = plt.subplots(1, 2, figsize=(11, 4.2))
for depth, (exact, approximate) in breaths.items():
    (line,) = loops.plot(-exact[:, 0], 1e3 * exact[:, 1], lw=3, alpha=0.35, label=f"full, depth {depth}")
    loops.plot(
        -approximate[:, 0], 1e3 * approximate[:, 1], "--", color=line.get_color(), label=f"reduced ({basis.size} POD)"
    )
loops.set(xlabel="pleural pressure [Pa]", ylabel="lung volume [L]", title="breaths not in the training set")
loops.legend(fontsize=7)
singular = np.array(basis.source["singular_values"])
decay.semilogy(np.arange(1, len(singular) + 1), singular / singular[0], "o-")
decay.axhline(1e-7, color="grey", ls=":", label="kept above 1e-7 σ₁ (below: solver tolerance and round-off)")
decay.set(xlabel="POD index", ylabel="σ_i / σ_1", title=f"POD of {snapshots.shape[1]} snapshots", ylim=(1e-12, 2))
decay.legend(fontsize=7)
figure.tight_layout()
demo.figure(figure, "reduced_lung.png")
demo.close()
