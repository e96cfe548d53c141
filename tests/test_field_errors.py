"""A trade's energy-norm errors (lungmech.app.field_errors): a field carried between non-matching
meshes and elements is exact for what both spaces hold (a quadratic onto P2, its nodal values
onto P1, a Taylor–Hood state's displacement alone); the energy norm at rest is the linear
elastic energy of the difference (an analytic value); a mesh that does not cover the
reference is refused; on a small scene the trade's energy errors shrink under refinement
at the order of P1 elements; and a full solve keeps its fields in the cache when asked."""

from dataclasses import replace

from mpi4py import MPI

import numpy as np
import pytest
from dolfinx import fem
from trades import written

from lungmech.app import answers, trade_report
from lungmech.app import scene as scenes
from lungmech.app.answers import Task
from lungmech.app.cache import Cache
from lungmech.app.field_errors import Transfer, Transfers, energy_norm_allowed
from lungmech.app.ladder import Discretisation
from lungmech.app.run import full_order_model
from lungmech.app.trade import Candidate, Family, trade
from lungmech.errors import LungmechError, ParameterError
from lungmech.fem.constraints import clamp
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.mesh import box, sphere
from lungmech.parallel.layout import layout
from lungmech.parallel.linalg import norms
from lungmech.parallel.owned import owned_size
from lungmech.rom.basis import inner_product

E, NU = 1.0e3, 0.3
LAME, SHEAR = E * NU / ((1 + NU) * (1 - 2 * NU)), E / (2 * (1 + NU))


def model(cells, degree=1, mixed=False, lengths=(1.0, 1.0, 1.0), constraints=()):
    geometry = box(MPI.COMM_WORLD, lengths, cells)
    return Model(geometry, NeoHookean.from_young(E, NU), degree=degree, mixed=mixed, constraints=constraints)


def quadratic(x):
    return np.vstack([x[0] ** 2, x[0] * x[1] - x[2], 0.5 * x[2] ** 2 + x[1]])


def interpolant(target: Model, field) -> np.ndarray:
    """The owned entries of ``target``'s state holding ``field`` in its displacement, 0 elsewhere."""
    state = fem.Function(target.space)
    if target.multi_field:
        space, dofs = target.space.sub(0).collapse()
        part = fem.Function(space)
        part.interpolate(field)
        state.x.array[np.asarray(dofs)] = part.x.array
    else:
        state.interpolate(field)
    return state.x.array[: owned_size(target.space)].copy()


@pytest.mark.parametrize(
    "source, target",
    [
        (((2, 2, 2), 2, False), ((3, 3, 3), 2)),  # non-nested P2 meshes: the quadratic exactly
        (((2, 2, 2), 2, False), ((3, 2, 4), 1)),  # onto P1: its nodal values
        (((2, 2, 2), 2, True), ((3, 3, 3), 2)),  # a Taylor–Hood state's displacement, its pressure left
    ],
)
def test_a_field_carried_between_non_matching_meshes_is_exact_where_both_hold_it(source, target):
    (cells, degree, mixed), (target_cells, target_degree) = source, target
    giver, taker = model(cells, degree, mixed), model(target_cells, target_degree)
    carried = Transfer(giver, taker)(interpolant(giver, quadratic))
    assert np.allclose(carried, interpolant(taker, quadratic), rtol=0.0, atol=1e-12)


def test_a_coarser_remesh_of_a_curved_body_reaches_the_finer_ones_boundary():
    """The finer sphere's boundary nodes lie outside the coarser's chords: they take the
    nearest cell's values, which for a linear field are its own."""
    A = np.array([[1.0, 2.0, 0.0], [0.0, -0.5, 1.0], [3.0, 0.0, 0.25]])
    coarse, fine = (Model(sphere(MPI.COMM_WORLD, 0.5, 1.0, size), NeoHookean.from_young(E, NU)) for size in (0.5, 0.2))
    carried = Transfer(coarse, fine)(interpolant(coarse, lambda x: A @ x))
    assert np.allclose(carried, interpolant(fine, lambda x: A @ x), rtol=0.0, atol=1e-12)


def test_a_source_numbered_as_one_before_takes_its_transfer():
    """Onto one target: a second model of the same mesh and element (built again) takes the
    first one's transfer, and carries its own state as a transfer of its own would; another
    element or another mesh gets a transfer of its own (on two ranks too: tests/test_mpi.py)."""
    onto = Transfers(model((3, 3, 3), degree=2))
    first, again = model((2, 2, 2)), model((2, 2, 2))
    assert onto(again) is onto(first)
    state = interpolant(again, quadratic)
    assert np.array_equal(onto(again)(state), Transfer(again, onto.target)(state))
    assert onto(model((2, 2, 2), degree=2)) is not onto(first)
    assert onto(model((2, 2, 3))) is not onto(first)


