"""The imaged body on its fixed mesh (inverse motion) against the fixed point on a moving mesh.

Two independent ways to the same problem — the mesh is the loaded state at t₀ for every μ:
:class:`lungmech.lung.inverse.Imaged` moves the mesh to the unloaded reference by a fixed point
of direct solves; :class:`lungmech.fem.inverse_motion.InverseMotion` keeps the mesh and solves
the image's equilibrium for the inverse map, then the breath for the motion from the image.
Their references and breaths agree to the solvers' tolerances, on 1 rank and on 2.
"""

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
from fem import bundled_lung

from lungmech.errors import ParameterError
from lungmech.fem.constraints import Displacement, clamp
from lungmech.fem.inverse_motion import InverseMotion
from lungmech.fem.loads import BodyForce, FollowerPressure, Traction
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.parameters import Parameter
from lungmech.fem.parametric import FullOrderModel
from lungmech.fem.placement import Image
from lungmech.fem.ramp import Ramp
from lungmech.fem.solver import Stepping
from lungmech.lung import Poromechanics, skeleton
from lungmech.lung.gravity import Gravity
from lungmech.lung.inverse import Imaged, InverseOptions
from lungmech.mesh import box, rectangle
from lungmech.mesh.geometry import Geometry
from lungmech.parallel.owned import owned_size

BREATH = Ramp((0.0, 1.0, 2.0), (1.0, 2.0, 1.0))  # end-expiration, end-inspiration, end-expiration
LUNG_PARAMETERS = (
    Parameter("stiffness", "material.c1", 200.0, (100.0, 400.0), log=True),
    Parameter("breath", "loads.pleural.amplitude", 1.0, (0.6, 1.4)),
    Parameter("posture", "loads.gravity.pitch", 0.0, (-90.0, 0.0)),
)


def imaged_lung(image: Image | None, comm: MPI.Comm = MPI.COMM_WORLD) -> Model:
    """The bundled right lung as imaged at end-expiration, held at its hilum, under pleural
    suction and its own weight balanced by the pleural pressure, with the three parameters of
    the bundled scene's box."""
    surface = ("pleura", "diaphragm", "mediastinum")
    loads = [
        FollowerPressure(surface, -500.0, ramp=BREATH, name="pleural"),
        Gravity(315.0, (0.0, 0.0, -9.81), balanced_on=surface, ramp=Ramp.constant(), name="gravity"),
    ]
    return bundled_lung(loads, comm, parameters=LUNG_PARAMETERS, image=image)


def inflated_block(
    image: Image | None,
    plane: bool = False,
    follower: bool = True,
    comm: MPI.Comm = MPI.COMM_WORLD,
    geometry: Geometry | None = None,
) -> Model:
    """A neo-Hookean block (3-D, or 2-D in plane strain) imaged at t₀ = 0.5 s: an imposed
    displacement already half applied, a follower pressure (or a dead traction) and a dead body
    force, with the stiffness and the pressure as parameters. ``geometry``: another mesh of it
    (a hyper-reduced model's body of sampled cells)."""
    if geometry is None:
        geometry = rectangle(comm, (1.0, 0.5), (6, 3)) if plane else box(comm, (1.0, 0.5, 0.5), (4, 2, 2))
    d = 2 if plane else 3
    pull = np.zeros(d)
    pull[0] = 0.08
    push = {"ramp": Ramp((0.0, 1.0), (0.0, 1.0)), "name": "push"}
    return Model(
        geometry,
        lambda mu: NeoHookean.from_young(mu["E"], 0.3),
        loads=[
            (FollowerPressure("y0", 0.15, **push) if follower else Traction("y0", (0.0,) * (d - 1) + (0.15,), **push)),
            BodyForce(tuple(-0.05 if i == 1 else 0.0 for i in range(d)), ramp=Ramp.constant(), name="weight"),
        ],
        constraints=[clamp("x0"), Displacement("x1", tuple(pull), ramp=Ramp((0.0, 1.0), (0.0, 1.0)))],
        parameters=[
            Parameter("E", "material.E", 10.0, (5.0, 20.0), log=True),
            Parameter("p", "loads.push.amplitude", 1.0, (0.5, 1.5)),
        ],
        plane="strain" if plane else None,
        image=image,
    )


