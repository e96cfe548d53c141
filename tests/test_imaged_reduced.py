"""A reduced model of an imaged body at every μ against the full model of the same problem.

The full model (:class:`lungmech.fem.inverse_motion.InverseMotion`) finds the unloaded
reference ξ(μ) on the fixed imaged mesh, then the breath from the image. The reduced model
(:mod:`lungmech.rom.imaged`) reduces both unknowns, each on its POD basis, and is judged at
parameter points it was not trained on: it starts on the image exactly, and its reference
volume, breath and energies are the full model's to a small fraction of their changes.
"""

from mpi4py import MPI

import numpy as np
import pytest
from test_inverse_motion import inflated_block

from lungmech.errors import ParameterError
from lungmech.fem.inverse_motion import InverseMotion
from lungmech.fem.parametric import FullOrderModel
from lungmech.fem.placement import Image
from lungmech.fem.quantities import Probe, deformed_volume
from lungmech.fem.solver import Stepping
from lungmech.rom import body
from lungmech.rom.imaged import ReducedImage
from lungmech.rom.indicator import enrichment
from lungmech.rom.reduced import ReducedModel
from lungmech.rom.reductor import ECSW, POD, Reductor, TrainingSet, errors
from lungmech.rom.store import load_body, load_reduced, write_reduced

STEPPING = Stepping(start=0.5, end=1.0, max_step=0.25)


def imaged_block(plane: bool = False) -> FullOrderModel:
    """The neo-Hookean block imaged half-way through its loading, on its fixed mesh."""
    model = inflated_block(Image.motion(STEPPING.start), plane)
    probe = [0.9, 0.25, 0.25][: 2 if plane else 3]
    return FullOrderModel(model, STEPPING, probes=[probe], start=InverseMotion(model))


TAU = 1e-5  # the hyper-reduced model's ECSW tolerance
# (reference volume, relative; breath volume, of the path's volume change; energy, of its
# largest; probe, of the block's size): the Galerkin model's and the hyper-reduced one's
BOUNDS = {"galerkin": (1e-7, 1e-6, 1e-6, 1e-7), "hyper": (1e-7, 5e-5, 2e-4, 1e-6)}


@pytest.fixture(scope="module", params=[False, True], ids=["3-D", "plane strain"])
def built(request):
    full = imaged_block(request.param)
    training = full.parameters.sample(8, seed=1)
    with Reductor(full, POD(10), TrainingSet(training)) as reductor:
        yield full, reductor, {"galerkin": reductor.reduce(), "hyper": reductor.reduce(ECSW(TAU))}


@pytest.mark.parametrize("kind", ["galerkin", "hyper"])
def test_unseen_points_answer_the_full_problem(built, kind):
    """At points of the box it was not trained on (and two corners), both reduced models start
    on the image (its volume to round-off) from their reference at μ, and their reference
    volumes, breaths, energies and probes are the full model's to the bounds."""
    full, _, models = built
    reduced, (reference_bound, volume_bound, energy_bound, probe_bound) = models[kind], BOUNDS[kind]
    box = full.parameters
    unseen = [*box.sample(4, seed=11), box.from_unit(np.zeros(2)), box.from_unit(np.ones(2))]
    for mu in unseen:
        a, b = full.solve(mu), reduced.solve(mu)
        assert b.start.kind == "imaged"
        assert b.start.details["volume"] == pytest.approx(b.start.details["imaged_volume"], rel=1e-12)
        reference = a.start.details["reference_volume"]
        assert b.start.details["reference_volume"] == pytest.approx(reference, rel=reference_bound)
        change = np.ptp(np.concatenate([[reference], a.outputs["volume"]]))
        assert np.abs(b.outputs["volume"] - a.outputs["volume"]).max() <= volume_bound * change
        energy = np.abs(a.outputs["strain_energy"]).max()
        assert np.abs(b.outputs["strain_energy"] - a.outputs["strain_energy"]).max() <= energy_bound * energy
        assert np.abs(b.outputs["probes"] - a.outputs["probes"]).max() <= probe_bound


