"""Shape registration: the image function, the shape derivative, similarity fits and the
registration itself, against analytic references."""

from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import fem

from lungmech import mesh as geometry
from lungmech import meshes
from lungmech.errors import ParameterError, RegistrationError
from lungmech.mesh.nodes import deformed
from lungmech.registration import align, field, metrics
from lungmech.registration.image import from_array
from lungmech.registration.sobolev import Options, ShapeEnergy, register


def ellipsoid_image(axes, spacing, transform=align.Similarity(), margin=0.012):
    """The voxelised ellipsoid transform({|x / axes| < 1})."""
    axes = np.asarray(axes, dtype=float)
    reach = transform.scale * axes.max() + margin
    lo = transform.translation - reach
    n = np.ceil(2 * reach / spacing).astype(int) + 1
    points = lo + np.indices((n, n, n)).reshape(3, -1).T * spacing
    local = transform.inverse()(points)
    mask = (np.sum((local / axes) ** 2, axis=1) < 1.0).reshape(n, n, n)
    return from_array(mask, spacing=(spacing,) * 3, origin=lo)


@pytest.fixture(scope="module")
def sphere_mesh():
    return geometry.ellipsoid(MPI.COMM_SELF, (0.05, 0.05, 0.05), mesh_size=0.012).mesh


def _rotation(axis, degrees):
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = np.radians(degrees)
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


# --- the image function ----------------------------------------------------------------------


def test_trilinear_sampling_reproduces_linear_fields_and_extends_outside_the_box():
    affine = np.array([[0.002, 0.0005, 0, -0.01], [0, 0.0025, 0, 0.02], [0.0003, 0, 0.0015, 0.0], [0, 0, 0, 1]])
    index = np.indices((12, 10, 9)).reshape(3, -1).T
    points = index @ affine[:3, :3].T + affine[:3, 3]
    a, b = np.array([1.5, -2.0, 0.7]), 0.3
    linear = field.ImageFunction((points @ a + b).reshape(12, 10, 9), affine, distance_outside=True)
    rng = np.random.default_rng(1)
    inside = (rng.uniform(0, 1, (200, 3)) * [11, 9, 8]) @ affine[:3, :3].T + affine[:3, 3]
    value, gradient = linear(inside)
    assert np.allclose(value, inside @ a + b, atol=1e-12)
    assert np.allclose(gradient, a, atol=1e-10)
    # Outside: the value at the nearest box point plus the distance to the box.
    corner = affine[:3, 3]
    away = corner - 0.01 * affine[:3, 0] / np.linalg.norm(affine[:3, 0])
    value, _ = linear(away[None])
    assert value[0] == pytest.approx(corner @ a + b + 0.01, abs=1e-12)
    binary = field.ImageFunction(np.zeros((12, 10, 9)), affine, distance_outside=False)
    value, gradient = binary(away[None])
    assert value[0] == 1.0 and not gradient.any()