def two_ways(build, stepping: Stepping, probes=()) -> tuple[FullOrderModel, FullOrderModel]:
    """The full model of one imaged problem by the fixed point and by the inverse motion."""
    fixed = build(None)
    moved = FullOrderModel(fixed, stepping, probes=probes, start=Imaged(fixed, InverseOptions(tolerance=1e-11)))
    motion = build(Image.motion(stepping.start))
    kept = FullOrderModel(motion, stepping, probes=probes, start=InverseMotion(motion))
    return moved, kept


def assert_same_answer(a, b, size: float) -> None:
    """Two solutions of one problem: the same reference volume, volumes along the path (of the
    path's volume change), strain energies, probes (of the body's size) and averages."""
    assert b.start.kind == a.start.kind == "imaged"
    reference = a.start.details["reference_volume"]
    assert b.start.details["reference_volume"] == pytest.approx(reference, rel=1e-9)
    for solution in (a, b):  # both start on the image
        assert solution.start.details["volume"] == pytest.approx(solution.start.details["imaged_volume"], rel=1e-9)
    change = np.ptp(np.concatenate([[reference], a.outputs["volume"]]))
    assert np.abs(b.outputs["volume"] - a.outputs["volume"]).max() <= 1e-7 * change
    energy = np.abs(a.outputs["strain_energy"]).max()
    assert np.abs(b.outputs["strain_energy"] - a.outputs["strain_energy"]).max() <= 1e-7 * energy
    if "probes" in a.outputs:
        assert np.abs(b.outputs["probes"] - a.outputs["probes"]).max() <= 1e-8 * size
    for name in a.outputs:
        if name.startswith("averages/"):
            scale = max(np.abs(a.outputs[name]).max(), 1e-300)
            assert np.abs(b.outputs[name] - a.outputs[name]).max() <= 1e-6 * scale, name


@pytest.mark.slow
def test_the_lung_with_balanced_gravity_at_several_mu():
    """The poromechanical lung, suction and weight balanced by the pleura, at the defaults and at
    a corner of its box (the posture turned): the fixed point's reference and breath, from the
    fixed mesh."""
    moved, kept = two_ways(imaged_lung, Stepping(end=2.0, max_step=0.5), probes=[[0.05, 0.0, 0.16]])
    for mu in ({}, {"stiffness": 100.0, "breath": 1.4, "posture": -90.0}):
        assert_same_answer(moved.solve(mu), kept.solve(mu), 0.24)


@pytest.mark.parametrize("plane", [False, True], ids=["3-D", "plane strain"])
def test_a_hyperelastic_block_imaged_half_way_through_its_loading(plane):
    """A neo-Hookean block imaged at t₀ = 0.5 s, when its imposed pull is half applied: the
    inverse map takes the pull off (ξ = −ū(t₀)) and the motion adds what follows (ū(t) − ū(t₀))."""
    stepping = Stepping(start=0.5, end=1.0, max_step=0.25)
    probe = [0.9, 0.25, 0.25][: 2 if plane else 3]
    moved, kept = two_ways(lambda image: inflated_block(image, plane), stepping, probes=[probe])
    for mu in ({}, {"E": 5.0, "p": 1.5}):
        assert_same_answer(moved.solve(mu), kept.solve(mu), 1.0)


def test_the_image_stays_where_it_was_imaged():
    """At any μ the state at t₀ is the image itself: w = 0, so the deformed volume is the image's
    exactly, and the reference map takes the imposed pull off the pulled face."""
    model = inflated_block(Image.motion(0.5))
    start = InverseMotion(model)
    start.place(model, None, model.parameters.values({"E": 7.0}), 0.5)
    owned = owned_size(model.space)
    assert np.all(model.state.x.array[:owned] == 0.0)
    pulled = model.imposed[1]
    xi = model.reference_map.x.array[pulled.where]
    assert np.allclose(xi, -0.5 * pulled.base, atol=1e-14)  # ξ = −ū(t₀) = −ramp(0.5) · 0.08 e_x


