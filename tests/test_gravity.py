"""Gravity on the lung held at its hilum, with and without the balancing pleural pressure.

Independent reference: the reaction at the hilum, read from the residual at its nodes. Held
by the hilum alone, the lung hangs there (reaction = −weight); with the balancing pressure
the hilum carries nothing, in force and in moment.
"""

import numpy as np
import pytest
from fem import MESHES
from mpi4py import MPI

from lungmech.errors import ParameterError
from lungmech.fem.constraints import clamp
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.quantities import reaction
from lungmech.fem.solver import solve
from lungmech.lung.gravity import Gravity
from lungmech.mesh import from_file

DENSITY, G = 300.0, np.array([0.0, 0.0, -9.81])
SURROUNDING = ("pleura", "diaphragm", "mediastinum")


@pytest.fixture(scope="module")
def lung():
    return from_file(MESHES / "lung_phantom_right.msh", MPI.COMM_WORLD)


def _hilum_reaction(lung, gravity):
    model = Model(lung, NeoHookean.from_young(1e4, 0.3), loads=[gravity], constraints=[clamp("hilum")])
    report = solve(model)
    return model, report, reaction(model, "hilum")()


def test_without_balance_the_hilum_carries_the_weight(lung):
    weight = DENSITY * lung.volume() * G
    _, _, held = _hilum_reaction(lung, Gravity(DENSITY, G))
    assert held.force == pytest.approx(-weight, abs=1e-9 * np.linalg.norm(weight))


def test_balancing_pressure_leaves_the_hilum_unloaded(lung):
    weight = np.linalg.norm(DENSITY * lung.volume() * G)
    model, report, held = _hilum_reaction(lung, Gravity(DENSITY, G, balanced_on=SURROUNDING))
    assert np.linalg.norm(held.force) < 1e-9 * weight
    assert np.linalg.norm(held.moment) < 1e-9 * weight * lung.size
    sag = model.displacement().x.array.reshape(-1, 3)[:, 2]
    assert sag.min() < -1e-4  # the lung does deform under its weight and the pressure gradient
    assert report.newton_iterations < 80  # linear convergence of the lagged coefficients, bounded


def test_a_surface_that_cannot_balance_the_weight_is_an_error(lung):
    # The mediastinal face is flat: its pressure pushes along x only, never against a weight along z.
    with pytest.raises(ParameterError, match="no pressure on mediastinum can balance"):
        _hilum_reaction(lung, Gravity(DENSITY, G, balanced_on=("mediastinum",)))
