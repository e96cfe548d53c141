"""lungmech.fem.stacked: the columns a(e_k; ·) of a form linear in a constant, assembled in one
pass over a stacked test space, are the ones assembled one unit at a time — on a vector space
and on a mixed one (a displacement and a cell field, as the poromechanical lung's), for a form
with a derivative in the state, a constant of any shape, and on a distributed mesh (ghost
cells' contributions summed on their owners)."""

from types import SimpleNamespace

from mpi4py import MPI

import numpy as np
import pytest
import ufl
from basix.ufl import element, mixed_element
from dolfinx import fem, la, mesh

from lungmech import jit
from lungmech.fem.stacked import StackedSpace, stacked_form, units
from lungmech.fem.state_dependent import FullIntegration
from lungmech.parallel.owned import owned_size


def _space(kind: str) -> fem.FunctionSpace:
    box = mesh.create_unit_cube(MPI.COMM_WORLD, 3, 2, 2)
    vector = element("Lagrange", "tetrahedron", 1, shape=(3,))
    if kind == "vector":
        return fem.functionspace(box, vector)
    return fem.functionspace(box, mixed_element([vector, element("DG", "tetrahedron", 0)]))


def _mixed(space: fem.FunctionSpace) -> bool:
    return space.dofmap.index_map_bs == 1  # (a blocked vector space's is 3)


def _state(space: fem.FunctionSpace) -> fem.Function:
    """A state far from rest, smooth, the same on any number of ranks."""
    state = fem.Function(space)
    if _mixed(space):
        state.sub(0).interpolate(lambda x: np.vstack([0.1 * x[1] ** 2, -0.2 * x[0] * x[2], 0.05 * np.sin(x[0])]))
        state.sub(1).interpolate(lambda x: 1.0 + x[0] + 0.5 * x[2])
    else:
        state.interpolate(lambda x: np.vstack([0.1 * x[1] ** 2, -0.2 * x[0] * x[2], 0.05 * np.sin(x[0])]))
    return state


def _form_of(space: fem.FunctionSpace, state: fem.Function):
    """a(c; w) for c of shape (2, 3): a load on the boundary and the derivative in the state of
    an energy, both linear in c (and no unit c zeroes a whole integrand); w the test function
    (None: the space's own)."""
    mixed = _mixed(space)
    u, p = ufl.split(state) if mixed else (state, 1.0)
    F = ufl.Identity(3) + ufl.grad(u)
    n = ufl.FacetNormal(space.mesh)

    def form_of(c, test):
        w = ufl.TestFunction(space) if test is None else test
        v = ufl.as_vector([w[i] for i in range(3)]) if mixed else w
        energy = (
            (p * ufl.det(F) * ufl.dot(c[0, :], u) + ufl.dot(c[1, :], ufl.as_vector([1.0, 2.0, 3.0])))
            * ufl.inner(F, F)
            * ufl.dx
        )
        return ufl.dot(c[1, :] - c[0, :], v) * ufl.det(F) * ufl.dot(n, n) * ufl.ds + ufl.derivative(energy, state, w)

    return form_of


def _one_at_a_time(space, form_of, shape) -> np.ndarray:
    work, owned = fem.Function(space).x, owned_size(space)
    columns = []
    for unit in units(shape):
        work.array[:] = 0.0
        fem.assemble_vector(work.array, jit.form(form_of(unit, None)))
        work.scatter_reverse(la.InsertMode.add)
        columns.append(work.array[:owned].copy())
    return np.column_stack(columns)


def _close(found: np.ndarray, expected: np.ndarray) -> None:
    scale = MPI.COMM_WORLD.allreduce(np.abs(expected).max(initial=0.0), op=MPI.MAX)
    assert found.shape == expected.shape and scale > 0
    assert MPI.COMM_WORLD.allreduce(np.abs(found - expected).max(initial=0.0), op=MPI.MAX) <= 1e-13 * scale


@pytest.mark.parametrize("kind", ["vector", "mixed"])
def test_stacked_columns_are_the_columns_one_unit_at_a_time(kind):
    space = _space(kind)
    form_of = _form_of(space, _state(space))
    stack = StackedSpace(space, 6)
    stacked = stack.columns(jit.form(stacked_form(stack, form_of, (2, 3))))
    _close(stacked, _one_at_a_time(space, form_of, (2, 3)))
    if kind == "mixed":  # the cell field's rows: the energy's derivative in p, nonzero
        cell_field = np.asarray(space.sub(1).collapse()[1])
        rows = stacked[cell_field[cell_field < owned_size(space)]]
        assert MPI.COMM_WORLD.allreduce(np.abs(rows).max(initial=0.0), op=MPI.MAX) > 0


@pytest.mark.parametrize("kind", ["vector", "mixed"])
def test_the_whole_mesh_integrations_columns_of_a_form_in_a_constant(kind):
    """FullIntegration: a form in a Constant (its derivative applied before the units replace
    it) and a bilinear form's two sets of columns, as the units set one at a time give them."""
    space = _space(kind)
    state = _state(space)
    form_of = _form_of(space, state)
    whole = FullIntegration(SimpleNamespace(geometry=SimpleNamespace(mesh=space.mesh), space=space))
    c = fem.Constant(space.mesh, np.zeros((2, 3)))
    _close(whole.columns("residual", form_of(c, None), c)(), _one_at_a_time(space, form_of, (2, 3)))

    left, right = fem.Constant(space.mesh, np.array([0.5, -2.0])), fem.Constant(space.mesh, np.array([1.0, 0.25, 3.0]))

    def bilinear(l, r, test=None):  # l ⊗ r as the constant above: linear in each
        return form_of(ufl.outer(l, r), test)

    over_right, over_left = whole.bilinear_columns("response", bilinear, left, right)()
    _close(over_right, _one_at_a_time(space, lambda unit, test: bilinear(left, unit, test), (3,)))
    _close(over_left, _one_at_a_time(space, lambda unit, test: bilinear(unit, right, test), (2,)))


@pytest.mark.mpi
@pytest.mark.parametrize("kind", ["vector", "mixed"])
def test_stacked_columns_on_two_ranks(kind):
    test_stacked_columns_are_the_columns_one_unit_at_a_time(kind)
    test_the_whole_mesh_integrations_columns_of_a_form_in_a_constant(kind)


def test_a_scalar_constant_has_one_unit():
    assert [float(u) for u in units(())] == [1.0]
    assert len(units((12,))) == 12 and units((2, 3))[4].ufl_shape == (2, 3)
