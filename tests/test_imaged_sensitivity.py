"""Sensitivities of an imaged body and of balanced gravity — full, Galerkin and hyper-reduced —
against central finite differences of each model's own solves.

On an imaged body the mesh is the loaded state at t₀ for every μ: the unloaded reference ξ(μ)
moves with μ (the inverse motion), and the breath's forms read it. Its answer's derivative is
then dx/dμ = −K⁻¹(∂R/∂μ + ∂R/∂ξ dξ/dμ), with dξ/dμ the inverse problem's own sensitivity
(K_ξ dξ/dμ = −∂R_ξ/∂μ, or its reduced form), and the probes' u = w − ξ less dξ/dμ. A
poromechanical cube covers a field of the state beyond the motion (Φs, handed over from the
inverse problem at t₀), a field parameter (Φs0), formulation and law constants and a load.
Balanced gravity's coefficients θ = Θ(x; c, ξ) (the centre of mass and the pressure that carries
the weight) add U Wᵀ to the tangent and their explicit dependence on the weight's direction and
on the imaged reference to ∂R/∂μ. Runs on 1 rank and, in the MPI group, on 2.
"""

from mpi4py import MPI

import numpy as np
import pytest
from test_sensitivity import LUNG, LUNG_MU, disagreement, finite_differences

from lungmech.errors import ParameterError
from lungmech.fem import FollowerPressure, Model, Stepping, clamp
from lungmech.fem.constraints import symmetry
from lungmech.fem.inverse_motion import InverseMotion
from lungmech.fem.parameters import Parameter
from lungmech.fem.parametric import FullOrderModel
from lungmech.fem.placement import Image
from lungmech.fem.ramp import Ramp
from lungmech.fem.sensitivity import output_derivatives, value_derivatives
from lungmech.lung import AlveolarPressure, Gravity, Poromechanics, skeleton
from lungmech.lung.inverse import Imaged
from lungmech.mesh import box, lung_phantom
from lungmech.mesh.geometry import Geometry
from lungmech.rom.imaged import ReducedImage
from lungmech.rom.reductor import ECSW, POD, Reductor, TrainingSet
from lungmech.rom.store import load_body, write_reduced

RTOL = 1e-6  # the finite differences' truncation is ~1e-8 here
STEPPING = Stepping(start=0.5, end=1.0, max_step=0.25)


def imaged_cube(image: Image | None = Image.motion(0.5), geometry: Geometry | None = None) -> Model:
    """A poromechanical cube imaged half-way through its inflation (held at x = 0);
    ``geometry``: another mesh of it (a hyper-reduced model's body of sampled cells)."""
    return Model(
        geometry or box(MPI.COMM_WORLD, cells=(3, 2, 2)),
        skeleton(0.16, 0.5, 0.2, 0.4),
        formulation=Poromechanics(100.0, 0.5, pore_barrier=1.0, pore_range=(0.5, 1.3)),
        constraints=[clamp("x0"), symmetry("y0", "y"), symmetry("z0", "z")],
        loads=[AlveolarPressure(0.5, name="air")],
        parameters=LUNG,
        image=image,
    )


@pytest.fixture(scope="module")
def models():
    model = imaged_cube()
    full = FullOrderModel(model, STEPPING, probes=[[1.0, 1.0, 1.0]], start=InverseMotion(model))
    with Reductor(full, POD(12), TrainingSet(full.parameters.sample(12, seed=1))) as reductor:
        yield {"full": full, "galerkin": reductor.reduce(), "hyper": reductor.reduce(ECSW(1e-6))}


@pytest.mark.parametrize("kind", ["full", "galerkin", "hyper"])
def test_an_imaged_bodys_sensitivities_are_its_own_finite_differences(models, kind):
    """Every output's derivative by every parameter, each model against its own solves."""
    model = models[kind]
    solution = model.solve(LUNG_MU, sensitivities=True)
    assert solution.start.kind == "imaged"
    for name in LUNG_MU:
        i = solution.parameter_names.index(name)
        for key, approximate in finite_differences(model, LUNG_MU, name).items():
            assert disagreement(solution.sensitivities[key][..., i], approximate) < RTOL, (kind, name, key)