def test_the_energy_norm_at_rest_is_the_linear_elastic_energy():
    """‖e‖²_E = ∫ λ (tr ε)² + 2μ ε:ε for e = A x on a 2 × 1 × 1 box: V (λ (tr ε)² + 2μ ε:ε)."""
    taker = model((4, 2, 2), lengths=(2.0, 1.0, 1.0))
    A = np.array([[1.0, 2.0, 0.0], [0.0, -0.5, 1.0], [3.0, 0.0, 0.25]]) * 1e-2
    strain = 0.5 * (A + A.T)
    expected = 2.0 * (LAME * np.trace(strain) ** 2 + 2 * SHEAR * np.sum(strain * strain))
    e = interpolant(taker, lambda x: A @ x)
    W = inner_product(taker, "energy")
    assert norms(e[:, None], W, MPI.COMM_WORLD)[0] ** 2 == pytest.approx(expected, rel=1e-10)
    W.destroy()


def test_a_mesh_that_does_not_cover_the_reference_is_refused():
    with pytest.raises(LungmechError, match="outside the candidate's mesh"):
        Transfer(model((2, 2, 2), lengths=(0.5, 1.0, 1.0)), model((3, 3, 3)))


def test_an_energy_that_is_no_norm_is_refused_in_one_line():
    with pytest.raises(ParameterError, match="--quantity energy") as raised:
        energy_norm_allowed(model((2, 2, 2)))  # nothing holds it: free to move rigidly
    assert "\n" not in str(raised.value)
    with pytest.raises(ParameterError, match="--quantity energy"):  # a mixed formulation's saddle point
        energy_norm_allowed(model((2, 2, 2), degree=2, mixed=True, constraints=[clamp("x0")]))
    energy_norm_allowed(model((2, 2, 2), constraints=[clamp("x0")]))


@pytest.mark.slow
def test_a_trades_energy_errors_shrink_at_the_order_of_its_elements(tmp_path):
    """P1 at h and h/2 against h/4: the errors fall by about 2 per halving, the reference's is
    0, and the observed order agrees with 1 (on two ranks: tests/test_trade_cli.py); P2 on h
    is noted as of a higher degree than the reference; the table carries the energy columns. A
    Galerkin model's error of reduction (one POD, its leading 2 and 3 vectors), against P1 h in
    that mesh's energy norm, lies within the triangle its error and P1 h's against the reference
    make (their denominators within 10 %)."""
    scene = written(tmp_path, mesh_size=0.6, pressure=0.1)  # (nearly linear: fewer Newton iterations)
    full = [Candidate.full(Discretisation(level, 1)) for level in (0, 1)] + [Candidate.full(Discretisation(0, 2))]
    galerkin = Family(taus=(), sizes=(2, 3), samples=2)  # Galerkin alone, at two basis sizes
    found = trade(scene, 0.5, quantity="energy", count=1, full=full, build=galerkin, cache=tmp_path / "cache")
    assert found.own == "full P1 h" and set(found.reduction) == {"POD Galerkin k=2", "POD Galerkin k=3"}
    mesh = found.errors["full P1 h"]["energy"]
    for k in (2, 3):
        name = f"POD Galerkin k={k}"
        alone, total = found.reduction[name]["energy"], found.errors[name]["energy"]
        assert found.results[name]["basis_size"] == k and np.all(alone > 0)
        assert np.all(alone <= 1.1 * (total + mesh)) and np.all(alone >= np.abs(total - mesh) / 1.1)
    h, half = (found.errors[f"full P1 {name}"]["energy"] for name in ("h", "h/2"))
    assert np.all(np.isfinite(h)) and np.all(h > half) and np.all(half > 0)
    assert np.all((h / half > 1.5) & (h / half < 3.0))
    assert np.all(found.errors[found.reference]["energy"] == 0.0)
    order = found.convergence["energy"]
    assert order.expected == 1.0 and abs(order.observed - 1.0) < 0.5
    assert found.choice is not None
    assert "full P2 h: of a higher degree than the reference (P1 h/4)" in " ".join(found.notes)
    if MPI.COMM_WORLD.rank == 0:
        (tmp_path / "out").mkdir()
        trade_report.write(found, tmp_path / "out")
        assert "energy-norm error max [-]" in (tmp_path / "out" / "trade.csv").read_text()


def test_an_answer_kept_without_its_fields_is_solved_again_for_them(tmp_path):
    """A task asking for fields finds an answer kept without them: it is solved again, and then
    serves both kinds of task; the fields kept are the model's start and last states in the
    canonical order (any number of ranks)."""
    path = written(tmp_path)
    cache, comm = str(tmp_path / "cache"), MPI.COMM_WORLD
    plain = Task(str(path), {"stiffness": 8.0}, Discretisation(0, 1), (1.0,))
    wanted = replace(plain, fields=True)
    kept = [answers.solved(task, comm, cache)["kept"] for task in (plain, wanted, plain, wanted)]
    answers.forget()
    assert kept == [False, False, True, True]
    scene = scenes.load(path)
    fields = Cache(cache, comm).read_arrays("fields", answers.entry(scene, wanted))
    full = full_order_model(scene, comm, start="inverse_motion")
    solution = full.solve({"stiffness": 8.0}, times=[1.0])
    where = layout(full.model.space)
    end, start = where.gather(solution.states[-1]), where.gather(np.zeros_like(solution.states[-1]))
    if comm.rank == 0:
        assert fields is not None and str(fields["fingerprint"]) == where.fingerprint
        assert np.array_equal(fields["end"], end) and np.array_equal(fields["start"], start)
        assert np.abs(end).max() > 0
