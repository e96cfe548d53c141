"""A reduced model of an imaged body at every μ against the full model of the same problem.

The full model (:class:`lungmech.fem.inverse_motion.InverseMotion`) finds the unloaded
reference ξ(μ) on the fixed imaged mesh, then the breath from the image. The reduced model
(:mod:`lungmech.rom.imaged`) reduces both unknowns, each on its POD basis, and is judged at
parameter points it was not trained on: it starts on the image exactly, and its reference
volume, breath and energies are the full model's to a small fraction of their changes.
"""

import numpy as np
import pytest
from test_inverse_motion import inflated_block

from lungmech.errors import ParameterError
from lungmech.fem.inverse_motion import InverseMotion
from lungmech.fem.parametric import FullOrderModel
from lungmech.fem.placement import Image
from lungmech.fem.solver import Stepping
from lungmech.rom.reductor import ECSW, POD, Reductor, TrainingSet

STEPPING = Stepping(start=0.5, end=1.0, max_step=0.25)


def imaged_block(plane: bool = False) -> FullOrderModel:
    """The neo-Hookean block imaged half-way through its loading, on its fixed mesh."""
    model = inflated_block(Image.motion(STEPPING.start), plane)
    probe = [0.9, 0.25, 0.25][: 2 if plane else 3]
    return FullOrderModel(model, STEPPING, probes=[probe], start=InverseMotion(model))


@pytest.fixture(scope="module", params=[False, True], ids=["3-D", "plane strain"])
def built(request):
    full = imaged_block(request.param)
    training = full.parameters.sample(8, seed=1)
    with Reductor(full, POD(10), TrainingSet(training)) as reductor:
        yield full, reductor, reductor.reduce()


def test_unseen_points_answer_the_full_problem(built):
    """At points of the box it was not trained on (and two corners): the reference volume to
    1e-7, the breath's volumes to 1e-5 of the path's volume change, the energies to 1e-5 of
    their largest and the probe to 1e-6 of the block's size; the start is the image."""
    full, _, reduced = built
    box = full.parameters
    unseen = [*box.sample(4, seed=11), box.from_unit(np.zeros(2)), box.from_unit(np.ones(2))]
    for mu in unseen:
        a, b = full.solve(mu), reduced.solve(mu)
        assert b.start.kind == "imaged"
        assert b.start.details["volume"] == pytest.approx(b.start.details["imaged_volume"], rel=1e-12)
        reference = a.start.details["reference_volume"]
        assert b.start.details["reference_volume"] == pytest.approx(reference, rel=1e-7)
        change = np.ptp(np.concatenate([[reference], a.outputs["volume"]]))
        assert np.abs(b.outputs["volume"] - a.outputs["volume"]).max() <= 1e-5 * change
        energy = np.abs(a.outputs["strain_energy"]).max()
        assert np.abs(b.outputs["strain_energy"] - a.outputs["strain_energy"]).max() <= 1e-5 * energy
        assert np.abs(b.outputs["probes"] - a.outputs["probes"]).max() <= 1e-6


def test_the_reduced_inverse_tangent_is_not_symmetric(built):
    """V_ξᵀ K_ξ V_ξ, the reduced inverse tangent, keeps the full one's asymmetry (it is solved
    by LU), while the breath's reduced tangent under dead loads would be symmetric."""
    full, reductor, reduced = built
    reduced.solve({"E": 7.0})
    tangent = reduced.image.solver.reduced_jacobian()
    asymmetry = np.linalg.norm(tangent - tangent.T) / np.linalg.norm(tangent)
    assert asymmetry > 1e-4
    assert reductor.inverse_basis.size >= 2


def test_what_is_not_built_yet_is_refused_in_one_line(built):
    _, reductor, reduced = built
    with pytest.raises(ParameterError, match="hyper-reduced model of an imaged body is not built yet"):
        reductor.reduce(ECSW(1e-4))
    with pytest.raises(ParameterError, match="sensitivities of an imaged body"):
        reduced.solve({}, sensitivities=True)
    with pytest.raises(ParameterError, match="POD bases of given size"):
        Reductor(imaged_block(), POD(4), TrainingSet([{}], tolerance=1e-3))