@pytest.mark.parametrize("kind", ["full", "galerkin", "hyper"])
def test_without_the_references_derivative_they_are_wrong(models, kind, monkeypatch):
    """The planted case: with dξ/dμ and the start's derivative dropped, the stiffness's and the
    pressure's derivatives are wrong by far more than the tolerance."""
    computed = ReducedImage.moved  # (computed, for the probes' ξ, but not handed to the breath)
    monkeypatch.setattr(InverseMotion, "moved", lambda self, model: None)
    monkeypatch.setattr(ReducedImage, "moved", lambda self, model: [computed(self, model), None][1])
    model = models[kind]
    solution = model.solve(LUNG_MU, sensitivities=True)
    for name in ("c1", "pf"):
        i = solution.parameter_names.index(name)
        differences = finite_differences(model, LUNG_MU, name)
        worst = max(disagreement(solution.sensitivities[key][..., i], differences[key]) for key in ("volume", "probes"))
        assert worst > 1e-3, (kind, name)


def test_the_moving_mesh_start_refuses_sensitivities_in_one_line():
    """The fixed point on a moving mesh has no derivative of its nodes: refused, naming the way."""
    model = imaged_cube(image=None)
    full = FullOrderModel(model, STEPPING, start=Imaged(model))
    with pytest.raises(ParameterError, match="InverseMotion"):
        full.solve(LUNG_MU, sensitivities=True)


def test_the_derivative_of_the_reference_is_the_inverse_problems(models):
    """dξ/dμ handed to the breath is the inverse problem's own: the central difference of ξ
    solved at μ ± h (the stiffness)."""
    full = models["full"]
    start = full.start
    model = full.model
    low, high = full.parameters.named("c1").range
    h = 1e-4 * (high - low)

    def xi(c1: float) -> np.ndarray:
        full.solve(LUNG_MU | {"c1": c1}, times=[STEPPING.start])
        return model.reference_map.x.array.copy()

    difference = (xi(LUNG_MU["c1"] + h) - xi(LUNG_MU["c1"] - h)) / (2 * h)
    full.solve(LUNG_MU, times=[STEPPING.start])
    exact = start.moved(model).functions[model.reference_map][:, full.parameters.names.index("c1")]
    scale = model.geometry.mesh.comm.allreduce(np.abs(difference).max(), op=MPI.MAX)
    worst = model.geometry.mesh.comm.allreduce(np.abs(exact - difference).max(), op=MPI.MAX)
    assert scale > 0 and worst < RTOL * scale


def test_a_model_file_on_its_body_gives_the_same_sensitivities(models, tmp_path_factory):
    """The hyper-reduced model written, then loaded on its body of sampled cells alone (no full
    mesh): its sensitivities are the model's it was written from, to round-off."""
    folder = tmp_path_factory.mktemp(f"imaged-rank{MPI.COMM_WORLD.rank}")
    path = MPI.COMM_WORLD.bcast(str(folder / "cube.npz"))  # one path for all ranks
    write_reduced(path, models["hyper"])
    on_body = load_body(path, lambda geometry: imaged_cube(geometry=geometry), STEPPING)
    expected = models["hyper"].solve(LUNG_MU, sensitivities=True)
    answer = on_body.solve(LUNG_MU, sensitivities=True)
    for key in ("volume", "strain_energy"):
        assert np.allclose(answer.sensitivities[key], expected.sensitivities[key], rtol=1e-9, atol=1e-14), key


WEIGHED = (
    Parameter("c1", "material.c1", 0.2, (0.1, 0.4), unit="Pa"),
    Parameter("pf", "loads.air.value", 0.5, (0.1, 1.0), unit="Pa"),
    Parameter("pitch", "loads.gravity.pitch", 0.0, (-90.0, 0.0)),  # the weight's direction
)
WEIGHED_MU = {"c1": 0.25, "pf": 0.6, "pitch": -30.0}


def weighed_cube() -> FullOrderModel:
    """A poromechanical cube held at x = 0, inflated, its weight (raised with the inflation)
    carried by a pressure on its faces."""
    faces = ("x0", "x1", "y0", "y1", "z0", "z1")
    model = Model(
        box(MPI.COMM_WORLD, cells=(3, 2, 2)),
        skeleton(0.16, 0.5, 0.2, 0.4),
        formulation=Poromechanics(100.0, 0.5),
        constraints=[clamp("x0")],
        loads=[
            AlveolarPressure(0.5, name="air"),
            Gravity(0.01, (0.0, 0.0, -1.0), balanced_on=faces, ramp=Ramp((0.0, 1.0), (0.0, 1.0)), name="gravity"),
        ],
        parameters=WEIGHED,
    )
    return FullOrderModel(model, Stepping(times=(0.5,)), probes=[[1.0, 1.0, 1.0]])


