"""Shape modes from a library of mappings: similarity removal, mass-weighted POD, leave-one-out
error, and new geometries from shape coefficients that a scene can run on."""

from mpi4py import MPI

import numpy as np
import pytest
from fem import write_once

from lungmech import mesh as geometry
from lungmech import meshes
from lungmech.errors import RegistrationError
from lungmech.mesh import nodes
from lungmech.registration import align
from lungmech.registration.library import Library, ShapeModes, leave_one_out

LUNG = meshes.reference("lung_phantom_right")


def _rotation(axis, degrees):
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = np.radians(degrees)
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


@pytest.fixture(scope="module")
def reference():
    mesh = geometry.from_file(LUNG, MPI.COMM_SELF).mesh
    space, where = nodes.displacement_space(mesh)
    u = nodes.positions(space, where)
    return u, nodes.masses(space, where), where.fingerprint


def _library(reference, latent, similarities):
    """Shapes X + Σ_k z_k w_k(X) placed by the given similarities."""
    X, weights, fingerprint = reference
    centred = (X - X.mean(axis=0)) / 0.1
    fields = [  # smooth shape changes of about a millimetre
        0.001 * np.column_stack([centred[:, 0] * centred[:, 2], np.zeros(len(X)), centred[:, 2] ** 2]),
        0.0008 * np.column_stack([np.sin(3 * centred[:, 1]), centred[:, 0] ** 2, np.zeros(len(X))]),
        0.0006 * np.column_stack([np.zeros(len(X)), np.cos(2 * centred[:, 2]), centred[:, 0] * centred[:, 1]]),
    ]
    displacements = []
    for z, similarity in zip(latent, similarities):
        shape = X + sum(zk * w for zk, w in zip(z, fields))
        displacements.append(similarity(shape) - X)
    names = tuple(f"s{j}" for j in range(len(latent)))
    return Library(names, X, weights, np.array(displacements), fingerprint, tuple({} for _ in names))


def _similarities(count, seed):
    rng = np.random.default_rng(seed)
    return [
        align.Similarity(
            rng.uniform(0.8, 1.2), _rotation(rng.normal(size=3), rng.uniform(0, 15)), rng.normal(0, 0.02, 3)
        )
        for _ in range(count)
    ]


def test_removing_similarities_makes_the_library_independent_of_pose_and_size(reference):
    latent = np.random.default_rng(0).normal(size=(6, 2))
    placed = _library(reference, latent, _similarities(6, 1))
    plain = _library(reference, latent, [align.Similarity()] * 6)
    assert np.allclose(placed.shape_changes(), plain.shape_changes(), atol=1e-12)
    a, b = placed.modes(), plain.modes()
    assert np.allclose(a.singular_values, b.singular_values, rtol=1e-9)


def test_a_rigid_pose_keeps_the_size_as_a_change_of_shape(reference):
    """Without position and orientation only, a library that differs by size alone has one mode,
    uniform dilation, whose spread is the sizes' (independent: the scales drawn)."""
    X, weights, _ = reference
    scales = np.random.default_rng(2).uniform(0.85, 1.15, 6)
    rigid = [align.Similarity(1.0, s.rotation, s.translation) for s in _similarities(6, 3)]
    placed = [align.Similarity(scale * r.scale, r.rotation, r.translation) for scale, r in zip(scales, rigid)]
    library = _library(reference, np.zeros((6, 1)), placed)
    assert np.abs(library.shape_changes("similarity")).max() < 1e-12  # size removed: nothing left
    modes = library.modes("rigid")
    assert modes.pose == "rigid" and len(modes.modes) == 1  # the POD keeps no round-off modes
    centred = X - weights @ X / weights.sum()
    radius = np.sqrt(weights @ np.sum(centred**2, axis=1) / weights.sum())  # RMS distance from the centroid
    assert modes.deviations[0] == pytest.approx(np.std(scales, ddof=1) * radius, rel=1e-6)
    for j in range(6):  # each member is the mean plus its size change
        assert np.allclose(modes.displacement(modes.coefficients[j, :1]), (scales[j] - 1) * centred, atol=1e-10)


def test_a_new_mapping_projects_on_the_modes_as_the_library_members_do(reference):
    """A member's own mapping (its pose included) projects to its coefficients with nothing left
    out; a shape change outside the library's span is left out, in metres."""
    latent = np.random.default_rng(4).normal(size=(7, 2))
    similarities = _similarities(7, 8)
    library = _library(reference, latent, similarities)
    for pose in ("similarity", "rigid"):
        modes = library.modes(pose)
        for j in (0, 3):
            found = modes.project(library.displacements[j], len(modes.modes))
            metres = modes.deviations  # (the last modes' spreads are round-off: compare in metres)
            assert np.allclose(found.coefficients * metres, modes.coefficients[j] * metres, atol=1e-12)
            assert found.rms < 1e-12 and found.largest < 1e-11
    X, weights, _ = reference
    bumps = 0.002 * np.cos(60 * X[:, 0]) * np.cos(60 * X[:, 1]) * np.cos(60 * X[:, 2])  # no rigid motion, no mode
    outside = np.column_stack([np.zeros(len(X)), np.zeros(len(X)), bumps])
    modes = library.modes("rigid")
    found = modes.project(library.displacements[1] + outside, len(modes.modes))
    assert found.rms == pytest.approx(np.sqrt(weights @ bumps**2 / weights.sum()), rel=0.05)
    assert found.largest == pytest.approx(np.abs(bumps).max(), rel=0.1)
    with pytest.raises(RegistrationError, match="project on 0 to"):
        modes.project(library.displacements[1], 9)


