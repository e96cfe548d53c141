"""The inverse problem: imaged (loaded) geometry -> unloaded reference -> direct solve -> imaged again."""

from mpi4py import MPI

import numpy as np
import pytest
from fem import bundled_lung

from lungmech.errors import ParameterError, SolverError
from lungmech.fem.loads import FollowerPressure
from lungmech.fem.model import Model
from lungmech.fem.solver import Stepping, solve
from lungmech.lung.gravity import Gravity
from lungmech.lung.inverse import InverseOptions, node_displacements, unloaded_reference

SURROUNDING = ("pleura", "diaphragm", "mediastinum")


def end_expiration_lung(comm=MPI.COMM_WORLD) -> Model:
    """The bundled lung as imaged at end-expiration: pleural suction −500 Pa and its weight."""
    loads = [FollowerPressure(b, -500.0) for b in SURROUNDING]
    loads.append(Gravity(315.0, (0.0, 0.0, -9.81), balanced_on=SURROUNDING))
    return bundled_lung(loads, comm)


@pytest.mark.slow
def test_inverse_then_direct_recovers_the_imaged_nodes():
    model = end_expiration_lung()
    mesh = model.geometry.mesh
    imaged, imaged_volume = mesh.geometry.x.copy(), model.geometry.volume()
    report = unloaded_reference(model, time=1.0)
    assert report.mismatch[-1] <= 1e-9 and report.iterations < 15
    assert model.geometry.volume() < 0.9 * imaged_volume  # the suction had inflated the lung

    # Round trip: a fresh direct solve, from the unloaded reference and zero loads.
    model.reset()
    solve(model, Stepping(end=1.0))
    nodes = mesh.geometry.x[:, :3] + node_displacements(model)()
    owned = mesh.geometry.index_map().size_local
    local = np.abs(nodes - imaged[:, :3])[:owned].max() / model.geometry.size
    assert mesh.comm.allreduce(local, op=MPI.MAX) <= 1e-6


@pytest.mark.slow
def test_inverse_errors():
    model = end_expiration_lung(MPI.COMM_SELF)
    with pytest.raises(ParameterError, match="tolerance"):
        InverseOptions(tolerance=0.0)
    with pytest.raises(ParameterError, match="max_iterations"):
        InverseOptions(max_iterations=0)
    with pytest.raises(SolverError, match="no unloaded reference within 1 iterations"):
        unloaded_reference(model, time=1.0, options=InverseOptions(max_iterations=1))
