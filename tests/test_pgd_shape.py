"""The a priori PGD over a population's shape coefficients (no full solve): the shape map
χ_a = x̂ + Σ aᵢ mᵢ enters every operator through det G and G⁻¹, rational in each aᵢ, so each
coefficient is a curve and the operators are the tensor product of Chebyshev series in all of
them (lungmech.pgd.assembly, lungmech.pgd.chebyshev), checked against the model's own residual.

Independent references: the full model on the template at random points of the box (its
energy-norm error, volume and probe), and at one shape the scene's physics built by hand on
the library's own moved mesh, with no shape map (tests/test_population_scene.py's)."""

from __future__ import annotations

from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest
import test_population_scene as shaped
from test_pgd import indicator_effectivity, relative_errors

from lungmech.app import reduce
from lungmech.app import scene as scenes
from lungmech.app.cli import main
from lungmech.app.run import full_order_model
from lungmech.pgd import chebyshev

# The population's block, linear: its own weight and a dead traction on its free end; the two
# shape coefficients and the stiffness over a factor 4.
LINEAR = {
    'law = "neo_hookean"': 'law = "linear"',
    'type = "follower_pressure"': 'type = "traction"',
    "value = 40.0": "value = [0.0, 0.0, 40.0]",
}
STIFFNESS = '[parameters.E]\ntarget = "material.E"\nrange = [5e2, 2e3]\nscale = "log"\n'


def linear_scene(folder: Path):
    """(the linear block's scene in ``folder``, beside the library's modes (every rank's); the
    library's modes)."""
    path, modes = shaped.population.__wrapped__(folder)
    text = shaped.BOX
    for old, new in LINEAR.items():
        text = text.replace(old, new)
    return shaped.write_once(path.with_name("linear.toml"), text + STIFFNESS), modes


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    """(the scene, its a priori PGD built by `lungmech pgd build` and loaded from the file, the
    library's modes)."""
    folder = Path(MPI.COMM_WORLD.bcast(str(tmp_path_factory.mktemp("pgd-shape"))))
    path, modes = linear_scene(folder)
    out = folder / "block-pgd.npz"
    assert main(["pgd", "build", str(path), "-o", str(out), "--modes", "20", "--intervals", "4", "-q"]) == 0
    return scenes.load(path), reduce.load(out), modes


@pytest.mark.slow
def test_the_shape_a_priori_is_the_full_model_at_random_points(block):
    """Each shape coefficient a curve of 9 to 33 points; the relative energy-norm error at 20
    random points ≤ 1e-4 (measured 6.0e-5 with 20 modes), the indicator's effectivity there
    within [1/3, 3]; the volume within 1e-3 of its change, the probe within 1e-3 of its motion
    and the strain energy within 1e-3 at 3 of them; the energy's quadratic form, read without
    its operator, the operator's."""
    scene, found, _ = block
    curves = found.built["curves"]
    assert [c["parameter"] for c in curves] == ["a1", "a2"] and all(9 <= c["points"] <= 33 for c in curves)
    model = found.model
    model.set_time(scene.stepping.end)
    points = model.parameters.sample(20, seed=99)
    errors = relative_errors(model, found.decomposition, points)
    assert errors.max() <= 1e-4
    # the indicator (the residual at the answer in W's dual norm, W the energy product of the
    # template at the defaults) against the error there: the stiffness's range against W's is
    # [1/2, 2], which the shape widens by its G (measured 0.47 to 1.9); every answer carries the
    # largest of the build's 16 points
    low, high = indicator_effectivity(model, found.decomposition, points, errors)
    assert 1 / 3 <= low and high <= 3
    assert found.solve(points[0]).indicator == found.built["estimate"] >= 0.5 * errors.max()
    full = full_order_model(scene)
    for point in points[:3]:
        a, b = found.solve(point), full.solve(point)
        assert a.start.details["volume"] == pytest.approx(b.start.details["volume"], rel=1e-12)  # the shape's own
        change = abs(b.outputs["volume"][-1] - b.start.details["volume"])
        assert abs(a.outputs["volume"][-1] - b.outputs["volume"][-1]) <= 1e-3 * change
        motion = np.abs(b.outputs["probes"]).max()
        assert np.abs(a.outputs["probes"] - b.outputs["probes"]).max() <= 1e-3 * motion
        assert a.outputs["strain_energy"][-1] == pytest.approx(b.outputs["strain_energy"][-1], rel=1e-3)
    # over a shape map the energy's quadratic form is on z alone (the volume's cubic on (z, a))
    online, rng = found.online, np.random.default_rng(3)
    assert online.shape == 2 and online.volume.c1.shape == (found.size + 2,)
    c, w, z = (rng.standard_normal(n) for n in (len(online.entries), len(online.energy), found.size))
    quadratic, powers = online.energy_and_volume(c, w, z)
    assert quadratic == pytest.approx(z @ online.operator(c, w) @ z, rel=1e-12) and powers is None