def test_the_inverse_tangent_is_not_symmetric_and_the_motion_tangent_is():
    """The inverse residual is a mixed derivative of the potential, not a gradient: its tangent
    is not symmetric. The motion's, the Hessian of a potential (dead loads only), is."""
    model = inflated_block(Image.motion(0.5), follower=False)
    start = InverseMotion(model)
    start.place(model, None, model.parameters.defaults, 0.5)

    def asymmetry(model: Model) -> float:
        matrix = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(model.jacobian), bcs=model.bcs)
        matrix.assemble()
        difference = matrix.copy()
        difference.transpose()
        difference.axpy(-1.0, matrix)
        ratio = difference.norm() / matrix.norm()
        for m in (matrix, difference):
            m.destroy()
        return ratio

    assert asymmetry(start.inverse) > 1e-3
    assert asymmetry(model) < 1e-12


def test_newton_converges_quadratically_with_the_weight_balanced():
    """The inverse problem's tangent carries the balanced weight's whole derivative: on an image
    the mass ∫ρ0 det(I + ∇ξ) dx moves with ξ, and with it the centre of mass and the force the
    pleura balances. Without that term Newton was linear (13 iterations at the defaults, 50 at a
    corner); with it, a few quadratic steps at every load."""
    model = imaged_lung(Image.motion(0.0))
    start = InverseMotion(model, body="lung")
    for mu in ({}, {"stiffness": 100.0, "breath": 1.4, "posture": -90.0}):
        assert start.place(model, None, model.parameters.values(mu), 0.0).newton_iterations <= 6


@pytest.mark.slow
def test_changing_mu_compiles_nothing(monkeypatch):
    """After one solve, the inverse motion and the breath at other μ compile no form."""
    stepping = Stepping(end=2.0, max_step=0.5)
    model = imaged_lung(Image.motion(0.0))
    full = FullOrderModel(model, stepping, start=InverseMotion(model))
    full.solve()
    calls = []
    original = dolfinx.jit.ffcx_jit
    monkeypatch.setattr(dolfinx.jit, "ffcx_jit", lambda *a, **k: calls.append(1) or original(*a, **k))
    solutions = [full.solve({"stiffness": c1, "posture": -45.0}) for c1 in (120.0, 300.0)]
    assert calls == []
    inspired = [solution.outputs["volume"][0] for solution in solutions]  # t = 1 s
    assert inspired[0] > inspired[1]  # a softer lung inflates more
    for solution in solutions:  # and breathes out to the image (t = 2 s, the loads of t = 0)
        assert solution.outputs["volume"][-1] == pytest.approx(solution.start.details["imaged_volume"], rel=1e-9)


def test_bad_inputs_are_refused_in_one_line():
    with pytest.raises(ParameterError, match="unknown must be 'motion' or 'inverse'"):
        Image("reference")
    with pytest.raises(ParameterError, match="starts a model of an image's motion"):
        InverseMotion(inflated_block(None))
    with pytest.raises(ParameterError, match="plane stress on an imaged mesh"):
        Model(rectangle(MPI.COMM_WORLD, (1.0, 1.0), (2, 2)), NeoHookean(1.0, 1.0), plane="stress", image=Image.motion())
    model = inflated_block(Image.motion(0.5))
    with pytest.raises(ParameterError, match=r"imaged at t = 0.5 s; its path cannot start at t = 0 s"):
        InverseMotion(model).place(model, None, model.parameters.defaults, 0.0)
    with pytest.raises(ParameterError, match="only a model of an image's motion"):
        inflated_block(None).set_reference_map(np.zeros(3))
    porous = Model(
        box(MPI.COMM_WORLD, (1.0, 1.0, 1.0), (1, 1, 1)),
        skeleton(160.0, 0.5, 200.0, 400.0),
        formulation=Poromechanics(1e4, imaged_porosity=0.7),
        constraints=[clamp("x0")],
        image=Image.motion(),
    )
    with pytest.raises(ParameterError, match="an imaged porosity is matched by the fixed point"):
        InverseMotion(porous)
