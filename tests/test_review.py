"""Defects found by review: reactions of every formulation, rigid motions on curved meshes,
the model's state kept through errors."""

from __future__ import annotations

from mpi4py import MPI

import numpy as np
import pytest

from lungmech.errors import ParameterError
from lungmech.fem.constraints import clamp
from lungmech.fem.loads import Traction
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.quantities import reaction
from lungmech.fem.solver import Stepping, solve
from lungmech.lung import Poromechanics, skeleton
from lungmech.mesh import box, sphere

COMM = MPI.COMM_SELF
PULL = np.array([0.3, -0.2, -1.0])  # traction on x1 (unit area), Pa


@pytest.mark.parametrize(
    "make",
    [
        lambda g: Model(g, NeoHookean.from_young(1e3, 0.3), constraints=[clamp("x0")], loads=[Traction("x1", PULL)]),
        lambda g: Model(
            g,
            NeoHookean.from_young(1e3, 0.45),
            degree=2,
            mixed=True,
            constraints=[clamp("x0")],
            loads=[Traction("x1", PULL)],
        ),
        lambda g: Model(
            g,
            skeleton(160.0, 0.5, 200.0, 400.0),
            formulation=Poromechanics(1e4, 0.3),
            constraints=[clamp("x0")],
            loads=[Traction("x1", PULL)],
        ),
    ],
    ids=["displacement", "mixed", "poromechanics"],
)
def test_the_support_carries_the_load_in_every_formulation(make):
    model = make(box(COMM, (1.0, 1.0, 1.0), (2, 2, 2)))
    solve(model, Stepping(), monitor=lambda step: None)
    assert reaction(model, "x0")().force == pytest.approx(-PULL, abs=1e-9)


def test_straight_displacements_on_curved_cells_are_refused():
    curved = sphere(COMM, 1.0, 2.0, octant=True, order=2)
    with pytest.raises(ParameterError, match="cannot move the body rigidly"):
        Model(curved, NeoHookean.from_young(1.0, 0.3), degree=1)
    Model(curved, NeoHookean.from_young(1.0, 0.3), degree=2)  # P2 on P2 cells is isoparametric


def test_the_state_survives_an_error_inside_kept_state():
    model = Model(box(COMM, cells=(1, 1, 1)), NeoHookean.from_young(1.0, 0.3))
    model.state.x.array[:] = 0.25
    with pytest.raises(RuntimeError):
        with model.kept_state():
            model.reset()
            raise RuntimeError("drawing failed")
    assert np.all(model.state.x.array == 0.25)
