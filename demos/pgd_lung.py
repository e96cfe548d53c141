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
# # A lung's answer over its whole parameter box, built a priori (PGD)
#
# A reduced model learns from full solves; a Proper Generalised Decomposition needs none. It
# writes the lung's displacement over the whole box of its parameters as a sum of separated
# terms, $u(x, \mu) \approx \sum_k \bar u_k(x) \prod_j \lambda_k^j(\mu_j)$, and finds them from
# the model's own equations integrated over the box ([PGD](../guide/pgd.md)).
#
# Here the lung phantom is linear elastic, clamped on its mediastinal face and loaded by its own
# weight. Three parameters span the box: its stiffness $E$ over a factor 10, and the posture
# turning the weight, the pitch over a full turn and the roll over ±90°. The PGD is built with
# no full solve, then checked against the full model at random points of the box, and over the
# (pitch, roll) plane.
#
# Run it as `python demos/pgd_lung.py [-o FOLDER]` (also under `mpiexec`). The command line does
# the same with `lungmech pgd build` and `lungmech rom solve --set`.

# %%
import time

import matplotlib

matplotlib.use("Agg")
from mpi4py import MPI

import matplotlib.pyplot as plt
import numpy as np

from lungmech.app import scene as scenes
from lungmech.app.demo import Demo
from lungmech.app.plot import deformed_body
from lungmech.app.run import build_model, full_order_model
from lungmech.parallel.linalg import norms
from lungmech.pgd.model import build
from lungmech.rom.basis import inner_product

demo = Demo("pgd_lung")
comm = MPI.COMM_WORLD

# %% [markdown]
# ## The scene
#
# A scene as a Python table: the generic right lung phantom on 3 cm cells, its weight
# ($\rho$ = 300 kg/m³ of tissue), $E$ around 3 kPa.

# %%
table = {
    "title": "a linear elastic lung phantom under its own weight",
    "geometry": {"builder": "lung_phantom", "mesh_size": 0.03},
    "material": {"law": "linear", "E": 3e3, "nu": 0.3},
    "constraints": [{"type": "clamp", "boundary": "mediastinum"}],
    "loads": [{"type": "gravity", "name": "gravity", "density": 300.0, "acceleration": [0.0, 0.0, -9.81]}],
    "stepping": {"end": 1.0, "initial_step": 1.0},
    "parameters": {
        "E": {"target": "material.E", "range": [1e3, 1e4], "scale": "log"},
        "pitch": {"target": "loads.gravity.pitch", "range": [-180.0, 180.0]},
        "roll": {"target": "loads.gravity.roll", "range": [-90.0, 90.0]},
    },
    "output": {"fields": False},
}
scene = scenes.parse(table)

# %% [markdown]
# ## The PGD, a priori
#
# `build` reads the model's residual as separated terms (from its own forms and its parameters'
# assignment), then adds terms greedily, each found by alternating directions and followed by
# an update of every term. No full solve enters.

# %%
tic = time.perf_counter()
pgd, rounds = build(build_model(scene, comm), scene.stepping)
offline = demo.report("offline_s", time.perf_counter() - tic, f"PGD built in {time.perf_counter() - tic:.1f} s")
terms = demo.report("terms", pgd.decomposition.terms, f"{pgd.decomposition.terms} separated terms")
modes = demo.report("modes", pgd.size, f"{pgd.size} space modes")
space = pgd.model.space.dofmap
dofs = demo.report("dofs", space.index_map.size_global * space.index_map_bs, "")

# %% [markdown]
# The build took {glue:text}`offline_s:.1f` s: {glue:text}`terms:.0f` separated terms on
# {glue:text}`modes:.0f` space modes, for {glue:text}`dofs:.0f` dofs. Gravity turned by a pitch
# and a roll has three components, each a sum of products of a sine or cosine of each angle,
# and the displacement scales with 1/E: the exact answer is a sum of a few separated terms, which
# the greedy finds.
#
# ## Against the full model
#
# At 12 random points of the box, the relative error in the energy norm (the energy product at
# the defaults) against the full model's own answer:

