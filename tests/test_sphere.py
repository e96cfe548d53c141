"""Thick-walled sphere under internal pressure: incompressible neo-Hookean, Taylor–Hood P2–P1,
against the closed form (VERIFICATION.md), with a follower pressure on curved quadratic cells."""

from mpi4py import MPI

import analytic as A
import pytest
from fem import inflated_sphere, mean_inner_radius

from lungmech.fem.solver import Stepping

P = 0.2871548459  # gives λ_a = 1.1 for A = 1, B = 2, μ = 1


def inner_displacement(mesh_size: float) -> float:
    return mean_inner_radius(inflated_sphere(MPI.COMM_WORLD, mesh_size, P, Stepping(initial_step=0.5))) - 1.0


def test_reference_value():
    assert A.thick_sphere_inner_stretch(P, 1.0, 2.0, 1.0) == pytest.approx(1.1, rel=1e-9)


@pytest.mark.slow
def test_thick_sphere_converges_to_closed_form():
    exact = A.thick_sphere_inner_stretch(P, 1.0, 2.0, 1.0) - 1.0
    errors = [abs(inner_displacement(h) - exact) / exact for h in (0.5, 0.3)]
    assert errors[1] < 0.01  # ≤ 1 % at the chosen mesh (measured: 0.11 %)
    assert errors[1] < 0.8 * errors[0]  # and converging under refinement