@pytest.mark.parametrize("k", [1, 2, 3])
def test_k_latent_parameters_give_k_modes_and_a_falling_leave_one_out_error(reference, k):
    latent = np.random.default_rng(k).normal(size=(9, k))
    library = _library(reference, latent, _similarities(9, 10 + k))
    modes = library.modes()
    sigma = modes.singular_values / modes.singular_values[0]
    # Removing similarities is non-linear: its second-order part (|u|/L ~ 1 %) leaks into
    # further modes, an order of magnitude down.
    assert sigma[k - 1] > 0.05 and sigma[k] < 0.05 * sigma[k - 1]
    assert modes.compactness()[k - 1] > 0.999
    error = library.leave_one_out()
    assert np.all(np.diff(error) <= 1e-12) and error[k] < 0.05 * error[0]
    # M-orthonormal modes.
    gram = np.einsum("n,knd,lnd->kl", modes.weights, modes.modes, modes.modes)
    assert np.allclose(gram, np.eye(len(gram)), atol=1e-10)
    # Each member is mean + its coefficients.
    for j, c in enumerate(modes.coefficients):
        assert np.allclose(modes.displacement(c), library.shape_changes()[j], atol=1e-9)


def test_leave_one_out_needs_three_shapes(reference):
    X, weights, _ = reference
    with pytest.raises(RegistrationError, match="at least 3"):
        leave_one_out(np.zeros((2, *X.shape)), weights)


def test_shape_modes_round_trip_and_refuse_another_mesh(reference, tmp_path):
    latent = np.random.default_rng(5).normal(size=(5, 2))
    modes = _library(reference, latent, _similarities(5, 6)).modes()
    path = tmp_path / "modes.npz"
    if MPI.COMM_WORLD.rank == 0:  # "call on one rank"
        modes.save(path)
    MPI.COMM_WORLD.Barrier()
    again = ShapeModes.load(path)
    for name in ("reference", "weights", "mean", "modes", "singular_values", "coefficients"):
        assert np.array_equal(getattr(modes, name), getattr(again, name))
    assert again.names == modes.names and again.fingerprint == modes.fingerprint and again.pose == "similarity"
    other = geometry.from_file(meshes.reference("lung_phantom_left"), MPI.COMM_SELF)
    with pytest.raises(RegistrationError, match="not the reference"):
        modes.geometry(other, [1.0])
    with pytest.raises(RegistrationError, match="at most"):
        modes.displacement(np.ones(len(modes.modes) + 1))
    write_once(tmp_path / "bad.npz", b"not a zip")
    with pytest.raises(RegistrationError, match="not a shape-modes file"):
        ShapeModes.load(tmp_path / "bad.npz")
    with pytest.raises(RegistrationError, match="not found"):
        ShapeModes.load(tmp_path / "none.npz")


@pytest.mark.slow
def test_a_shape_from_coefficients_is_a_geometry_a_scene_runs_on(reference, tmp_path):
    from lungmech.app import scene as scenes
    from lungmech.app.run import run

    latent = np.random.default_rng(7).normal(size=(5, 2))
    modes = _library(reference, latent, _similarities(5, 8)).modes()
    fresh = geometry.from_file(LUNG, MPI.COMM_WORLD)
    space, where = nodes.displacement_space(fresh.mesh)  # the node order of the reference
    new = modes.geometry(fresh, [2.0, -1.0])
    X, weights, _ = reference
    expected = X + modes.displacement([2.0, -1.0])
    placed = nodes.positions(space, where)  # on rank 0
    assert placed is None or np.allclose(placed, expected, atol=1e-12)
    geometry.write(new, tmp_path / "new_lung.vtu")
    scene = tmp_path / "scene.toml"
    write_once(
        scene,
        '[geometry]\nfile = "new_lung.vtu"\n[material]\nlaw = "neo_hookean"\nE = 1.0e3\nnu = 0.3\n'
        '[[constraints]]\ntype = "clamp"\nboundary = "hilum"\n'
        '[[loads]]\ntype = "follower_pressure"\nboundary = "pleura"\nvalue = -20.0\n'
        "[stepping]\nend = 1.0\ninitial_step = 1.0\n[output]\nfields = false\n",
    )
    summary = run(scenes.load(scene), tmp_path / "out", MPI.COMM_WORLD)
    assert summary["reference_volume"] == pytest.approx(new.volume(), rel=1e-10)
    assert summary["deformed_volume"] > summary["reference_volume"]
