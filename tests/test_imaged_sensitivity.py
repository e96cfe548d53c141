"""Sensitivities of an imaged body — full, Galerkin and hyper-reduced — against central finite
differences of each model's own solves.

On an imaged body the mesh is the loaded state at t₀ for every μ: the unloaded reference ξ(μ)
moves with μ (the inverse motion), and the breath's forms read it. Its answer's derivative is
then dx/dμ = −K⁻¹(∂R/∂μ + ∂R/∂ξ dξ/dμ), with dξ/dμ the inverse problem's own sensitivity
(K_ξ dξ/dμ = −∂R_ξ/∂μ, or its reduced form), and the probes' u = w − ξ less dξ/dμ. A
poromechanical cube covers a field of the state beyond the motion (Φs, handed over from the
inverse problem at t₀), a field parameter (Φs0), formulation and law constants and a load.
Runs on 1 rank and, in the MPI group, on 2.
"""

from mpi4py import MPI

import numpy as np
import pytest
from test_sensitivity import LUNG, LUNG_MU, disagreement, finite_differences

from lungmech.errors import ParameterError
from lungmech.fem import Model, Stepping, clamp
from lungmech.fem.constraints import symmetry
from lungmech.fem.inverse_motion import InverseMotion
from lungmech.fem.parametric import FullOrderModel
from lungmech.fem.placement import Image
from lungmech.fem.sensitivity import ValueDerivatives, value_derivatives
from lungmech.lung import AlveolarPressure, Poromechanics, skeleton
from lungmech.lung.inverse import Imaged
from lungmech.mesh import box
from lungmech.mesh.geometry import Geometry
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
    monkeypatch.setattr(ValueDerivatives, "with_start", lambda self, functions, start: self)
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
    derivatives = start.derivatives(model, value_derivatives(model))
    exact = derivatives.functions[model.reference_map][:, full.parameters.names.index("c1")]
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