@pytest.fixture(scope="module")
def weighed():
    full = weighed_cube()
    with Reductor(full, POD(8), TrainingSet(full.parameters.sample(6, seed=1))) as reductor:
        yield {"full": full, "galerkin": reductor.reduce(), "hyper": reductor.reduce(ECSW(1e-6))}


@pytest.mark.parametrize("kind", ["full", "galerkin", "hyper"])
def test_balanced_gravitys_sensitivities_are_the_finite_differences(weighed, kind):
    """The low-rank tangent and θ's explicit dependence: the stiffness, the pressure and the
    weight's direction (which moves θ alone), each model against its own solves."""
    model = weighed[kind]
    solution = model.solve(WEIGHED_MU, sensitivities=True)
    for name in WEIGHED_MU:
        i = solution.parameter_names.index(name)
        for key, approximate in finite_differences(model, WEIGHED_MU, name).items():
            # the weight's direction barely changes the volume and the energy (derivatives ~1e-9 of
            # them): there the differences' own noise is ~1e-6
            bound = 1e-5 if name == "pitch" and key in ("volume", "strain_energy") else RTOL
            assert disagreement(solution.sensitivities[key][..., i], approximate) < bound, (kind, name, key)


def test_without_thetas_own_derivative_the_weights_direction_is_wrong(weighed):
    """The planted case: θ not set again at the difference points (its explicit dependence on
    the weight's direction dropped), the probe's derivative by the direction is wrong."""
    full = weighed["full"]
    name = "pitch"
    expected = finite_differences(full, WEIGHED_MU, name)["probes"][-1]
    full.solve(WEIGHED_MU)  # the model at the end of the path
    frozen = value_derivatives(full.model, update=lambda: None)
    derived = output_derivatives(full.model, full.outputs, full.solver, derivatives=frozen)
    wrong = np.asarray(derived["probes"])[..., full.parameters.names.index(name)]
    assert disagreement(wrong, expected) > 1e-2


@pytest.mark.slow
def test_an_imaged_lung_with_its_weight_balanced():
    """The bundled lung's physics on a coarse phantom (1,350 cells), imaged at end-expiration,
    its weight balanced by the pleural pressure: the stiffness, the breath and the posture, full
    and hyper-reduced (the inverse problem carries the weight too)."""
    surface = ("pleura", "diaphragm", "mediastinum")
    parameters = (
        Parameter("stiffness", "material.c1", 200.0, (100.0, 400.0), log=True),
        Parameter("breath", "loads.pleural.amplitude", 1.0, (0.6, 1.4)),
        Parameter("posture", "loads.gravity.pitch", 0.0, (-90.0, 0.0)),
    )
    model = Model(
        lung_phantom(MPI.COMM_WORLD, mesh_size=0.03),
        skeleton(160.0, 0.5, 200.0, 400.0),
        formulation=Poromechanics(1e4, 0.3),
        constraints=[clamp("hilum")],
        loads=[
            FollowerPressure(surface, -500.0, ramp=Ramp((0.0, 1.0), (1.0, 2.0)), name="pleural"),
            Gravity(315.0, (0.0, 0.0, -9.81), balanced_on=surface, ramp=Ramp.constant(), name="gravity"),
        ],
        parameters=parameters,
        image=Image.motion(0.0),
    )
    full = FullOrderModel(
        model, Stepping(start=0.0, end=1.0, max_step=0.5), probes=[[0.05, 0.0, 0.16]], start=InverseMotion(model)
    )
    mu = {"stiffness": 250.0, "breath": 1.1, "posture": -40.0}
    with Reductor(full, POD(6), TrainingSet(full.parameters.sample(4, seed=1))) as reductor:
        models = {"full": full, "hyper": reductor.reduce(ECSW(1e-6))}  # (Galerkin: the weighed cube's)
    for kind, each in models.items():
        solution = each.solve(mu, sensitivities=True)
        for name in mu:
            i = solution.parameter_names.index(name)
            for key, approximate in finite_differences(each, mu, name).items():
                assert disagreement(solution.sensitivities[key][..., i], approximate) < RTOL, (kind, name, key)
