"""Nothing a solve touched outlives it: the model, its forms and its mesh are freed, with the
mesh's MPI communicators (Python 3.13.0-3.13.1 kept every differentiated UFL form alive,
CPython gh-127750; lungmech._dispatch mends that Python)."""

import gc
import weakref

from mpi4py import MPI

import pytest
from fem import pushed_block

from lungmech._dispatch import leaks


def test_singledispatchmethod_keeps_nothing_alive():
    assert not leaks()


@pytest.mark.serial  # under MPI, PETSc frees a parallel solver (and the Python objects it calls) collectively, later
def test_a_solved_model_and_its_mesh_are_freed():
    """solve(μ) twice, with sensitivities (UFL derivatives of the forms), as a sweep does."""

    def solved() -> weakref.ref:
        full = pushed_block(MPI.COMM_WORLD, cells=(2, 1, 1))
        full.solve({"E": 12.0})
        full.solve({"E": 8.0}, sensitivities=True)
        return weakref.ref(full.model.geometry.mesh)

    mesh = solved()
    gc.collect()
    assert mesh() is None, "the mesh (and its communicators) outlived the model"
