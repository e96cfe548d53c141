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
# # Inflating a thick-walled sphere
#
# A hollow sphere of incompressible neo-Hookean rubber, inner radius $A = 1$, outer radius
# $B = 2$, shear modulus $\mu = 1$, is inflated by a pressure $P$ on its cavity. The pressure
# follows the inner surface as it grows (a follower load). Incompressibility makes the
# deformation radial, and the exact pressure is a function of the inner stretch
# $\lambda_a = a/A$ alone:
#
# $$
# \frac{P}{\mu} = \frac{2}{\lambda_b} + \frac{1}{2\lambda_b^4} - \frac{2}{\lambda_a}
#   - \frac{1}{2\lambda_a^4},
# \qquad \lambda_b^3 = 1 + (\lambda_a^3 - 1)\left(\frac{A}{B}\right)^3 .
# $$
#
# $P$ rises to a maximum, the limit point, and then falls: beyond it the sphere inflates at a
# falling pressure, as a balloon does. This demo drives the finite-element model to 90 % of
# the limit-point pressure and compares its pressure–stretch curve with the closed form.
#
# Run it as `python demos/inflate_sphere.py [-o FOLDER]`, or on several ranks as
# `mpiexec -n 2 python demos/inflate_sphere.py`.

# %%
import matplotlib

matplotlib.use("Agg")
from mpi4py import MPI

import matplotlib.pyplot as plt
import numpy as np
import ufl

from lungmech.app.demo import Demo
from lungmech.fem.constraints import symmetry
from lungmech.fem.loads import FollowerPressure
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.quantities import integral
from lungmech.fem.solver import Stepping, solve
from lungmech.mesh import sphere

demo = Demo("inflate_sphere")
A, B, MU = 1.0, 2.0, 1.0
FRACTION = 0.9  # of the limit-point pressure: the last load step


def closed_form_pressure(stretch: np.ndarray) -> np.ndarray:
    """P(λ_a) of the incompressible neo-Hookean thick sphere (outer stretch from volume conservation)."""
    outer = np.cbrt(1 + (stretch**3 - 1) * (A / B) ** 3)
    return MU * (2 / outer + 1 / (2 * outer**4) - 2 / stretch - 1 / (2 * stretch**4))


stretches = np.linspace(1.0, 3.0, 400)
limit = closed_form_pressure(stretches).max()

# %% [markdown]
# ## The model
#
# One eighth of the sphere, meshed by gmsh with curved quadratic tetrahedra, with symmetry on
# the three cut planes. An incompressible law needs the mixed formulation: Taylor–Hood
# P2–P1, the displacement and a pressure that enforces $J = 1$. The follower pressure on
# `inner` ramps from 0 to 90 % of the limit point over the time $t \in [0, 1]$.

# %%
geometry = sphere(MPI.COMM_WORLD, A, B, mesh_size=0.3, octant=True, order=2)
model = Model(
    geometry,
    NeoHookean.incompressible(MU),
    degree=2,
    mixed=True,
    constraints=[symmetry("x0", "x"), symmetry("y0", "y"), symmetry("z0", "z")],
    loads=[FollowerPressure("inner", FRACTION * limit)],
)

# %% [markdown]
# ## Load stepping
#
# Newton's method with load steps of at most 0.05. After every step, the mean inner radius is
# the deformed radius $|x + u|$ averaged over the inner surface (in the reference, where its
# area is known).

# %%
x = ufl.SpatialCoordinate(geometry.mesh)
inner_radius = integral(ufl.sqrt(ufl.dot(x + model.u, x + model.u)) * geometry.ds("inner"), geometry.mesh.comm)
area = geometry.area("inner")
curve = [(0.0, 1.0)]
solve(
    model,
    Stepping(initial_step=0.05, max_step=0.05),
    on_step=lambda step: curve.append((FRACTION * limit * step.time, inner_radius() / area)),
)
pressure, stretch = np.array(curve).T

# %% [markdown]
# ## Against the closed form
#
# The error is the largest difference of the model's pressure from the exact one at the same
# stretch, relative to the limit-point pressure $P_{max}$.

# %%
error = np.abs(pressure - closed_form_pressure(stretch)).max() / limit
demo.report("percent", 100 * FRACTION)
demo.report("steps", len(curve) - 1)
demo.report("stretch", stretch[-1])
demo.report(
    "error",
    error,
    f"{len(curve) - 1} steps to {100 * FRACTION:.0f} % of the limit-point pressure; "
    f"max |P_FE - P_exact| / P_max = {error:.2e}",
)
assert error < 1e-3, f"the sphere's pressure misses the closed form by {error:.1e} of P_max"

# %% [markdown]
# The model took {glue:text}`steps:.0f` load steps to {glue:text}`percent:.0f` % of the
# limit-point pressure, where the inner radius has grown by a factor
# {glue:text}`stretch:.2f`, and agrees with the closed form to {glue:text}`error:.1e` of
# $P_{max}$ (the demo requires 1e-3: the discretisation error of P2 on this mesh).

# %%
fig, ax = plt.subplots(figsize=(5.5, 4))
ax.plot(stretches, closed_form_pressure(stretches), "k-", label="closed form")
ax.plot(stretch, pressure, "o", color="tab:red", label="lungmech, P2–P1 mixed")
ax.axhline(limit, color="gray", ls=":", label="limit point")
ax.set_xlabel("inner stretch a/A")
ax.set_ylabel("internal pressure P / μ")
ax.set_title("Thick-walled sphere (B = 2A), incompressible neo-Hookean")
ax.legend()
fig.tight_layout()
demo.figure(fig, "sphere_inflation.png")
demo.close()