def test_an_earlier_answer_is_rebuilt_on_its_own_reference(built):
    """A reduced answer made whole after other solves — its state, its errors — is on the
    reference of its own μ, not the last solve's; a training point's answer is a reduced
    Newton's too, as its neighbours' are."""
    full, reductor, models = built
    reduced = models["galerkin"]
    first, second = {"E": 6.5, "p": 1.3}, {"E": 17.0, "p": 0.6}
    answer = reduced.solve(first)
    reduced.solve(second)
    reduced.reconstruct(answer, len(answer.times) - 1)
    model = reduced.model
    assert deformed_volume(model)() == pytest.approx(answer.outputs["volume"][-1], rel=1e-12)
    u = Probe(model.geometry.mesh, reduced.outputs.probe_points)(model.displacement())  # w − ξ: its own ξ
    assert np.allclose(u, answer.outputs["probes"][-1], rtol=1e-10, atol=1e-14)
    found = errors(reduced, full.solve(first), answer)
    assert found.energy < 1e-4 and found.volume_change < 1e-5
    trained = reductor.points[0]
    assert models["hyper"].solve(trained, times=[STEPPING.start]).start.newton_iterations >= 1


def test_the_reduced_inverse_tangent_is_not_symmetric(built):
    """V_ξᵀ K_ξ V_ξ, the reduced inverse tangent, keeps the full one's asymmetry (it is solved
    by LU), while the breath's reduced tangent under dead loads would be symmetric."""
    full, reductor, models = built
    for reduced in models.values():
        reduced.solve({"E": 7.0})
        tangent = reduced.image.solver.reduced_jacobian()
        asymmetry = np.linalg.norm(tangent - tangent.T) / np.linalg.norm(tangent)
        assert asymmetry > 1e-4
    assert reductor.inverse_basis.size >= 2


def test_a_model_file_answers_as_the_model_it_was_written_from(built, tmp_path_factory):
    """Written and loaded again — on the full mesh, or on its body of sampled cells alone — the
    hyper-reduced imaged model gives the answers it gave before writing, to round-off."""
    full, _, models = built
    plane = full.model.geometry.mesh.geometry.dim == 2
    folder = tmp_path_factory.mktemp(f"imaged-rank{MPI.COMM_WORLD.rank}")  # one path for all ranks
    path = MPI.COMM_WORLD.bcast(str(folder / "imaged.npz"))
    write_reduced(path, models["hyper"])
    mesh_model = inflated_block(Image.motion(STEPPING.start), plane)
    probe = [0.9, 0.25, 0.25][: 2 if plane else 3]
    on_mesh = load_reduced(path, mesh_model, STEPPING, probes=[probe])
    on_body = load_body(
        path, lambda geometry: inflated_block(Image.motion(STEPPING.start), plane, geometry=geometry), STEPPING
    )
    # the body holds both samples; each solver works on its own sample's cells alone (a
    # submesh), the inverse motion's not on the breath's cells too
    for solver in (on_body.solver, on_body.image.solver):
        cells = solver.mesh.mesh.topology.index_map(solver.mesh.mesh.topology.dim).size_local
        assert cells == len(body.cells_of(solver.sample))
    for mu in ({"E": 6.5, "p": 1.2}, {"E": 17.0, "p": 0.7}):
        expected = models["hyper"].solve(mu)
        for loaded in (on_mesh, on_body):
            answer = loaded.solve(mu)
            assert answer.start.details["reference_volume"] == pytest.approx(
                expected.start.details["reference_volume"], rel=1e-12
            )
            for name in ("volume", "strain_energy", "probes"):
                assert np.allclose(answer.outputs[name], expected.outputs[name], rtol=1e-9, atol=1e-14), name


