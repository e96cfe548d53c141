"""The personalisation's least squares and its uncertainty, on a model whose answer is known.

A "breathing sphere": surface nodes x_i = R₀ n_i of a sphere, moved radially by
w_i = (a μ₁ + b μ₂ n_z,i) n_i, so the surface at μ is the body R(n) = c + d n_z with
c = R₀ + a μ₁, d = b μ₂, whose volume is (4π/3)(c³ + c d²). The end-inspiration image is that
body voxelised at 1 mm for the true μ: without noise the estimate is the truth to the voxels'
accuracy. With Gaussian noise on the data of the exact surface (a smooth function that vanishes
on it, sampled finely: no voxels' bias) the nominal 95 % intervals hold the truth in about 95 %
of replicates; the weak combination of two parameters that move the surface alike is
named; a parameter driven to its bound is said to be there, with no interval.
"""

from dataclasses import dataclass

import numpy as np
import pytest

from lungmech.errors import ParameterError
from lungmech.fem.parameters import Parameter, Parameters
from lungmech.registration.field import ImageFunction
from lungmech.registration.image import from_array
from lungmech.twin.fit import Fit, View, estimate
from lungmech.twin.surface import Surface, SurfaceNodes, surface_data
from lungmech.twin.uncertainty import laplace, resampled

R0, A, B = 0.05, 0.01, 0.008  # m
TRUTH = {"swell": 1.4, "tilt": -0.3}


@dataclass(frozen=True)
class Stepping:
    start: float = 0.0


@dataclass(frozen=True)
class Answer:
    outputs: dict
    sensitivities: dict


class BreathingSphere:
    """The answer of a model: probes at the surface nodes and the volume, with derivatives.
    ``alike``: a third parameter that moves the surface as ``swell`` does (not identifiable)."""

    def __init__(self, nodes: np.ndarray, alike: bool = False, swell: tuple[float, float] = (0.2, 2.0)) -> None:
        self.normals = nodes / np.linalg.norm(nodes, axis=1)[:, None]
        default = min(max(1.0, swell[0]), swell[1])
        items = [Parameter("swell", "material.E", default, swell), Parameter("tilt", "material.nu", 0.5, (-1.0, 1.0))]
        if alike:
            items.append(Parameter("puff", "loads.p.value", 0.0, (-1.0, 1.0)))
        self.parameters = Parameters(items)
        self.stepping = Stepping()

    def solve(self, mu, sensitivities=False, times=(0.0, 1.0)):
        values = self.parameters.values(mu)
        swell, tilt, puff = values["swell"], values["tilt"], values.get("puff", 0.0)
        nz = self.normals[:, 2]
        radial = A * (swell + puff) + B * tilt * nz
        c, d = R0 + A * (swell + puff), B * tilt
        volume = 4 * np.pi / 3 * (c**3 + c * d**2)
        dvolume = 4 * np.pi / 3 * np.array([(3 * c**2 + d**2) * A, 2 * c * d * B])
        columns = [A * self.normals, B * nz[:, None] * self.normals]
        if "puff" in values:
            dvolume, columns = np.append(dvolume, dvolume[0]), [*columns, A * self.normals]
        p = len(values)
        at_start = {"probes": np.zeros((len(nz), 3)), "volume": 4 * np.pi / 3 * R0**3}
        outputs = {
            "probes": np.stack([at_start["probes"], radial[:, None] * self.normals]),
            "volume": np.array([at_start["volume"], volume]),
        }
        derived = {
            "probes": np.stack([np.zeros((len(nz), 3, p)), np.stack(columns, axis=-1)]),
            "volume": np.stack([np.zeros(p), dvolume]),
        }
        return Answer(outputs, derived)


def sphere_nodes(count: int = 400) -> SurfaceNodes:
    """Fibonacci points on the sphere of radius R₀, each with an equal share of its area."""
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z**2)
    points = R0 * np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    return SurfaceNodes(points, np.full(count, 4 * np.pi * R0**2 / count))


