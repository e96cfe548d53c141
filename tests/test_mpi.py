"""The same problem on MPI.COMM_WORLD and on one rank gives the same answer.

Run under ``mpiexec -n 2`` by ``make test`` (they also pass serially, trivially).
"""

import json

import numpy as np
import pytest
from fem import inflated_sphere, mean_inner_radius
from mpi4py import MPI

from lungmech.app import scene as scenes
from lungmech.app.run import run
from lungmech.fem.constraints import clamp
from lungmech.fem.loads import BodyForce, FollowerPressure, Traction
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.quantities import Probe, deformed_volume, strain_energy
from lungmech.fem.solver import Stepping, solve
from lungmech.mesh import box

pytestmark = pytest.mark.mpi
RTOL = 1e-10


def bent_block(comm) -> np.ndarray:
    geometry = box(comm, lengths=(3.0, 1.0, 1.0), cells=(6, 2, 2))
    model = Model(
        geometry,
        NeoHookean.from_young(10.0, 0.3),
        degree=2,
        constraints=[clamp("x0")],
        loads=[Traction("x1", (0.0, 0.0, -0.2)), BodyForce((0.0, 0.05, 0.0)), FollowerPressure("z1", 0.1)],
    )
    solve(model, Stepping(initial_step=0.25, growth=1.0))
    tip = Probe(geometry.mesh, [[3.0, 0.5, 0.5], [1.5, 1.0, 1.0]])(model.state)
    return np.concatenate([[deformed_volume(model)(), strain_energy(model)()], tip.ravel()])


def test_block_same_on_all_ranks_as_on_one():
    parallel, serial = bent_block(MPI.COMM_WORLD), bent_block(MPI.COMM_SELF)
    assert np.allclose(parallel, serial, rtol=RTOL, atol=RTOL * np.abs(serial).max())


def test_mixed_sphere_same_on_all_ranks_as_on_one():
    def inner_radius(comm) -> float:
        return mean_inner_radius(inflated_sphere(comm, 0.5, 0.25, Stepping(initial_step=0.5, growth=1.0)))

    assert inner_radius(MPI.COMM_WORLD) == pytest.approx(inner_radius(MPI.COMM_SELF), rel=RTOL)


SCENE = {
    "geometry": {"builder": "box", "lengths": [2.0, 1.0, 1.0], "cells": [4, 2, 2]},
    "material": {"law": "mooney_rivlin", "E": 1.0e3, "nu": 0.45},
    "formulation": {"degree": 2, "type": "mixed"},
    "constraints": [{"type": "clamp", "boundary": "x0"}],
    "loads": [{"type": "traction", "boundary": "x1", "value": [0.0, 0.0, -5.0]}],
    "stepping": {"initial_step": 0.5, "growth": 1.0},
    "output": {"fields": True, "probes": [[2.0, 0.5, 0.5]]},
}


def test_scene_run_same_on_all_ranks_as_on_one(tmp_path):
    comm = MPI.COMM_WORLD
    folder = comm.bcast(tmp_path, root=0)
    scene = scenes.parse(SCENE)
    parallel = run(scene, folder / "parallel", comm)
    serial = run(scene, tmp_path / "serial", MPI.COMM_SELF)
    assert parallel["dofs"] == serial["dofs"] and parallel["mpi_ranks"] == comm.size
    assert parallel["deformed_volume"] == pytest.approx(serial["deformed_volume"], rel=RTOL)
    assert np.allclose(parallel["probes"]["displacement"], serial["probes"]["displacement"], rtol=1e-8)
    written = json.loads((folder / "parallel" / "summary.json").read_text())
    assert written["deformed_volume"] == parallel["deformed_volume"]
    import pyvista

    # Fields: one .vtu piece per rank under a .pvtu per step, listed in fields.pvd
    reader = pyvista.PVDReader(str(folder / "parallel" / "fields.pvd"))
    reader.set_active_time_value(reader.time_values[-1])
    read = reader.read()[0]
    assert read.n_cells == serial["cells"] and "displacement" in read.point_data and "J" in read.cell_data


def test_lung_model_same_on_all_ranks_as_on_one():
    from test_lung import averages, unit_cube

    def state(comm) -> dict:
        model = unit_cube(0.5, comm=comm)
        solve(model, Stepping(initial_step=0.25, growth=1.0))
        return averages(model)

    parallel, serial = state(MPI.COMM_WORLD), state(MPI.COMM_SELF)
    for key in serial:
        assert parallel[key] == pytest.approx(serial[key], rel=RTOL), key


def test_inverse_with_balanced_gravity_same_on_all_ranks_as_on_one():
    from test_inverse import end_expiration_lung

    from lungmech.lung.inverse import unloaded_reference

    def reference(comm) -> tuple[float, float]:
        model = end_expiration_lung(comm)
        unloaded_reference(model, time=1.0)
        return model.geometry.volume(), deformed_volume(model)()

    parallel, serial = reference(MPI.COMM_WORLD), reference(MPI.COMM_SELF)
    assert parallel == pytest.approx(serial, rel=1e-8)