def test_signed_distance_of_a_ball_is_the_distance_to_its_sphere():
    radius, h = 0.03, 0.002
    image = ellipsoid_image([radius] * 3, h)
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(300, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    distances = rng.uniform(-0.02, 0.03, 300)
    points = directions * (radius + distances)[:, None]
    for smoothing in (0.0, 1.0):
        value, gradient = field.signed_distance(image, smoothing)(points)
        assert np.max(np.abs(value - distances)) < 0.75 * h
        near = np.abs(distances) > 3 * h  # away from the staircase: a unit outward gradient
        assert np.median(np.sum(gradient[near] * directions[near], axis=1)) > 0.95
    binary = field.binary(image)(points)[0]
    assert np.all(binary[distances > h] == 1.0) and np.all(binary[distances < -h] == -1.0)
    with pytest.raises(ParameterError, match="smoothing"):
        field.signed_distance(image, -1.0)


def test_signed_distance_on_an_anisotropic_grid_and_its_gradient_everywhere():
    """A half-space on 1 × 1 × 3 mm voxels: I = z − z_surface exactly, inside and outside the box,
    and the gradient is the derivative of the value (finite differences), also outside."""
    mask = np.zeros((10, 10, 12), dtype=bool)
    mask[:, :, :6] = True  # the surface is the face between k = 5 and 6: z = 16.5 mm
    f = field.signed_distance(from_array(mask, spacing=(0.001, 0.001, 0.003)), smoothing=0.0)
    z = np.linspace(0.002, 0.03, 15)
    value, _ = f(np.column_stack([np.full(15, 0.004), np.full(15, 0.005), z]))
    assert np.allclose(value, z - 0.0165, atol=1e-12)
    rng = np.random.default_rng(2)
    points = rng.uniform([-0.01, -0.01, -0.02], [0.02, 0.02, 0.05], (50, 3))  # many outside the box
    value, gradient = f(points)
    step = 1e-7
    for axis in range(3):
        shift = np.zeros(3)
        shift[axis] = step
        difference = (f(points + shift)[0] - f(points - shift)[0]) / (2 * step)
        assert np.allclose(gradient[:, axis], difference, atol=1e-5)


# --- the energy and its shape derivative -----------------------------------------------------


def _energy(mesh, image_function, options=Options()):
    u = fem.Function(fem.functionspace(mesh, ("Lagrange", 1, (3,))))
    energy = ShapeEnergy(u, 1.0 / 0.05**2, options)
    energy.use(image_function)
    return u, energy


@pytest.mark.parametrize("distortion", [0.0, 0.01])
def test_shape_derivative_passes_the_taylor_test(sphere_mesh, distortion):
    """Ψ(u + t v) − Ψ(u) − t DΨ(u)[v] = O(t²), for a linear image function (exactly sampled),
    with and without the shape-distortion term."""
    affine = np.diag([0.004, 0.004, 0.004, 1.0])
    affine[:3, 3] = -0.1
    points = np.indices((51, 51, 51)).reshape(3, -1).T * 0.004 - 0.1
    a = np.array([2.0, -1.0, 3.0])
    linear = field.ImageFunction((points @ a + 0.01).reshape(51, 51, 51), affine, distance_outside=True)
    u, energy = _energy(sphere_mesh, linear)
    energy.use(linear, distortion)
    try:
        u.interpolate(lambda x: np.stack([0.1 * x[1] ** 2 / 0.05, 0.05 * x[0], 0.2 * x[2] * x[0] / 0.05]))
        start = energy.state()
        v = fem.Function(u.function_space)
        v.interpolate(lambda x: np.stack([np.sin(40 * x[2]), x[0] * x[1] / 0.05**2, np.cos(30 * x[0])]) * 0.01)
        direction = v.x.array[: energy.owned]
        psi0 = energy.value()
        slope = energy.dot(energy.derivative(), direction)
        remainders = []
        for t in (0.4, 0.2, 0.1, 0.05):
            energy.set_state(start + t * direction)
            remainders.append(abs(energy.value() - psi0 - t * slope))
        rates = np.log2(np.array(remainders[:-1]) / remainders[1:])
        assert np.all(rates > 1.9), rates
    finally:
        energy.destroy()


def test_binary_energy_measures_the_symmetric_difference(sphere_mesh):
    """With the ±1 image, Ψ(ω) − Ψ(S) = |ω Δ S|, Ψ(S) = −|S|: for ω ⊃ S, |ω| − 2|S|."""
    h = 0.0015
    for radius in (0.04, 0.055):  # the 0.05 ball strictly contains / lies in the image's ball
        image = ellipsoid_image([radius] * 3, h)
        u, energy = _energy(sphere_mesh, field.binary(image), Options(quadrature_degree=4))
        try:
            psi = energy.value()
        finally:
            energy.destroy()
        mesh_volume = metrics_volume(sphere_mesh)
        symmetric = abs(mesh_volume - image.volume)  # one contains the other
        assert psi + image.volume == pytest.approx(symmetric, rel=0.03)


def metrics_volume(mesh):
    return mesh.comm.allreduce(fem.assemble_scalar(fem.form(1.0 * ufl.dx(domain=mesh))), op=MPI.SUM)


# --- similarity transforms -------------------------------------------------------------------


def test_procrustes_recovers_a_similarity_and_its_removal_leaves_nothing():
    rng = np.random.default_rng(3)
    points = rng.normal(size=(50, 3))
    weights = rng.uniform(0.5, 2.0, 50)
    truth = align.Similarity(1.3, _rotation([1, 2, 0.5], 35), np.array([0.1, -0.2, 0.3]))
    fit = align.procrustes(points, truth(points), weights)
    assert fit.scale == pytest.approx(1.3, rel=1e-12)
    assert np.allclose(fit.rotation, truth.rotation, atol=1e-12)
    assert np.allclose(fit.inverse()(truth(points)), points, atol=1e-12)
    from lungmech.registration.library import without_similarity

    shape_change = 0.01 * np.sin(points)
    moved = truth(points + shape_change) - points
    residual = without_similarity(points, moved, weights)
    # Removing the similarity leaves a shape change, up to the similarity that best fits it.
    again = without_similarity(points, shape_change, weights)
    assert np.allclose(residual, again, atol=1e-12)
    assert np.allclose(without_similarity(points, truth(points) - points, weights), 0.0, atol=1e-12)
    with pytest.raises(RegistrationError):
        align.procrustes(points, points[:10])


def test_moments_fit_recovers_a_rotated_scaled_shifted_ellipsoid():
    mesh = geometry.ellipsoid(MPI.COMM_SELF, (0.06, 0.045, 0.03), mesh_size=0.01).mesh
    truth = align.Similarity(1.15, _rotation([0.3, 1.0, 0.2], 20), np.array([0.01, -0.02, 0.015]))
    image = ellipsoid_image([0.06, 0.045, 0.03], 0.0015, truth)
    fit = align.moments_fit(mesh, image)
    # Mesh faceting and voxel staircase limit the moments to about a percent.
    assert fit.scale == pytest.approx(truth.scale, rel=0.01)
    assert np.allclose(fit.translation, truth.translation, atol=0.5 * 0.0015)
    angle = np.degrees(np.arccos(np.clip((np.trace(fit.rotation.T @ truth.rotation) - 1) / 2, -1, 1)))
    assert angle < 1.0
    no_rotation = align.moments_fit(mesh, image, rotation=False)
    assert np.allclose(no_rotation.rotation, np.eye(3))


# --- registration ----------------------------------------------------------------------------


@pytest.mark.slow
def test_registering_a_sphere_to_an_ellipsoid_meets_the_targets(sphere_mesh):
    h = 0.002
    transform = align.Similarity(1.0, _rotation([0, 0, 1], 10), np.array([0.01, -0.005, 0.02]))
    image = ellipsoid_image([0.06, 0.045, 0.08], h, transform)
    reference = sphere_mesh.geometry.x.copy()
    result = register(sphere_mesh, image)
    assert result.converged and result.min_jacobian > 0.2
    with deformed(result.displacement) as mesh:
        report = metrics.report(mesh, image)
    assert report["dice"] >= 0.97
    assert report["mean_surface_distance"] <= h
    assert report["hd95"] <= 2 * h
    summary = result.summary()
    assert summary["iterations"] == sum(s["iterations"] for s in summary["stages"])
    assert np.array_equal(sphere_mesh.geometry.x, reference)  # the reference is untouched


def test_registration_options_are_checked():
    with pytest.raises(ParameterError, match="image_function"):
        Options(image_function="mutual information")
    with pytest.raises(ParameterError, match="min_jacobian"):
        Options(min_jacobian=1.5)
    with pytest.raises(ParameterError, match="stages"):
        Options(stages=())


# --- lung phantoms ---------------------------------------------------------------------------

from lungmech.mesh.lung_shape import LungShape  # noqa: E402
from lungmech.registration import phantom  # noqa: E402
from lungmech.registration.library import mapping_library  # noqa: E402

PHANTOMS = {  # reference mesh, target shape, voxel size, pose
    "taller, narrower right lung": ("right", LungShape(height=0.27, width=0.10, depth=0.15, apex=0.27), 0.0025),
    "smaller right lung, higher dome": ("right", LungShape(height=0.20, width=0.10, depth=0.15, dome=0.23), 0.0015),
    "broad left lung, small notch": (
        "left",
        LungShape(side="left", width=0.12, depth=0.18, notch=0.35, mediastinal=0.38),
        0.002,
    ),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", PHANTOMS)
def test_registering_the_reference_lung_to_phantoms_meets_the_targets(case):
    side, shape, spacing = PHANTOMS[case]
    mesh = geometry.from_file(meshes.reference(f"lung_phantom_{side}"), MPI.COMM_WORLD).mesh
    image = phantom.voxelise(shape, spacing, offset=(0.01, -0.02, 0.03))
    result = register(mesh, image)
    with deformed(result.displacement) as mapped:
        report = metrics.report(mapped, image)
    assert report["dice"] >= 0.97, report
    assert report["mean_surface_distance_voxels"] <= 1.0, report
    assert result.min_jacobian > 0.2


@pytest.mark.slow
def test_a_cohort_of_k_latent_parameters_gives_k_dominant_shape_modes():
    k = 2
    cohort = phantom.cohort(8, k, seed=1, size_spread=0.05, shift=0.01)
    images = {f"p{j}": im for j, im in enumerate(cohort.images(spacing=0.0025))}
    mesh = geometry.from_file(meshes.reference("lung_phantom_right"), MPI.COMM_WORLD).mesh
    library = mapping_library(mesh, images)
    assert min(r["dice"] for r in library.reports) >= 0.97
    modes = library.modes()
    # k modes carry the variance; the rest is registration noise (about a third of a voxel).
    assert modes.compactness()[k - 1] >= 0.95
    loo = library.leave_one_out()
    assert loo[k] < 0.5 * loo[0]
    assert np.all(np.diff(loo) <= 1e-3 * loo[0])


@pytest.mark.mpi
def test_registration_is_the_same_on_any_number_of_ranks():
    """1 and N ranks give the same registered shape and metrics. Node by node the mappings agree
    to a fraction of a voxel only: partitions differ in round-off, and where the energy is flat
    (nodes sliding along the surface) the descent's step decisions amplify it."""
    from lungmech.mesh import nodes

    h = 0.0025
    image = ellipsoid_image([0.06, 0.045, 0.08], h, align.Similarity(1.0, np.eye(3), np.array([0.01, 0, 0])))
    results = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        mesh = geometry.ellipsoid(comm, (0.05, 0.05, 0.05), mesh_size=0.012).mesh
        result = register(mesh, image)
        space, where = nodes.displacement_space(mesh)
        with deformed(result.displacement) as mapped:
            report = metrics.report(mapped, image)
        results.append((MPI.COMM_WORLD.bcast(nodes.gather(result.displacement, where)), result.psi, report))
    (parallel, psi_p, report_p), (serial, psi_s, report_s) = results
    distance = np.linalg.norm(parallel - serial, axis=1)
    assert psi_p == pytest.approx(psi_s, rel=1e-4)
    assert report_p["dice"] == pytest.approx(report_s["dice"], abs=2e-3)
    assert report_p["mean_surface_distance"] == pytest.approx(report_s["mean_surface_distance"], abs=0.05 * h)
    # Measured over repeated runs: RMS 0.01-0.19 voxel, largest 0.04-0.54 voxel.
    assert np.sqrt(np.mean(distance**2)) < 0.3 * h and distance.max() < h
