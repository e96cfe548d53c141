"""The one reductor: every recipe gives a ReducedModel that answers solve(μ), orthonormal in its
inner product, and survives the model file (rom.store.write_reduced / load_reduced) unchanged."""

from mpi4py import MPI

import numpy as np
import pytest
from fem import BOX, pushed_block

from lungmech.errors import ParameterError
from lungmech.fem.parameters import Parameters
from lungmech.parallel.linalg import apply, gram
from lungmech.rom import store
from lungmech.rom.basis import inner_product
from lungmech.rom.reductor import ECSW, POD, Enriched, Modal, Polynomial, Reductor, TrainingSet, errors, reduce

POINTS = Parameters(BOX).sample(4, seed=3)
MU = {"E": 12.0, "nu": 0.35, "p": 0.8}


@pytest.fixture(scope="module")
def full():
    return pushed_block()


def orthonormality(reduced) -> float:
    model, V = reduced.model, reduced.basis.vectors
    W = inner_product(model, reduced.basis.inner_product)
    G = gram(V, apply(W, V, model.geometry.mesh.comm), model.geometry.mesh.comm)
    if W is not None:
        W.destroy()
    return float(np.abs(G - np.eye(V.shape[1])).max())


@pytest.mark.parametrize(
    ("recipe", "kind", "inner"),
    [
        (POD(6), "pod", "energy"),
        (POD(6), "pod", "mass"),
        (Modal(5), "modal", "mass"),  # a modal basis is M-orthonormal whatever is asked
        (Polynomial(1, size=8), "polynomial", "energy"),
        (Enriched((POD(4), Modal(3)), size=6), "enriched", "energy"),
    ],
)
def test_every_recipe_gives_a_model_that_answers(full, recipe, kind, inner):
    reduced = reduce(full, recipe, TrainingSet(POINTS), inner=inner)
    assert reduced.basis.kind == kind and reduced.size <= getattr(recipe, "size", 99)
    assert orthonormality(reduced) < 1e-10
    answer = reduced.solve(MU)
    assert answer.times.tolist() == full.times.tolist() and np.all(np.isfinite(answer.outputs["volume"]))
    assert reduced.built["basis"] == kind and reduced.built["training"] == POINTS


def test_pod_training_scales_and_points_make_the_error_small(full):
    """More training, smaller error (the POD of the paths at the points × scales)."""
    poor = reduce(full, POD(2), TrainingSet(POINTS[:1]))
    rich = reduce(full, POD(10), TrainingSet(POINTS, scales=(0.5, 1.0)))
    reference = full.solve(MU)
    assert errors(rich, reference, rich.solve(MU)).energy < errors(poor, reference, poor.solve(MU)).energy / 10


def test_a_galerkin_model_of_the_leading_vectors_is_the_smaller_pods(full):
    """reduce(size=k) of a POD of 8: the model a POD of k gives (a POD is nested), its answers
    and its indicator too (the enrichment made for its own k vectors, not the 8's)."""
    with Reductor(full, POD(8), TrainingSet(POINTS)) as larger, Reductor(full, POD(3), TrainingSet(POINTS)) as small:
        cut, own = larger.reduce(size=3), small.reduce()
        assert larger.reduce(size=99).size == larger.basis.size  # no more vectors than the basis has
        with pytest.raises(ParameterError, match="basis size must be a positive integer"):
            larger.reduce(size=0)
    assert cut.size == own.size == 3
    signs = np.sign(np.sum(cut.basis.vectors * own.basis.vectors, axis=0))  # a POD vector's sign is free
    np.testing.assert_allclose(cut.basis.vectors * signs, own.basis.vectors, atol=1e-9)
    a, b = cut.solve(MU), own.solve(MU)
    np.testing.assert_allclose(a.outputs["volume"], b.outputs["volume"], rtol=1e-10)
    assert a.indicator is not None and a.indicator == pytest.approx(b.indicator, rel=1e-6)


@pytest.mark.slow
def test_a_hyper_reduced_model_truncated_after_sampling(full):
    """ECSW(τ, size=k): the sample of the whole basis, the basis cut to its first k vectors."""
    whole = reduce(full, POD(8), TrainingSet(POINTS), ECSW(1e-5))
    cut = reduce(full, POD(8), TrainingSet(POINTS), ECSW(1e-5, size=4))
    assert cut.size == 4 and whole.sample is not None and cut.sample is not None
    np.testing.assert_allclose(cut.basis.vectors, whole.basis.vectors[:, :4], atol=1e-12)
    for family, cells in whole.sample.cells.items():
        np.testing.assert_array_equal(cut.sample.cells[family], cells)
    reference = full.solve(MU)
    assert errors(whole, reference, whole.solve(MU)).energy < 1e-2
    assert cut.solve(MU).indicator is not None  # its enrichment: the POD directions after the 4


