"""Reduced-order models: bases, reduced Galerkin Newton, storage; each against an exact reference."""

from mpi4py import MPI

import numpy as np
import pytest
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix
from fem import write_once

from lungmech import rom
from lungmech.errors import ModelFileError, ParameterError
from lungmech.fem.constraints import clamp
from lungmech.fem.loads import BodyForce, FollowerPressure
from lungmech.fem.materials import LinearElastic, NeoHookean, SaintVenantKirchhoff
from lungmech.fem.modal import modal_analysis
from lungmech.fem.model import Model
from lungmech.fem.solver import NewtonSolver, Stepping, solve
from lungmech.mesh import box
from lungmech.parallel.layout import layout
from lungmech.parallel.linalg import apply, gram
from lungmech.parallel.owned import owned_size
from lungmech.rom.basis import Basis

STEPPING = Stepping(initial_step=0.25, max_step=0.25)
TRAINING = (0.5, 1.0, 1.5)


def beam(comm=MPI.COMM_SELF, law=None, cells=(8, 2, 2), clamped=True) -> Model:
    """A hyperelastic cantilever under its weight and a follower pressure on its top."""
    return Model(
        box(comm, lengths=(5.0, 1.0, 1.0), cells=cells),
        law or NeoHookean.from_young(100.0, 0.3),
        constraints=[clamp("x0")] if clamped else [],
        loads=[BodyForce((0.0, 0.0, -1.0)), FollowerPressure("z1", 0.5)],
    )


def run(model, solver, scale):
    model.reset()
    solve(model, STEPPING, solver=solver, drive=lambda t: model.set_time(t, scale, about=0.0))
    return model.state.x.array.copy()


@pytest.fixture(scope="module")
def trained():
    model = beam()
    data = rom.snapshots(model, STEPPING, TRAINING)
    return model, data


def owned(model) -> int:
    return owned_size(model.space)


@pytest.mark.parametrize("inner", ["l2", "mass", "energy"])
def test_pod_discards_exactly_its_truncated_energy(trained, inner):
    """Σ_j ‖s_j − P_k s_j‖²_W = Σ_{i>k} σ_i² (Eckart–Young in the W inner product)."""
    model, data = trained
    basis = rom.pod(model, data, inner=inner)
    comm = model.geometry.mesh.comm
    W = rom.inner_product(model, inner)
    assert gram(basis.vectors, apply(W, basis.vectors, comm), comm) == pytest.approx(np.eye(basis.size), abs=1e-10)
    total = np.sum(np.array(basis.source["singular_values"]) ** 2)
    for k in (1, 2, basis.size):
        V = basis.vectors[:, :k]
        rest = data - V @ gram(apply(W, V, comm), data, comm)
        discarded = np.trace(gram(rest, apply(W, rest, comm), comm))
        expected = np.sum(np.array(basis.source["singular_values"][k:]) ** 2)
        assert discarded == pytest.approx(expected, rel=1e-6, abs=1e-12 * total)
    # Everything the snapshots hold, to the POD's noise level (1e-7 of the largest singular value).
    assert discarded <= (1e-7 * basis.values[0]) ** 2 * data.shape[1]


def test_truncation(trained):
    model, data = trained
    basis = rom.pod(model, data)
    captured = np.cumsum(basis.values**2) / np.sum(basis.values**2)
    cut = basis.truncate(energy=0.9999)
    assert captured[cut.size - 1] >= 0.9999 and (cut.size == 1 or captured[cut.size - 2] < 0.9999)
    assert np.array_equal(basis.truncate(2).vectors, basis.vectors[:, :2])
    with pytest.raises(ParameterError, match="size must be an integer"):
        basis.truncate(basis.size + 1)
    with pytest.raises(ParameterError, match="either size or energy"):
        basis.truncate()
    with pytest.raises(ParameterError, match="POD"):
        rom.modal_basis(model, 2).truncate(energy=0.9)


def test_complete_basis_gives_the_full_solution():
    """With every free dof in the basis, the reduced problem is the full problem."""
    model = beam(cells=(2, 1, 1))
    full = run(model, NewtonSolver(model), 1.3)
    n = owned(model)
    free = np.ones(n, dtype=bool)
    for bc in model.bcs:
        dofs, _ = bc.dof_indices()
        free[dofs[dofs < n]] = False
    vectors = np.eye(n)[:, free]
    basis = Basis(vectors, np.ones(free.sum()), "identity", "l2", layout(model.space).fingerprint)
    reduced = run(model, rom.ReducedSolver(model, basis), 1.3)
    assert np.abs(reduced - full).max() <= 1e-9 * np.abs(full).max()


def test_reduced_newton_is_quadratic_and_accurate_on_unseen_loads(trained):
    model, data = trained
    basis = rom.pod(model, data, size=6)
    solver = rom.ReducedSolver(model, basis)
    for scale in (0.75, 1.25):  # not in the training set
        full = run(model, NewtonSolver(model), scale)
        reduced = run(model, solver, scale)
        assert np.linalg.norm(reduced - full) <= 1e-4 * np.linalg.norm(full)
    # One step of a tenth of the load: Newton's contraction r_{k+1} ≈ C r_k² until round-off.
    model.reset()
    model.set_time(0.1)
    result = solver.solve()
    residuals = result.residuals
    assert result.converged and residuals[-1] <= 1e-10 * residuals[0], (result.reason, residuals)
    r = np.array(residuals)
    useful = r[1:][r[1:] > 1e-11 * r[0]]
    ratios = np.log(useful[1:] / r[0]) / np.log(useful[:-1] / r[0])
    assert len(ratios) >= 2 and ratios[-1] >= 1.8, r


