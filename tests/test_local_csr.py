"""LocalCSR: a DOLFINx matrix's rank-local rows times vectors, against its dense rows (DOLFINx's to_dense)."""

from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import fem, la

from lungmech.mesh import box
from lungmech.parallel.linalg import LocalCSR


def test_a_local_matrix_product_is_scipys_and_follows_the_matrix():
    """Products with a vector and with columns, |A|, and the values of a later assembly."""
    _check()


@pytest.mark.mpi
def test_a_local_matrix_product_on_two_ranks_holds_ghost_rows_and_columns():
    _check()


def _check():
    mesh = box(MPI.COMM_WORLD, cells=(3, 2, 2)).mesh
    space = fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u, v = ufl.TrialFunction(space), ufl.TestFunction(space)
    weight = fem.Constant(mesh, 1.0)
    form = fem.form(weight * ufl.inner(u, v) * ufl.dx + ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx)
    matrix = fem.create_matrix(form, block_mode=la.BlockMode.expanded)
    fem.assemble_matrix(matrix, form)
    local, reference = LocalCSR(matrix), _dense(matrix)
    rng = np.random.default_rng(MPI.COMM_WORLD.rank)
    columns = rng.standard_normal((reference.shape[1], 4))
    np.testing.assert_allclose(local @ columns, reference @ columns, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(local @ columns[:, 0], reference @ columns[:, 0], rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(abs(local) @ columns, np.abs(reference) @ columns, rtol=1e-13, atol=1e-15)
    weight.value = -3.0
    matrix.set_value(0.0)
    fem.assemble_matrix(matrix, form)  # in place: the product sees the new values
    np.testing.assert_allclose(local @ columns, _dense(matrix) @ columns, rtol=1e-13, atol=1e-15)
    assert np.abs(local @ columns - LocalCSR(matrix) @ columns).max() == 0.0


def _dense(matrix: la.MatrixCSR) -> np.ndarray:
    """The rank's rows (ghost rows too) on its local and ghost columns, from DOLFINx's to_dense
    (whose columns are global)."""
    columns = matrix.index_map(1)
    local = np.arange(columns.size_local + columns.num_ghosts, dtype=np.int32)
    return matrix.to_dense()[:, columns.local_to_global(local)]


def test_a_rank_holding_none_of_the_entries_has_an_empty_product():
    """A form over no cell of this rank (a hyper-reduced model's sample, all on other ranks):
    no value to share, and the product is zero (it was refused as a copy)."""
    from dolfinx.mesh import meshtags

    mesh = box(MPI.COMM_SELF, cells=(2, 1, 1)).mesh
    space = fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u, v = ufl.TrialFunction(space), ufl.TestFunction(space)
    none = meshtags(mesh, mesh.topology.dim, np.zeros(0, dtype=np.int32), np.zeros(0, dtype=np.int32))
    form = fem.form(ufl.inner(u, v) * ufl.dx(domain=mesh, subdomain_data=none, subdomain_id=1))
    matrix = fem.create_matrix(form, block_mode=la.BlockMode.expanded)
    fem.assemble_matrix(matrix, form)
    local = LocalCSR(matrix)
    assert local.data.size == 0
    assert np.all(local @ np.ones((matrix.index_map(1).size_local, 2)) == 0.0)