def test_the_projection_error_is_the_best_the_basis_can_do(full):
    """errors().projection against an independent least-squares fit in the energy norm (dense E,
    its Cholesky factor): min over c of ‖L(d − V c)‖₂ at every output time; a Galerkin answer
    is no better than it, and a mass-orthonormal basis projects in the energy norm all the same."""
    from lungmech.rom.basis import origin

    for inner in ("energy", "mass"):
        reduced = reduce(full, POD(2), TrainingSet(POINTS), inner=inner)
        reference = full.solve(MU)
        found = errors(reduced, reference, reduced.solve(MU))
        W = inner_product(full.model, "energy")
        L = np.linalg.cholesky(W.convert("dense").getDenseArray())
        W.destroy()
        V = reduced.basis.vectors
        best, change = 0.0, 0.0
        for index in range(len(reference.times)):
            full.model.set_time(float(reference.times[index]))
            d = reference.states[index] - origin(full.model, reduced.start)[: V.shape[0]]
            c = np.linalg.lstsq(L.T @ V, L.T @ d, rcond=None)[0]
            best, change = max(best, np.linalg.norm(L.T @ (d - V @ c))), max(change, np.linalg.norm(L.T @ d))
        assert found.projection == pytest.approx(best / change, rel=1e-6)
        assert 0 < found.projection <= found.energy * (1 + 1e-6)


class Counted:
    """``full`` with its solves counted (a reductor's models must not solve it again)."""

    def __init__(self, full):
        self.full, self.solves = full, 0

    def __getattr__(self, name):
        return getattr(self.full, name)

    def solve(self, *args, **kwargs):
        self.solves += 1
        return self.full.solve(*args, **kwargs)


@pytest.mark.slow
@pytest.mark.parametrize("greedy", [False, True], ids=["training set", "greedy"])
def test_one_reductor_gives_models_at_every_tau_and_size_from_one_training(full, greedy):
    """Several τ, a truncation and the Galerkin model from one Reductor: no full solve after its
    training (a greedy's iterates are replayed; a training set's solves watched once more), and
    each model is the one :func:`reduce` builds alone at its τ. A greedy judging at 1e-5 and
    sampled at 1e-3 too: a coarser sample, still accurate."""
    counted = Counted(full)
    training = TrainingSet(POINTS, tolerance=1e-3) if greedy else TrainingSet(POINTS)
    with Reductor(counted, POD(8), training, judge=1e-5 if greedy else None) as reductor:
        trained = counted.solves
        galerkin = reductor.reduce()
        fine, coarse = reductor.reduce(ECSW(1e-5)), reductor.reduce(ECSW(1e-3))
        cut = reductor.reduce(ECSW(1e-5, size=2))
        replayed = counted.solves - trained
    assert trained >= len(reductor.points) and replayed == (0 if greedy else len(POINTS))
    assert galerkin.sample is None and galerkin.built["hyper"] is None
    if greedy:
        assert fine.sample is reductor.trained.sample and fine.built["timings"]["nnls"] == 0.0
    assert cut.size == 2 and cut.sample is fine.sample
    assert sum(map(len, coarse.sample.cells.values())) < sum(map(len, fine.sample.cells.values()))
    assert coarse.built["hyper"] == {"method": "ecsw", "tolerance": 1e-3, "judge": 1e-5 if greedy else 1e-3}
    alone = reduce(full, POD(8), training, ECSW(1e-3, judge=1e-5 if greedy else None))
    for family, cells in alone.sample.cells.items():
        np.testing.assert_array_equal(coarse.sample.cells[family], cells)
    if greedy:  # a greedy kept from before is a basis the reductor takes as it is
        with Reductor(counted, reductor.trained) as again:
            kept = again.reduce(ECSW(1e-3))
        assert counted.solves - trained == 0 and again.judge == 1e-5
        assert kept.built == coarse.built | {"timings": kept.built["timings"]}
        for family, cells in coarse.sample.cells.items():
            np.testing.assert_array_equal(kept.sample.cells[family], cells)
    reference = full.solve(MU)
    for reduced, most in ((galerkin, 1e-2), (fine, 1e-2), (coarse, 5e-2)):
        assert errors(reduced, reference, reduced.solve(MU)).energy < most


@pytest.mark.slow
def test_a_reduced_model_survives_its_file(full, tmp_path):
    """write_reduced then load_reduced on the same mesh: the same answers, start and record."""
    reduced = reduce(full, POD(6), TrainingSet(POINTS), ECSW(1e-4))
    path = MPI.COMM_WORLD.bcast(tmp_path) / "m.npz"
    store.write_reduced(path, reduced)
    loaded = store.load_reduced(path, full.model, full.stepping)
    a, b = reduced.solve(MU), loaded.solve(MU)
    np.testing.assert_allclose(b.outputs["volume"], a.outputs["volume"], rtol=1e-12)
    assert b.indicator == pytest.approx(a.indicator, rel=1e-10)
    assert loaded.described == reduced.described and loaded.built["hyper"]["tolerance"] == 1e-4


def test_bad_recipes_are_refused_in_one_line(full):
    for make, said in (
        (lambda: POD(0), "basis size must be a positive integer"),
        (lambda: ECSW(2.0), "the ECSW tolerance must lie in (0, 1)"),
        (lambda: TrainingSet([]), "give at least one training parameter point"),
        (lambda: TrainingSet(POINTS, scales=(0.5,), tolerance=1e-3), "put a load's amplitude in [parameters]"),
        (lambda: reduce(full, Modal(3), TrainingSet(POINTS, tolerance=1e-3)), "trains a POD basis"),
        (lambda: reduce(full, POD(3), TrainingSet(POINTS), inner="h1"), "inner product must be one of"),
        (lambda: Reductor(full, POD(3), TrainingSet(POINTS), judge=0.0), "the ECSW tolerance must lie in (0, 1)"),
    ):
        with pytest.raises(ParameterError, match=said.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")):
            make()