def test_modal_basis_and_derivatives():
    linear = beam(law=LinearElastic.from_young(100.0, 0.3))
    modes = rom.modal_basis(linear, 3, density=2.0)
    assert modes.values == pytest.approx(modal_analysis(linear, 3, density=2.0).eigenvalues, rel=1e-8)
    W = rom.inner_product(linear, "mass")
    comm = linear.geometry.mesh.comm
    assert gram(modes.vectors, apply(W, modes.vectors, comm), comm) == pytest.approx(np.eye(3), abs=1e-10)
    assert np.abs(rom.modal_derivatives(linear, modes)).max() == 0.0  # a linear law has no third variation
    assert rom.with_modal_derivatives(linear, modes).size == 3

    model = beam(law=SaintVenantKirchhoff.from_young(100.0, 0.3))
    modes = rom.modal_basis(model, 2)
    derivatives = rom.modal_derivatives(model, modes)  # pairs (0,0), (0,1), (1,1)
    # Independent check: K is quadratic in u for this law, so a central difference of K is exact.
    n, eps = owned(model), 1e-2

    def tangent(shift):
        model.state.x.array[:n] = shift
        model.state.x.scatter_forward()
        K = assemble_matrix(fem.form(model.jacobian), bcs=model.bcs, diag=1.0)
        K.assemble()
        return K

    plus, minus = tangent(eps * modes.vectors[:, 1]), tangent(-eps * modes.vectors[:, 1])
    K0 = tangent(0.0)
    dK = plus - minus
    phi, rhs = K0.createVecRight(), K0.createVecLeft()
    phi.array[:] = modes.vectors[:, 0]
    dK.mult(phi, rhs)
    rhs.scale(-1.0 / (2 * eps))
    rom.basis.zero_imposed(model, rhs.array[:, None])
    expected = np.linalg.solve(K0.convert("dense").getDenseArray(), rhs.array)
    assert derivatives[:, 1] == pytest.approx(expected, abs=1e-8 * np.abs(expected).max())
    assert rom.with_modal_derivatives(model, modes).size == 5


def test_polynomial_basis_spans_affine_maps():
    model = beam(clamped=False)
    basis = rom.polynomial_basis(model, 1)
    assert basis.size == 12
    assert rom.polynomial_basis(model, 2).size == 30  # (cubics need more than 3 nodes across: not here)
    affine = fem.Function(model.space)
    affine.interpolate(lambda x: np.array([0.1 * x[0] - 0.3 * x[2] + 1.0, 0.2 * x[1], 0.05 * x[0] + 2.0]))
    x = affine.x.array[: owned(model)]
    comm = model.geometry.mesh.comm
    W = rom.inner_product(model, basis.inner_product)
    rest = x - basis.vectors @ gram(apply(W, basis.vectors, comm), x[:, None], comm)[:, 0]
    assert np.abs(rest).max() <= 1e-10 * np.abs(x).max()
    with pytest.raises(ParameterError, match="order"):
        rom.polynomial_basis(model, 0)


def test_enrichment_spans_its_parts_without_repeats(trained):
    model, data = trained
    pod = rom.pod(model, data, size=3)
    modes = rom.modal_basis(model, 3)
    both = rom.enrich(model, pod, modes)
    assert both.kind == "enriched" and both.size == 6
    assert rom.enrich(model, pod, pod).size == pod.size
    comm = model.geometry.mesh.comm
    W = rom.inner_product(model, "mass")
    for part in (pod, modes):
        rest = part.vectors - both.vectors @ gram(apply(W, both.vectors, comm), part.vectors, comm)
        assert np.abs(rest).max() <= 1e-9 * np.abs(part.vectors).max()


def test_save_load_round_trip_and_mesh_check(trained, tmp_path):
    model, data = trained
    basis = rom.pod(model, data, inner="energy")
    # the beam is each rank's own (COMM_SELF) and tmp_path one folder for all: a file per rank (two
    # ranks saving one path at once found each other's staging folder, a live run's, and stopped)
    own = tmp_path / f"beam-rank{MPI.COMM_WORLD.rank}.npz"
    path = rom.save(own, model, basis, extra={"note": "test"}, arrays={"start": np.arange(3.0)})
    loaded, extra, arrays = rom.load(path, model)
    assert np.array_equal(loaded.vectors, basis.vectors) and np.array_equal(loaded.values, basis.values)
    assert (loaded.kind, loaded.inner_product, loaded.fingerprint) == ("pod", "energy", basis.fingerprint)
    assert (
        loaded.source == basis.source and extra == {"note": "test"} and np.array_equal(arrays["start"], np.arange(3.0))
    )
    with pytest.raises(ModelFileError, match="another mesh"):
        rom.load(path, beam(cells=(8, 2, 1)))
    moved = beam()
    moved.geometry.mesh.geometry.x[:, 0] *= 1.001  # same topology, other nodes
    with pytest.raises(ModelFileError, match="another mesh"):
        rom.load(path, moved)
    with pytest.raises(ParameterError, match="another mesh"):
        rom.ReducedSolver(moved, basis)
    write_once(tmp_path / "junk.npz", b"not a model")
    with pytest.raises(ModelFileError, match="not a lungmech reduced model"):
        rom.load(tmp_path / "junk.npz", model)
    with pytest.raises(ModelFileError, match="not found"):
        rom.load(tmp_path / "missing.npz", model)
    with pytest.raises(ParameterError, match=".npz"):
        rom.save(tmp_path / "beam.h5", model, basis)
