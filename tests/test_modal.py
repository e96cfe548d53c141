"""Modal analysis: a slender clamped beam against Euler–Bernoulli, M-orthonormal modes."""

from mpi4py import MPI

import numpy as np
import pytest

from lungmech.errors import ParameterError
from lungmech.fem.constraints import clamp
from lungmech.fem.materials import LinearElastic, NeoHookean
from lungmech.fem.modal import mass_matrix, modal_analysis
from lungmech.fem.model import Model
from lungmech.mesh import box

BETA_L = np.array([1.8751040687, 4.6940911330])  # VERIFICATION.md, first two bending modes
LENGTH, SIDE, E, RHO = 10.0, 0.5, 1.0, 1.0  # slenderness 20


def cantilever(comm=MPI.COMM_WORLD, clamped=True) -> Model:
    geometry = box(comm, lengths=(LENGTH, SIDE, SIDE), cells=(40, 2, 2))
    return Model(geometry, LinearElastic.from_young(E, 0.0), degree=2, constraints=[clamp("x0")] if clamped else [])


def euler_bernoulli() -> np.ndarray:
    inertia, area = SIDE**4 / 12.0, SIDE**2
    return BETA_L**2 * np.sqrt(E * inertia / (RHO * area * LENGTH**4))


def test_cantilever_frequencies_and_orthonormality():
    model = cantilever()
    modes = modal_analysis(model, 4, density=RHO)
    # A square section bends alike in y and z: each frequency comes twice, resolved as two modes.
    expected = np.repeat(euler_bernoulli(), 2)
    assert modes.frequencies == pytest.approx(expected, rel=0.02)
    assert np.all(modes.frequencies <= expected * 1.001)  # a 3-D beam with ν = 0 is slightly softer
    M = mass_matrix(model, RHO)
    gram = np.array([[v.x.petsc_vec.dot(M * w.x.petsc_vec) for w in modes.vectors] for v in modes.vectors])
    # SLEPc's tolerance is 1e-10: within a repeated pair, M-orthogonality holds to about that.
    assert gram == pytest.approx(np.eye(4), abs=1e-8)
    assert not modes.rigid.any()


def test_free_body_has_six_rigid_modes():
    modes = modal_analysis(cantilever(MPI.COMM_SELF, clamped=False), 8, density=RHO)
    assert modes.rigid.sum() == 6 and not modes.rigid[6:].any()


def test_modal_errors():
    model = cantilever(MPI.COMM_SELF, clamped=False)
    with pytest.raises(ParameterError, match="negative shift"):
        modal_analysis(model, 2, shift=0.0)
    with pytest.raises(ParameterError, match="count"):
        modal_analysis(model, 0)
    mixed = Model(box(MPI.COMM_SELF, cells=(1, 1, 1)), NeoHookean.from_young(1.0, 0.3), degree=2, mixed=True)
    with pytest.raises(ParameterError, match="displacement formulation"):
        modal_analysis(mixed, 2)
