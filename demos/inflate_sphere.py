"""Inflate a thick-walled incompressible neo-Hookean sphere and compare with the closed form.

Taylor–Hood P2–P1 on curved quadratic tetrahedra, a follower pressure on the cavity, adaptive
load stepping up to 90 % of the limit-point pressure. Writes a pressure–stretch plot,
sphere_inflation.png, into the output folder (default demos/output/inflate_sphere).

    python demos/inflate_sphere.py [-o FOLDER]
"""

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
from mpi4py import MPI

import matplotlib.pyplot as plt
import numpy as np
import ufl

from lungmech.fem.constraints import symmetry
from lungmech.fem.loads import FollowerPressure
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.quantities import integral
from lungmech.fem.solver import Stepping, solve
from lungmech.mesh import sphere
from lungmech.parallel.destination import output_folder

A, B, MU = 1.0, 2.0, 1.0
FRACTION = 0.9  # of the limit-point pressure: the last load step


def closed_form_pressure(stretch: np.ndarray) -> np.ndarray:
    """P(λ_a) of the incompressible neo-Hookean thick sphere (outer stretch from volume conservation)."""
    outer = np.cbrt(1 + (stretch**3 - 1) * (A / B) ** 3)
    return MU * (2 / outer + 1 / (2 * outer**4) - 2 / stretch - 1 / (2 * stretch**4))


def main(output: Path) -> None:
    """Inflate the sphere and write the plot into the (empty) folder ``output``."""
    stretches = np.linspace(1.0, 3.0, 400)
    limit = closed_form_pressure(stretches).max()
    geometry = sphere(MPI.COMM_WORLD, A, B, mesh_size=0.3, octant=True, order=2)
    model = Model(
        geometry,
        NeoHookean.incompressible(MU),
        degree=2,
        mixed=True,
        constraints=[symmetry("x0", "x"), symmetry("y0", "y"), symmetry("z0", "z")],
        loads=[FollowerPressure("inner", FRACTION * limit)],
    )
    x = ufl.SpatialCoordinate(geometry.mesh)
    inner_radius = integral(ufl.sqrt(ufl.dot(x + model.u, x + model.u)) * geometry.ds("inner"), geometry.mesh.comm)
    area = geometry.area("inner")
    curve = [(0.0, 1.0)]
    solve(
        model,
        Stepping(initial_step=0.05, max_step=0.05),
        on_step=lambda step: curve.append((FRACTION * limit * step.time, inner_radius() / area)),
    )

    if MPI.COMM_WORLD.rank == 0:
        pressure, stretch = np.array(curve).T
        error = np.abs(pressure - closed_form_pressure(stretch)).max() / limit
        print(
            f"{len(curve) - 1} steps to {100 * FRACTION:.0f} % of the limit-point pressure; "
            f"max |P_FE - P_exact| / P_max = {error:.2e}"
        )
        fig, ax = plt.subplots(figsize=(5.5, 4))
        ax.plot(stretches, closed_form_pressure(stretches), "k-", label="closed form")
        ax.plot(stretch, pressure, "o", color="tab:red", label="lungmech, P2–P1 mixed")
        ax.axhline(limit, color="gray", ls=":", label="limit point")
        ax.set_xlabel("inner stretch a/A")
        ax.set_ylabel("internal pressure P / μ")
        ax.set_title("Thick-walled sphere (B = 2A), incompressible neo-Hookean")
        ax.legend()
        fig.tight_layout()
        fig.savefig(output / "sphere_inflation.png", dpi=120)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "-o", "--output", type=Path, default=Path(__file__).resolve().parent / "output" / "inflate_sphere"
    )
    target = parser.parse_args().output
    # Staged, and moved into place only when the demo succeeds; a folder that is not empty and
    # not lungmech's own is refused, so no file of the user's is ever overwritten.
    with output_folder(target, MPI.COMM_WORLD, command="python demos/inflate_sphere.py") as staging:
        main(staging)
    if MPI.COMM_WORLD.rank == 0:
        print(f"wrote {target / 'sphere_inflation.png'}")