def test_a_training_that_cannot_make_an_imaged_model_is_refused_in_one_line():
    with pytest.raises(ParameterError, match="every training point has the unloaded reference of the defaults"):
        Reductor(imaged_block(), POD(4), TrainingSet([{}]))
    with pytest.raises(ParameterError, match="POD bases of given size"):
        Reductor(imaged_block(), POD(4), TrainingSet([{}], tolerance=1e-3))


def test_the_indicator_sees_an_error_of_the_reference(built):
    """On an inverse basis of one vector, the reference at μ is off, and the breath from the
    image with it: the answers' online indicator (the Newton correction in [V W], where at the
    start — the image at the reduced reference, not solved for — it is the breath's release from
    the image) reads the true energy-norm error within 3× either way. The breath's own W part
    alone would read it as about the training's error, orders of magnitude below."""
    full, reductor, _ = built
    model = full.model
    coarse = reductor.inverse_basis.truncate(1)
    known = [(point, a[:1]) for point, a in reductor.inverse_known]
    image = ReducedImage(model, coarse, reductor.inverse_start, full.solver.options, sample=None, known=known)
    basis = reductor.modes.truncate(reductor.modes.size - 2)  # so that two POD directions enrich it
    reduced = ReducedModel(
        model, basis, full.stepping, full.solver.options, reductor.start, full.outputs.probe or (),
        enrichment=enrichment(basis, reductor.modes), image=image,
    )  # fmt: skip
    box = full.parameters
    for mu in [*box.sample(2, seed=11), box.from_unit(np.ones(2))]:
        answer = reduced.solve(mu)
        error = errors(reduced, full.solve(mu), answer).energy
        assert error > 1e-4  # the reference's error, not the breath's (≤ 1e-6 on the whole inverse basis)
        assert error / 3 <= answer.indicator <= 3 * error, (mu, answer.indicator, error)


def test_the_sampled_inverse_tangent_keeps_the_spectrum_at_the_training_points(built):
    """At every training point's reduced reference, the hyper-reduced inverse tangent's
    eigenvalues against the Galerkin one's (at the same a) lie within 10 % of 1 (1.5 % when
    written), and both tangents' eigenvalues keep one sign of their real parts: the sample
    trained on residual and tangent rows reproduces the non-symmetric tangent, not its forces
    alone."""
    full, reductor, models = built
    hyper, galerkin = models["hyper"].image, models["galerkin"].image
    for point in reductor.points:
        models["hyper"].solve(point, times=[STEPPING.start])
        sampled = hyper.solver.reduced_jacobian()
        galerkin.inverse.set_parameters(full.parameters.values(point))
        galerkin.inverse.set_time(STEPPING.start)
        galerkin.solver.reconstruct(hyper.solver.state.copy())
        exact = galerkin.solver.reduced_jacobian()
        relative = np.linalg.eigvals(np.linalg.solve(exact, sampled))
        assert np.abs(relative - 1).max() <= 0.1, relative
        for tangent in (exact, sampled):
            signs = np.sign(np.linalg.eigvals(tangent).real)
            assert np.all(signs == signs[0])


def test_the_online_newton_converges_from_the_defaults_reference(built):
    """Without the training points' coordinates, every reduced inverse solve starts from the
    defaults' reference (a = 0): reduced Newton converges at every unseen point and corner, to
    the answer it gives from the nearest training point."""
    full, reductor, models = built
    reduced = models["hyper"]
    image = reduced.image
    alone = ReducedImage(
        full.model, image.basis, image.start, full.solver.options, sample=image.solver.sample, known=()
    )
    box = full.parameters
    corners = [box.from_unit(np.array(c, dtype=float)) for c in ((0, 0), (0, 1), (1, 0), (1, 1))]
    for mu in [*box.sample(4, seed=11), *corners]:
        near = reduced.solve(mu, times=[STEPPING.start]).start.details["reference_volume"]
        alone.place(full.model, reduced.solver, full.parameters.values(mu), STEPPING.start)
        assert alone.reference_volume() == pytest.approx(near, rel=1e-10)
    reduced.restart()  # its own reference again (alone's placed the model's ξ)
