"""Thick-walled sphere under internal pressure: incompressible neo-Hookean, Taylor–Hood P2–P1,
against the closed form (VERIFICATION.md), with a follower pressure on curved quadratic cells."""

import pytest
import ufl
from mpi4py import MPI

import analytic as A
from lungmech.constraints import symmetry
from lungmech.geometry import sphere
from lungmech.loads import FollowerPressure
from lungmech.materials import NeoHookean
from lungmech.model import Model
from lungmech.quantities import integral
from lungmech.solver import Stepping, solve

P = 0.2871548459  # gives λ_a = 1.1 for A = 1, B = 2, μ = 1


def inner_displacement(mesh_size: float) -> float:
    geometry = sphere(MPI.COMM_WORLD, 1.0, 2.0, mesh_size=mesh_size, octant=True, order=2)
    model = Model(
        geometry,
        NeoHookean.incompressible(1.0),
        degree=2,
        mixed=True,
        constraints=[symmetry("x0", "x"), symmetry("y0", "y"), symmetry("z0", "z")],
        loads=[FollowerPressure("inner", P)],
    )
    solve(model, Stepping(initial_step=0.5))
    x = ufl.SpatialCoordinate(geometry.mesh)
    radius = ufl.sqrt(ufl.dot(x + model.u, x + model.u))
    return integral(radius * geometry.ds("inner"), geometry.mesh.comm)() / geometry.area("inner") - 1.0


def test_reference_value():
    assert A.thick_sphere_inner_stretch(P, 1.0, 2.0, 1.0) == pytest.approx(1.1, rel=1e-9)


def test_thick_sphere_converges_to_closed_form():
    exact = A.thick_sphere_inner_stretch(P, 1.0, 2.0, 1.0) - 1.0
    errors = [abs(inner_displacement(h) - exact) / exact for h in (0.5, 0.3)]
    assert errors[1] < 0.01  # ≤ 1 % at the chosen mesh (measured: 0.11 %)
    assert errors[1] < 0.8 * errors[0]  # and converging under refinement