@pytest.mark.slow
def test_at_one_shape_it_is_the_physics_on_the_librarys_moved_mesh(block):
    """At a = (1.3, −0.7): the probe's displacement and the volumes as the scene's physics built
    by hand on the library's mesh moved to that shape (no shape map) gives them, to 1e-3."""
    scene, found, modes = block
    point = {"a1": 1.3, "a2": -0.7, "E": 1e3}
    a = found.solve(point)
    b = shaped.on_the_moved_mesh(scene, modes, [1.3, -0.7]).solve({})
    assert a.start.details["volume"] == pytest.approx(b.start.details["volume"], rel=1e-10)
    change = abs(b.outputs["volume"][-1] - b.start.details["volume"])
    assert abs(a.outputs["volume"][-1] - b.outputs["volume"][-1]) <= 1e-3 * change
    assert np.abs(a.outputs["probes"] - b.outputs["probes"]).max() <= 1e-3 * np.abs(b.outputs["probes"]).max()


@pytest.mark.slow
def test_its_derivatives_in_the_shape_are_its_own_differences(block):
    """The volume's and the strain energy's derivatives in a1, a2 and E (the series' own slopes
    in the shape, :meth:`Online.weights` along an axis) against central differences of the
    model's own answers, to 1e-6; an answer without them leaves the fem model's parameters
    as they were (the shape's values in closed form: no assembly, no fold check)."""
    _, found, _ = block
    point = {"a1": 0.4, "a2": -1.1, "E": 800.0}
    before = dict(found.model.parameter_values)
    found.solve(point)  # an answer from the values' closed forms: the fem model's parameters are not set
    assert found.model.parameter_values == before
    exact = found.solve(point, sensitivities=True).sensitivities
    for i, (name, h) in enumerate((("a1", 1e-5), ("a2", 1e-5), ("E", 1e-2))):
        up, down = (found.solve(point | {name: point[name] + s}) for s in (h, -h))
        for quantity in ("volume", "strain_energy"):
            slope = (up.outputs[quantity][-1] - down.outputs[quantity][-1]) / (2 * h)
            assert np.asarray(exact[quantity])[-1, i] == pytest.approx(slope, rel=1e-6, abs=1e-9 * abs(slope) + 1e-14)


def test_a_tensor_of_chebyshev_series_is_their_products():
    """chebyshev.tensor: Π T_{kᵢ}(2σᵢ − 1) in C order, and its derivative along one parameter,
    against numpy's Chebyshev polynomials."""
    from numpy.polynomial import chebyshev as numpy_chebyshev

    sigmas, counts = (0.3, 0.8, 0.55), (3, 4, 2)
    x = [2 * s - 1 for s in sigmas]
    values = [numpy_chebyshev.chebvander(np.array([xi]), n - 1)[0] for xi, n in zip(x, counts)]
    expected = np.einsum("i,j,k->ijk", *values).ravel()
    assert np.allclose(chebyshev.tensor(sigmas, counts), expected, rtol=1e-14, atol=1e-14)
    slopes = numpy_chebyshev.chebval(x[1], numpy_chebyshev.chebder(np.eye(4), scl=2.0, axis=0))
    along = np.einsum("i,j,k->ijk", values[0], slopes, values[2]).ravel()
    assert np.allclose(chebyshev.tensor(sigmas, counts, along=1), along, rtol=1e-13, atol=1e-13)
    assert chebyshev.tensor((), ()).tolist() == [1.0]