def test_modal_frequencies_same_on_all_ranks_as_on_one():
    from test_modal import cantilever

    from lungmech.fem.modal import modal_analysis

    parallel = modal_analysis(cantilever(MPI.COMM_WORLD), 4).eigenvalues
    serial = modal_analysis(cantilever(MPI.COMM_SELF), 4).eigenvalues
    assert parallel == pytest.approx(serial, rel=1e-8)


def test_dof_layout_is_the_same_on_all_ranks_as_on_one():
    from lungmech.parallel.layout import layout

    def canonical(comm):
        model = Model(box(comm, cells=(3, 2, 2)), NeoHookean.from_young(1.0, 0.3), degree=2)
        f = model.state
        f.interpolate(lambda x: np.array([x[0] + x[1] ** 2, x[2] * x[0], np.sin(x[1])]))
        where = layout(model.space)
        return where.fingerprint, where.gather(f.x.array[: len(where.index)])

    (parallel_print, parallel), (serial_print, serial) = canonical(MPI.COMM_WORLD), canonical(MPI.COMM_SELF)
    assert parallel_print == serial_print
    assert parallel == pytest.approx(serial, abs=1e-14)


def test_reduced_model_same_on_all_ranks_and_portable(tmp_path):
    """Built and solved on N ranks = built and solved on one; a file saved on N loads on one."""
    from test_rom import STEPPING, TRAINING, beam, run

    from lungmech import rom

    path = MPI.COMM_WORLD.bcast(str(tmp_path / "beam.npz"))

    def reduced(comm, saved=None):
        model = beam(comm)
        if saved is None:
            basis = rom.pod(model, rom.snapshots(model, STEPPING, TRAINING), size=5)
            if comm == MPI.COMM_WORLD:  # saved by the (possibly parallel) run, read by a serial one
                rom.save(path, model, basis)
        else:
            basis, _, _ = rom.load(saved, model)
        run(model, rom.ReducedSolver(model, basis), 1.25)
        return np.array([deformed_volume(model)(), strain_energy(model)()])

    parallel = reduced(MPI.COMM_WORLD)
    serial = reduced(MPI.COMM_SELF)
    loaded = reduced(MPI.COMM_SELF, saved=path)
    assert parallel == pytest.approx(serial, rel=1e-8)
    assert loaded == pytest.approx(parallel, rel=1e-10)


def _scene_folder(tmp_path):
    comm = MPI.COMM_WORLD
    return comm.bcast(tmp_path, root=0)


def test_a_failure_on_rank_0_is_raised_on_every_rank(tmp_path, monkeypatch):
    """Rank 0 alone writes the tables: its failure reaches every rank (no hang), the earlier
    result stays and the staging folder goes. A picture that cannot be drawn there is a warning."""
    import lungmech.app.run
    from lungmech.app import plot
    from lungmech.errors import LungmechError

    comm = MPI.COMM_WORLD
    folder = _scene_folder(tmp_path)
    scene = scenes.parse(
        {
            **SCENE,
            "output": {"fields": False},
            "formulation": {"degree": 1},
            "material": {"law": "neo_hookean", "E": 1.0e3, "nu": 0.3},
        }
    )
    run(scene, folder / "out", comm)
    before = {p.name: p.read_bytes() for p in (folder / "out").iterdir()}

    def broken(*args, **kwargs):
        raise RuntimeError("no display")

    monkeypatch.setattr(plot, "_draw", broken)  # rank 0 draws: the run goes on without the picture
    run(scene, folder / "pictureless", comm)
    assert not (folder / "pictureless" / "deformed.png").exists()
    assert (folder / "pictureless" / "summary.json").is_file()

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device", "history.csv")

    monkeypatch.setattr(lungmech.app.run, "_write_history", full)
    with pytest.raises((OSError, LungmechError), match="No space left on device"):
        run(scene, folder / "out", comm)
    comm.Barrier()
    assert {p.name: p.read_bytes() for p in (folder / "out").iterdir()} == before
    assert sorted(p.name for p in folder.iterdir()) == ["out", "pictureless"]


def test_a_bad_mesh_read_on_rank_0_is_an_error_on_every_rank(tmp_path):
    from lungmech import mesh as geometry
    from lungmech.errors import GeometryError

    comm = MPI.COMM_WORLD
    folder = _scene_folder(tmp_path)
    if comm.rank == 0:
        (folder / "cut.msh").write_text("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 2")
    comm.Barrier()
    with pytest.raises(GeometryError, match="cut.msh"):
        geometry.from_file(folder / "cut.msh", comm)


def test_rigid_body_modes_are_rigid_on_every_partition():
    """The near-nullspace of AMG: each mode, as a displacement, strains nothing (global centre)."""
    from dolfinx import fem
    from dolfinx.fem.petsc import assemble_matrix

    from lungmech.fem.materials import LinearElastic
    from lungmech.fem.solver import rigid_body_modes

    geometry = box(MPI.COMM_WORLD, lengths=(3.0, 1.0, 1.0), cells=(6, 2, 2), origin=(5.0, -2.0, 1.0))
    model = Model(geometry, LinearElastic.from_young(1.0, 0.3))
    K = assemble_matrix(fem.form(model.jacobian))
    K.assemble()
    space = rigid_body_modes(model.space)
    for mode in space.getVecs():
        product = mode.duplicate()
        K.mult(mode, product)
        assert product.norm() <= 1e-12 * K.norm() * mode.norm()