def body_radius(x: np.ndarray) -> np.ndarray:
    """R(n) = c + d n_z of the true body at the directions of the points ``x`` (…, 3)."""
    radius = np.linalg.norm(x, axis=-1)
    nz = np.divide(x[..., 2], radius, out=np.zeros_like(radius), where=radius > 0)
    return R0 + A * TRUTH["swell"] + B * TRUTH["tilt"] * nz


def grid(spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Voxel centres (…, 3) of a cube around the body, and its first corner."""
    half = R0 + A * 2.5
    axes = np.arange(-half, half, spacing) + spacing / 2
    return np.stack(np.meshgrid(axes, axes, axes, indexing="ij"), axis=-1), np.full(3, axes[0] - spacing / 2)


@pytest.fixture(scope="module")
def data():
    """The body at the true μ, voxelised at 1 mm, as a segmentation's data."""
    centres, corner = grid(0.001)
    inside = np.linalg.norm(centres, axis=-1) <= body_radius(centres)
    return surface_data(from_array(inside, spacing=(0.001,) * 3, origin=corner))


@pytest.fixture(scope="module")
def exact():
    """The true body's surface without voxels: |x| − R(x/|x|), zero on it, sampled at 1 mm
    (smooth: its trilinear samples are exact to a few µm), and its volume."""
    spacing = 0.001
    centres, corner = grid(spacing)
    values = np.linalg.norm(centres, axis=-1) - body_radius(centres)
    affine = np.diag([spacing, spacing, spacing, 1.0])
    affine[:3, 3] = corner + spacing / 2
    c, d = R0 + A * TRUTH["swell"], B * TRUTH["tilt"]
    return Surface(ImageFunction(values, affine, distance_outside=True), 4 * np.pi / 3 * (c**3 + c * d**2), spacing)


def fit_of(data, alike=False, swell=(0.2, 2.0)) -> Fit:
    nodes = sphere_nodes()
    model = BreathingSphere(nodes.points, alike, swell)
    names = ["swell", "tilt", "puff"] if alike else ["swell", "tilt"]
    return Fit([View(model, nodes, data, 1.0, name="supine")], names)


def test_without_noise_the_estimate_is_the_truth(data):
    """To the 1 mm voxels' accuracy, from the defaults: the motion each parameter makes is
    within 0.1 mm (swell, over the whole surface) and 0.75 voxel (tilt, at the poles alone) of
    the true one. The distance field of a voxelised surface is itself wrong by ~0.4 mm (RMS):
    the residual at the truth is not zero."""
    fit = fit_of(data)
    result = estimate(fit)
    assert abs(result.values["swell"] - TRUTH["swell"]) * A <= 1e-4
    assert abs(result.values["tilt"] - TRUTH["tilt"]) * B <= 0.75e-3
    assert result.active == {"swell": None, "tilt": None}
    assert result.history[0]["cost"] > 100 * result.cost
    assert np.sqrt(np.mean(result.residual**2)) < 5e-4  # m: the voxelised distance's own error, under half a voxel


def test_the_jacobian_is_the_residuals_derivative(data):
    """The chain ∇d · ∂w/∂μ · ∂μ/∂θ against central differences of the residual in θ."""
    fit = fit_of(data)
    theta = np.array([0.4, 0.6])
    exact = fit.jacobian(theta)
    h = 1e-6
    for j in range(2):
        step = np.eye(2)[j] * h
        difference = (fit.residual(theta + step) - fit.residual(theta - step)) / (2 * h)
        assert np.abs(exact[:, j] - difference).max() <= 1e-5 * np.abs(difference).max()


def test_intervals_hold_the_truth_at_their_level(exact):
    """Gaussian noise of 1 mm on every surface datum (and the volume's equivalent): the 95 %
    intervals hold the truth in 93–99 % of 200 replicates, for each parameter; the noise level
    is estimated from the residual to within 10 %."""
    fit = fit_of(exact)
    rng = np.random.default_rng(7)
    sigma = 0.001
    held = {name: 0 for name in fit.names}
    estimated = []
    replicates = 200
    for _ in range(replicates):
        noise = rng.normal(0.0, sigma, fit.rows)
        result = estimate(fit, offset=noise)
        uncertainty = laplace(result, fit)
        estimated.append(uncertainty.sigma)
        for name in fit.names:
            interval = uncertainty.intervals[name]
            held[name] += interval.low <= TRUTH[name] <= interval.high
    for name, count in held.items():
        assert 0.93 * replicates <= count <= 0.99 * replicates, (name, count)
    assert np.mean(estimated) == pytest.approx(sigma, rel=0.1)


def test_resampled_estimates_spread_as_the_laplace_deviation(exact):
    """The bootstrap's spread and the Laplace standard deviation agree within 35 % (20 draws)."""
    fit = fit_of(exact)
    noise = np.random.default_rng(3).normal(0.0, 0.001, fit.rows)
    result = estimate(fit, offset=noise)
    uncertainty = laplace(result, fit)
    draws = resampled(fit, result, count=20, seed=1)
    spread = draws.std(axis=0, ddof=1)
    laplace_deviation = np.sqrt(np.diag(uncertainty.covariance))
    assert np.all(np.abs(spread / laplace_deviation - 1) < 0.35), (spread, laplace_deviation)


def test_the_model_error_widens_the_interval_as_a_bias(exact):
    """A model error δr enters as the shift A δr it makes: a uniform 0.5 mm error widens
    swell's interval by about 0.5 mm in its units of motion, whatever the number of data."""
    fit = fit_of(exact)
    result = estimate(fit, offset=np.random.default_rng(5).normal(0.0, 0.001, fit.rows))
    exact, biased = laplace(result, fit), laplace(result, fit, np.full(fit.rows, 5e-4))
    # swell moves every node by A per unit μ, over a range of 1.8: 0.5 mm is 0.5e-3/(A·1.8) in θ
    assert biased.bias[0] == pytest.approx(5e-4 / (A * 1.8), rel=0.05)
    for name in fit.names:
        assert (
            biased.intervals[name].high - biased.intervals[name].low
            > exact.intervals[name].high - exact.intervals[name].low
        )


def test_a_model_errors_signs_carry_it_into_the_estimate(exact):
    """An error that moves the poles one way and the equator the other (δr ∝ n_z² − 1/3,
    0.5 mm at most) hardly moves swell, which the whole surface determines: its bias is that
    shift, far below the worst case abs(A) abs(δr) of errors all of the hurtful sign; of the
    check points' errors, the largest shift counts."""
    fit = fit_of(exact)
    result = estimate(fit, offset=np.random.default_rng(5).normal(0.0, 0.001, fit.rows))
    nz = fit.views[0].nodes.points[:, 2] / R0
    pattern = np.append(5e-4 * (nz**2 - 1 / 3) / (2 / 3), 0.0)
    shifts = np.linalg.solve(result.jacobian.T @ result.jacobian, result.jacobian.T)
    biased = laplace(result, fit, np.vstack([pattern, 0.5 * pattern]))
    assert biased.bias == pytest.approx(np.abs(shifts @ pattern), rel=1e-9)
    assert biased.bias[0] < 0.1 * (np.abs(shifts) @ np.abs(pattern))[0]


def test_a_weak_combination_keeps_its_intervals_in_the_box_and_their_level(exact):
    """Swell and puff move the surface alike: only their sum is seen, and the Laplace deviation
    of each is larger than its whole range. Cut to the box (the posterior under a flat prior
    in it), each interval lies in its range and holds the truth in 90–100 % of 100 replicates
    at 1 mm noise; tilt's, which the data see, is as narrow as without puff."""
    fit, alone = fit_of(exact, alike=True), fit_of(exact)
    truth = TRUTH | {"puff": 0.0}
    rng = np.random.default_rng(11)
    held = {name: 0 for name in fit.names}
    for k in range(100):
        noise = rng.normal(0.0, 0.001, fit.rows)
        result = estimate(fit, offset=noise)
        uncertainty = laplace(result, fit, seed=k)
        if k == 0:
            assert np.sqrt(uncertainty.covariance[0, 0]) > 1.0  # (the unit box is 1 wide)
            narrow = laplace(estimate(alone, offset=noise), alone).intervals["tilt"]
            assert uncertainty.intervals["tilt"].noise == pytest.approx(narrow.noise, rel=0.15)
        for name, parameter in zip(fit.names, fit.parameters):
            interval = uncertainty.intervals[name]
            if interval.low is None:
                continue
            low, high = parameter.range
            assert low <= interval.low <= interval.high <= high
            held[name] += interval.low <= truth[name] <= interval.high
    for name, count in held.items():
        assert 90 <= count <= 100, (name, count)


def test_a_combination_the_data_cannot_see_is_named(exact):
    """Two parameters that move the surface alike: their correlation is −1 in the Laplace
    covariance and the weak direction is their difference."""
    fit = fit_of(exact, alike=True)
    result = estimate(fit, offset=np.random.default_rng(1).normal(0.0, 0.001, fit.rows))
    uncertainty = laplace(result, fit)
    weak = [d for d in uncertainty.directions if d.weak]
    assert len(weak) == 1
    assert abs(weak[0].combination["tilt"]) < 0.05
    assert weak[0].combination["swell"] * weak[0].combination["puff"] < 0  # swell − puff (in θ)
    assert "swell" in weak[0].text() and "puff" in weak[0].text()


def test_a_parameter_at_its_bound_gets_no_gaussian_interval(data):
    """With swell's range below the truth, the estimate stops at its upper bound and says so."""
    fit = fit_of(data, swell=(0.2, 0.7))
    result = estimate(fit)
    assert result.active["swell"] == "upper"
    interval = laplace(result, fit).intervals["swell"]
    assert interval.low is None and "upper bound" in interval.reason


def test_bad_inputs_are_refused_in_one_line(data):
    nodes = sphere_nodes()
    model = BreathingSphere(nodes.points)
    with pytest.raises(ParameterError, match="unknown parameter 'stiff'"):
        Fit([View(model, nodes, data, 1.0)], ["stiff"])
    with pytest.raises(ParameterError, match="both estimated and fixed"):
        Fit([View(model, nodes, data, 1.0, fixed={"tilt": 0.1})], ["tilt"])
    with pytest.raises(ParameterError, match="outside its range"):
        Fit([View(model, nodes, data, 1.0, fixed={"tilt": 3.0})], ["swell"])
    with pytest.raises(ParameterError, match="probes 400 points, not the 3 surface nodes"):
        Fit([View(model, SurfaceNodes(nodes.points[:3], nodes.areas[:3]), data, 1.0)], ["swell"]).residual(
            np.array([0.5])
        )


def test_a_meshs_surface_nodes_and_areas_are_the_same_on_any_partition():
    """A box's boundary vertices (all but the interior ones) with lumped areas summing to its
    surface area, listed alike on every rank (collective; runs on 2 ranks in the MPI group)."""
    from mpi4py import MPI

    from lungmech.mesh import box
    from lungmech.twin.surface import surface_nodes

    nodes = surface_nodes(box(MPI.COMM_WORLD, (1.0, 0.5, 0.5), (4, 2, 2)).mesh)
    assert len(nodes.points) == 5 * 3 * 3 - 3 * 1 * 1
    assert nodes.area == pytest.approx(2 * (0.5 + 0.5 + 0.25), rel=1e-12)
    gathered = MPI.COMM_WORLD.allgather(nodes.points)
    assert all(np.array_equal(points, gathered[0]) for points in gathered)
    # its triangles: the box's 2 (4·2 + 4·2 + 2·2) boundary triangles, closed (each edge in two), the same area
    corners = nodes.points[nodes.triangles]
    areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    assert len(nodes.triangles) == 2 * 2 * (8 + 8 + 4) and areas.sum() == pytest.approx(nodes.area, rel=1e-12)
    edges = np.sort(nodes.triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    assert set(np.unique(edges, axis=0, return_counts=True)[1]) == {2}


def test_an_interval_beside_a_parameter_at_its_bound_says_so(data):
    """With swell stopped at its bound, tilt's interval is conditional on it: the note says so.
    Its posterior cut to the box (the Gaussian's centre far beyond the bound: drawn by Gibbs
    sampling) has the quantiles of an independent weighing of uniform points in the box."""
    fit = fit_of(data, swell=(0.2, 0.7))
    result = estimate(fit)
    interval = laplace(result, fit).intervals["tilt"]
    assert interval.low is not None and "swell at a bound" in interval.reason
    J, r = result.jacobian, result.residual
    precision = J.T @ J / (r @ r / (len(r) - 2))
    centre = result.unit - np.linalg.solve(J.T @ J, J.T @ r)
    assert centre[0] > 1.0 + 5 / np.sqrt(precision[0, 0])  # (beyond the box's reach of plain draws)
    points = np.random.default_rng(3).random((400_000, 2))
    log = -0.5 * np.einsum("ni,ij,nj->n", points - centre, precision, points - centre)
    order = np.argsort(points[:, 1])
    weights = np.cumsum(np.exp(log - log.max())[order])
    expected = points[order, 1][np.searchsorted(weights / weights[-1], [0.025, 0.975])]
    tilt = fit.parameters[1]
    assert [tilt.to_unit(interval.low), tilt.to_unit(interval.high)] == pytest.approx(expected, abs=0.01)


def test_surface_noise_is_its_fraction_of_the_motion_and_correlated_as_asked(data):
    """Twin experiments' data noise: standard deviation 10 % of the surface's RMS observed
    motion, none on the volume row, seeded; independent between neighbours, or correlated
    over ℓ (near nodes alike, opposite ones not)."""
    from lungmech.twin.synthetic import surface_noise

    fit = fit_of(data)
    view = fit.views[0]
    rms = np.sqrt(np.mean(view.surface.distance(view.nodes.points)[0] ** 2))
    white = np.array([surface_noise(fit, 0.1, seed) for seed in range(300)])
    coloured = np.array([surface_noise(fit, 0.1, seed, correlation=0.3 * R0) for seed in range(300)])
    assert np.all(white[:, -1] == 0) and np.all(coloured[:, -1] == 0)
    assert white[:, :-1].std() == pytest.approx(0.1 * rms, rel=0.02)
    assert coloured[:, :-1].std() == pytest.approx(0.1 * rms, rel=0.1)
    assert np.array_equal(surface_noise(fit, 0.1, 7), surface_noise(fit, 0.1, 7))
    points = view.nodes.points
    near = int(np.argsort(np.linalg.norm(points - points[0], axis=1))[1])
    far = int(np.argmax(np.linalg.norm(points - points[0], axis=1)))

    def correlation(draws: np.ndarray, j: int) -> float:  # between node 0 and node j
        return float(np.corrcoef(draws[:, 0], draws[:, j])[0, 1])

    assert abs(correlation(white, near)) < 0.2
    assert correlation(coloured, near) > 0.8 and abs(correlation(coloured, far)) < 0.2
    with pytest.raises(ParameterError, match="correlation length"):
        surface_noise(fit, 0.1, correlation=-1.0)


def test_a_segmentations_boundary_noise_flips_surface_voxels_only():
    """A fraction of the voxels with a neighbour across the surface, and no others, flipped."""
    from lungmech.twin.synthetic import flip_boundary

    mask = np.zeros((12, 12, 12), dtype=bool)
    mask[3:9, 3:9, 3:9] = True
    image = from_array(mask, spacing=(0.002,) * 3, origin=(0.1, 0.0, -0.05))
    noisy = flip_boundary(image, 0.25, seed=4)
    changed = noisy.mask != mask
    inner, outer = np.zeros_like(mask), np.zeros_like(mask)
    inner[4:8, 4:8, 4:8] = True  # deeper than one voxel inside
    outer[2:10, 2:10, 2:10] = True  # within one voxel outside
    assert not (changed & inner).any() and not (changed & ~outer).any()
    surface = (6**3 - 4**3) + 6 * 6**2  # the cube's outer shell and the face-neighbours outside it
    assert changed.sum() == round(0.25 * surface)
    assert np.allclose(noisy.affine, image.affine)
    with pytest.raises(ParameterError, match="must lie in"):
        flip_boundary(image, 1.5)


def test_a_registered_meshs_own_offset_is_not_taken_for_motion(exact):
    """Nodes left 0.5 mm outside the end-expiration surface (as a registration that matches
    volumes leaves a faceted mesh's nodes): fitted to the distances themselves, the swell is
    short by that offset; to their changes from end-expiration (the baseline), it is found."""
    spacing = 0.001
    centres, corner = grid(spacing)
    affine = np.diag([spacing, spacing, spacing, 1.0])
    affine[:3, 3] = corner + spacing / 2
    at_rest = Surface(
        ImageFunction(np.linalg.norm(centres, axis=-1) - R0, affine, distance_outside=True),
        4 * np.pi / 3 * R0**3,
        spacing,
    )
    nodes = sphere_nodes()
    outside = SurfaceNodes(nodes.points * (R0 + 5e-4) / R0, nodes.areas)
    model = BreathingSphere(nodes.points)  # its motion is the sphere's, from where the nodes are

    def swell(baseline):
        fit = Fit([View(model, outside, exact, 1.0, baseline=baseline)], ["swell", "tilt"])
        return estimate(fit).values["swell"]

    assert abs(swell(None) - TRUTH["swell"]) * A == pytest.approx(5e-4, rel=0.1)  # the offset, taken for motion
    assert abs(swell(at_rest) - TRUTH["swell"]) * A < 5e-5


def test_the_model_error_is_the_chains_difference_on_the_data(exact):
    """At each check point, the last model's residual less the first's, signed, row by row; per
    step, the largest surface difference and the volume's offset. The models: the breathing
    sphere, then one whose nodes go 0.3 mm further out (a reduction's error), then one that also
    tilts by 0.2 mm n_z (a mesh's)."""
    from lungmech.twin.model_error import model_error

    class Moved(BreathingSphere):
        def __init__(self, nodes, radial):
            super().__init__(nodes)
            self.radial = radial

        def solve(self, mu, sensitivities=False, times=(0.0, 1.0)):
            answer = super().solve(mu, sensitivities, times)
            extra = self.radial(self.normals[:, 2])[:, None] * self.normals
            answer.outputs["probes"][1] += extra
            return answer

    nodes = sphere_nodes()
    views = [
        View(model, nodes, exact, 1.0, name="supine")
        for model in (
            BreathingSphere(nodes.points),
            Moved(nodes.points, lambda nz: np.full_like(nz, 3e-4)),
            Moved(nodes.points, lambda nz: 3e-4 + 2e-4 * nz),
        )
    ]
    errors, checked = model_error(views, [{"swell": 1.0, "tilt": 0.2}, TRUTH])
    nz = nodes.points[:, 2] / R0
    assert errors.shape == (2, len(nz) + 1)
    assert errors[:, :-1] == pytest.approx(np.tile(3e-4 + 2e-4 * nz, (2, 1)), abs=2e-5)  # (the distance's ∇: ~ n)
    assert np.all(errors[:, -1] == 0.0)  # (these models' volumes are their own, alike)
    assert [len(point["steps"]) for point in checked] == [2, 2]
    assert checked[1]["steps"][0]["surface_error_max"] == pytest.approx(3e-4, abs=2e-5)
    assert checked[1]["steps"][1]["surface_error_max"] == pytest.approx(2e-4, abs=2e-5)