# %%
full = full_order_model(scene, comm)
W = inner_product(full.model, "energy")
end = scene.stepping.end


def error(point: dict) -> float:
    """‖u_PGD − u‖_W / ‖u‖_W at ``point``."""
    exact = full.solve(point, times=[end]).states[-1]
    found = pgd.reconstruct(pgd.solve(point, times=[end]), -1)
    return float(norms((found - exact)[:, None], W, comm)[0] / norms(exact[:, None], W, comm)[0])


errors = [error(point) for point in pgd.parameters.sample(12, seed=3)]
worst = demo.report("worst", max(errors), f"largest relative energy-norm error at 12 random points: {max(errors):.1e}")
tic = time.perf_counter()
for point in pgd.parameters.sample(200, seed=4):
    pgd.solve(point, times=[end])
online = demo.report("online_ms", 1e3 * (time.perf_counter() - tic) / 200, "")
assert worst < 1e-4  # the splines' error: 32 intervals per axis

# %% [markdown]
# The largest error is {glue:text}`worst:.1e`: what the splines on each axis leave, not the
# decomposition. One answer (the volume, the strain energy) takes {glue:text}`online_ms:.2f` ms.
#
# Over the (pitch, roll) plane at the default stiffness:

# %%
pitches, rolls = np.linspace(-165.0, 165.0, 12), np.linspace(-82.5, 82.5, 8)
plane = np.array([[error({"pitch": p, "roll": r}) for p in pitches] for r in rolls])
figure, axes = plt.subplots(figsize=(6.5, 3.6))
image = axes.pcolormesh(pitches, rolls, np.log10(plane), shading="nearest")
figure.colorbar(image, ax=axes, label="log₁₀ relative energy-norm error [-]")
axes.set_xlabel("pitch [deg] (−90: supine, 90: prone)")
axes.set_ylabel("roll [deg]")
axes.set_title(f"The PGD against the full model, E = {pgd.parameters.defaults['E']:g} Pa", fontsize=10)
figure.tight_layout()
demo.figure(figure, "pgd_error_map.png")

# %% [markdown]
# ## Its first space modes
#
# Each space mode is a displacement field of the lung, orthonormal to the others in the energy
# product; the answer at any point of the box is a combination of them. Drawn deformed (scaled
# to 2 cm at most), coloured by the local volume ratio J, with the share of each axis in the
# mode's motion (the mean of |uₓ|, |u_y|, |u_z| over the nodes, summing to 1):

# %%
model = pgd.model
with model.kept_state():
    for k in range(min(2, pgd.size)):
        mode = pgd.decomposition.modes[:, k]
        largest = comm.allreduce(float(np.abs(mode).max()), op=MPI.MAX)
        pgd.fields(np.eye(pgd.size)[k] * 0.02 / largest, end)  # the state Q z, z its k-th coordinate
        u = model.motion()
        motion = np.abs(u.x.array.reshape(-1, 3)[: u.function_space.dofmap.index_map.size_local])  # owned nodes
        along = np.array([comm.allreduce(float(c), op=MPI.SUM) for c in motion.sum(axis=0)])
        for axis, share in zip("xyz", along / along.sum()):
            demo.report(f"mode{k + 1}_{axis}", share, f"mode {k + 1}: {share:.2f} of its motion along {axis}")
        deformed_body(model, demo.folder / f"pgd_mode_{k + 1}.png", f"space mode {k + 1} (largest motion 2 cm)")
        demo.show(f"pgd_mode_{k + 1}.png")

# %% [markdown]
# | mode | along x (right) | along y (anterior) | along z (superior) |
# |---|---|---|---|
# | 1 | {glue:text}`mode1_x:.2f` | {glue:text}`mode1_y:.2f` | {glue:text}`mode1_z:.2f` |
# | 2 | {glue:text}`mode2_x:.2f` | {glue:text}`mode2_y:.2f` | {glue:text}`mode2_z:.2f` |
#
# The weight turns over every direction, and the modes share its directions between them; a
# point of the box weighs them by the splines of its pitch, roll and stiffness.

# %%
W.destroy()
demo.close()
