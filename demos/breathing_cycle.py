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
# # A breath of the left lung: spontaneous against ventilated
#
# The bundled left lung phantom plays a lung imaged at end-expiration, under a pleural
# pressure of −500 Pa. Its unloaded reference, the shape it would have with no load at all,
# is found first (the inverse problem). Then one breath starts from the imaged state, in two
# ways:
#
# * **spontaneous**: the pleural pressure goes −500 → −1000 → −500 Pa, the alveolar pressure
#   stays 0;
# * **ventilated**: the pleural pressure stays −500 Pa, the alveolar pressure goes
#   0 → 500 → 0 Pa.
#
# Both raise the transpulmonary pressure $p_f - p_{pl}$ from 500 to 1000 Pa. The lung is the
# poromechanical model of Patte, Genet & Chapelle (2022) without the porosity barrier
# $W_{pore}$: the displacement then sees the fluid and pleural pressures only through their
# difference (the solid fraction $\Phi_s$ alone feels $p_f$), so the two breaths must give
# the same pressure–volume loop, to round-off.
#
# Run it as `python demos/breathing_cycle.py [-o FOLDER]`, or `mpiexec -n 2 python demos/breathing_cycle.py`.

# %%
import matplotlib

matplotlib.use("Agg")
from mpi4py import MPI

import matplotlib.pyplot as plt
import numpy as np

from lungmech import meshes
from lungmech.app.demo import Demo
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

MESH = meshes.reference("lung_phantom_left")
demo = Demo("breathing_cycle", inputs=[MESH])

# %% [markdown]
# ## The lung
#
# The skeleton's strain energy is the sum of Patte et al.'s terms with
# $\alpha = 160$ Pa, $\gamma = 0.5$, $c_1 = 200$ Pa, $c_2 = 400$ Pa; the bulk term of the
# solid has $\kappa = 10^4$ Pa and the reference solid fraction is $\Phi_{s0} = 0.3$. The
# pleural pressure acts on the pleura, diaphragm and mediastinum as a follower pressure; the
# hilum, where the airways and vessels enter, is clamped. Each load is its amplitude times a
# ramp of the time: `CYCLE` is 0 at both end-expirations ($t = 0, 2$) and 1 at
# end-inspiration ($t = 1$).

# %%
SURFACE = ("pleura", "diaphragm", "mediastinum")
CYCLE = Ramp((0.0, 1.0, 2.0), (0.0, 1.0, 0.0))
SWING = 500.0  # Pa


def lung(pleural: Ramp, alveolar: Ramp) -> Model:
    """The left lung under the pleural pressure −SWING·pleural(t) and the alveolar SWING·alveolar(t)."""
    return Model(
        from_file(MESH, MPI.COMM_WORLD),
        skeleton(160.0, 0.5, 200.0, 400.0),
        formulation=Poromechanics(1e4, 0.3),
        loads=[FollowerPressure(SURFACE, -SWING, pleural), AlveolarPressure(SWING, alveolar)],
        constraints=[clamp("hilum")],
    )


MODES = {
    "spontaneous": (Ramp((0.0, 1.0, 2.0), (1.0, 2.0, 1.0)), Ramp((0.0, 2.0), (0.0, 0.0))),
    "ventilated": (Ramp((0.0, 2.0), (1.0, 1.0)), CYCLE),
}

# %% [markdown]
# ## Unloading, then breathing
#
# `unloaded_reference` moves the mesh to the reference from which the loads at $t = 0$ give
# back the imaged lung (a fixed point on the nodes). The breath then steps from the imaged
# state through $t \in [0, 2]$ in steps of 0.1, recording the transpulmonary pressure and the
# deformed volume after each.


# %%
def breathe(model: Model, pleural: Ramp, alveolar: Ramp, picture: str) -> np.ndarray:
    """One cycle from the imaged state: (transpulmonary pressure, volume) after every step."""
    volume = deformed_volume(model)
    curve = [(SWING, volume())]

    def record(step) -> None:
        t = step.time
        curve.append((SWING * alveolar(t) + SWING * pleural(t), volume()))
        if abs(t - 1.0) < 1e-12:
            deformed_body(model, demo.folder / picture, picture.removesuffix(".png").replace("_", " "))

    solve(model, Stepping(end=2.0, initial_step=0.1, max_step=0.1), on_step=record)
    return np.array(curve).T


curves = {}
for mode, (pleural, alveolar) in MODES.items():
    model = lung(pleural, alveolar)
    imaged = model.geometry.volume()
    report = unloaded_reference(model, time=0.0, solver=NewtonSolver(model))
    unloaded = model.geometry.volume()  # collective: on every rank
    demo.report(f"{mode}_imaged", 1e3 * imaged)
    demo.report(
        f"{mode}_unloaded",
        1e3 * unloaded,
        f"{mode}: imaged {1e3 * imaged:.3f} L, unloaded {1e3 * unloaded:.3f} L "
        f"({report.iterations} fixed-point iterations)",
    )
    curves[mode] = breathe(model, pleural, alveolar, f"{mode}_end_inspiration.png")

# %% [markdown]
# ## The two loops coincide
#
# The relative difference of the end-inspiration volumes is the test of the model's
# structure: it must be round-off.

# %%
(_, spontaneous), (_, ventilated) = curves.values()
difference = (spontaneous.max() - ventilated.max()) / spontaneous.max()
demo.report("spontaneous_inspired", 1e3 * spontaneous.max())
demo.report("ventilated_inspired", 1e3 * ventilated.max())
demo.report(
    "difference",
    difference,
    f"end-inspiration volumes: spontaneous {spontaneous.max() * 1e3:.4f} L, "
    f"ventilated {ventilated.max() * 1e3:.4f} L (relative difference {difference:+.2e})",
)
assert abs(difference) < 1e-12, f"the two breaths differ by {difference:.1e} relative"

# %% [markdown]
# Both start from the unloaded reference of the imaged lung
# ({glue:text}`spontaneous_imaged:.3f` L imaged, {glue:text}`spontaneous_unloaded:.3f` L
# unloaded) and inhale to {glue:text}`spontaneous_inspired:.3f` L. Their end-inspiration
# volumes differ by {glue:text}`difference:.1e` relative (the demo requires less than 1e-12).

# %%
fig, ax = plt.subplots(figsize=(5.5, 4))
labels = {"spontaneous": "spontaneous (pleural −500 → −1000 Pa)", "ventilated": "ventilated (alveolar 0 → 500 Pa)"}
for (mode, (pressure, volume)), style in zip(curves.items(), ("-o", "--s")):
    ax.plot(pressure, volume * 1e3, style, ms=3, label=labels[mode])
ax.set_xlabel("transpulmonary pressure p_f − p_pleural [Pa]")
ax.set_ylabel("lung volume [L]")
ax.set_title("Left lung, one breath from the imaged end-expiration")
ax.legend(fontsize=8)
ax.grid(alpha=0.3)
fig.tight_layout()
demo.figure(fig, "breathing_cycle.png")

# %% [markdown]
# The lung at end-inspiration, coloured by the local volume ratio $J = \det F$ from the
# unloaded reference. It is nearly uniform, about 1.5, the ratio of the inspired volume to the
# unloaded one: this lung is homogeneous and weightless, so nothing makes its base expand more
# than its apex (gravity would, [lung poromechanics](../guide/lung.md)).

# %%
demo.show("spontaneous_end_inspiration.png")
demo.close()
