"""A hyper-reduced model loaded on its body alone (its sampled cells, no full mesh) answers as the
same model loaded on the full mesh, on 1 and 2 ranks; ``rom solve`` uses it unless full fields
are asked for."""

import csv
import json

from mpi4py import MPI

import numpy as np
import pytest
from fem import PARAMETRIC_SCENE

from lungmech.app import reduce as reduce_app
from lungmech.app import scene as scenes
from lungmech.app.cli import main
from lungmech.errors import ModelFileError, ParameterError
from lungmech.rom import body, store
from lungmech.rom.accuracy import errors
from lungmech.rom.whole import Stored

# the pulled block, a softer slab in it (a regional stiffness: a material field), a probe
SCENE = (
    PARAMETRIC_SCENE.replace("fields = false", "fields = true\nprobes = [[2.0, 0.5, 0.5]]")
    + """[parameters.soft]
target = "material.E"
range = [100.0, 1000.0]
region = { normal = [1.0, 0.0, 0.0], position = 1.0, width = 0.4 }
[stepping]
times = [0.5]
"""
)
POINT = {"stiffness": 1500.0, "pull": 3.5, "soft": 300.0}  # not a training point


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A hyper-reduced model of the block (with its indicator's enrichment), and its folder."""
    comm = MPI.COMM_WORLD
    folder = comm.bcast(tmp_path_factory.mktemp("body") if comm.rank == 0 else None)
    if comm.rank == 0:
        (folder / "scene.toml").write_text(SCENE)
    comm.barrier()
    scene = scenes.load(folder / "scene.toml")
    reduce_app.build(scene, folder / "m.npz", size=5, samples=3, hyper="ecsw", hyper_tolerance=1e-5, comm=comm)
    return folder


def _outputs(solution) -> dict:
    return {name: np.asarray(value) for name, value in solution.outputs.items()}


@pytest.mark.mpi
def test_the_body_answers_as_the_model_on_its_full_mesh(built):
    """Outputs (volume, energy, probes), loads and the indicator at an unseen μ agree to round-off;
    the body holds the sampled cells only, and says the full model's size."""
    on_body = reduce_app.load(built / "m.npz")
    on_mesh = reduce_app.load(built / "m.npz", fields=True)
    mesh = on_body.model.geometry.mesh
    cells = mesh.comm.allreduce(mesh.topology.index_map(3).size_local, op=MPI.SUM)
    full = on_mesh.model.geometry.mesh.topology.index_map(3).size_global
    sampled = mesh.comm.allreduce(len(body.cells_of(on_mesh.sample)), op=MPI.SUM)
    assert cells == sampled < full
    # the sampled cells' nodes, shared as on the full mesh: as many as they touch there
    full_mesh = on_mesh.model.geometry.mesh
    touched = np.unique(
        full_mesh.geometry.input_global_indices[full_mesh.geometry.dofmaps[0][body.cells_of(on_mesh.sample)]]
    )
    every = np.unique(np.concatenate(mesh.comm.allgather(touched)))
    nodes = mesh.geometry.index_map().size_global
    assert nodes == len(every) < 4 * cells
    assert on_body.describe()["cells"] == full and on_body.describe()["dofs"] == 3 * 7 * 3 * 3
    a, b = on_body.solve(POINT), on_mesh.solve(POINT)
    for name, value in _outputs(b).items():
        assert _outputs(a)[name] == pytest.approx(value, rel=1e-10, abs=1e-14), name
    assert a.indicator == pytest.approx(b.indicator, rel=1e-8) and a.indicator > 0
    assert np.allclose(a.states, b.states, rtol=1e-9, atol=1e-12)
    assert on_body.model.geometry.volume() == pytest.approx(on_mesh.model.geometry.volume(), rel=1e-14)
    with pytest.raises(ParameterError, match="lives on its sampled cells alone and has no full state to compare"):
        errors(on_body, b, a)  # its states' full fields: on the full mesh only


def test_rom_solve_writes_numbers_in_real_time_and_fields_when_asked(built):
    """Without --fields: summary.json and history.csv only, from the body; with it, what run writes;
    the same rows either way."""
    model, quick, full = built / "m.npz", built / "quick", built / "with-fields"
    sets = [item for name, value in POINT.items() for item in ("--set", f"{name}={value}")]
    assert main(["rom", "solve", str(model), "-o", str(quick), *sets, "-q"]) == 0
    assert main(["rom", "solve", str(model), "-o", str(full), *sets, "--fields", "-q"]) == 0
    assert sorted(p.name for p in quick.iterdir() if not p.name.startswith(".")) == ["history.csv", "summary.json"]
    assert {"fields.pvd", "deformed.png", "summary.json", "history.csv"} <= {p.name for p in full.iterdir()}
    fast, slow = (json.loads((folder / "summary.json").read_text()) for folder in (quick, full))
    assert fast["full_fields"] is False and slow["full_fields"] is True
    assert fast["dofs"] == slow["dofs"] and fast["cells"] == slow["cells"]
    assert fast["outputs"]["volume"] == pytest.approx(slow["outputs"]["volume"], rel=1e-10)
    rows = [list(csv.DictReader((folder / "history.csv").open())) for folder in (quick, full)]
    assert len(rows[0]) == len(rows[1]) and rows[0][0].keys() == rows[1][0].keys()
    for fast_row, slow_row in zip(*rows):
        for name, value in fast_row.items():
            if name != "step_seconds [s]":
                assert (value == "") == (slow_row[name] == ""), name
                assert value == "" or float(value) == pytest.approx(float(slow_row[name]), rel=1e-9, abs=1e-14), name


def test_what_the_file_does_not_hold_is_refused_in_one_line(built, tmp_path):
    """A name the body's file does not hold; a reduced model without a body (not hyper-reduced)."""
    with pytest.raises(ModelFileError, match="holds no 'volume' of its reduced model: rebuild it"):
        Stored({"constraints": np.zeros(0, int)}, np.zeros(3), np.zeros((3, 0)), "m.npz").get("volume", None)
    scene = scenes.load(built / "scene.toml")
    galerkin = tmp_path / "galerkin.npz"
    reduce_app.build(scene, galerkin, size=3, samples=2)
    with pytest.raises(ModelFileError, match="is not hyper-reduced: it is solved on its full mesh"):
        store.load_body(galerkin, None, scene.stepping)


PLATE = """title = "pulled plate"
[geometry]
builder = "rectangle"
cells = [8, 3]
lengths = [2.0, 1.0]
[material]
law = "neo_hookean"
E = 1.0e3
nu = 0.3
[formulation]
plane = "strain"
degree = 2
[[constraints]]
type = "clamp"
boundary = "x0"
[[loads]]
type = "traction"
boundary = "x1"
value = [0.0, -10.0]
name = "pull"
[parameters.pull]
target = "loads.pull.amplitude"
range = [0.5, 5.0]
[output]
fields = false
probes = [[2.0, 0.5]]
"""


@pytest.mark.slow
def test_a_plane_body_of_quadratic_elements_answers_as_its_full_mesh(tmp_path):
    """Triangles in plane strain, P2 (dofs on edges too): the body's answer is the full mesh's."""
    (tmp_path / "plate.toml").write_text(PLATE)
    scene = scenes.load(tmp_path / "plate.toml")
    reduce_app.build(scene, tmp_path / "p.npz", size=4, samples=3, hyper="ecsw", hyper_tolerance=1e-5)
    on_body, on_mesh = (reduce_app.load(tmp_path / "p.npz", fields=fields) for fields in (False, True))
    assert on_body.model.geometry.mesh.geometry.dim == 2 and on_body.describe()["dofs"] == 2 * 17 * 7
    a, b = on_body.solve({"pull": 3.0}), on_mesh.solve({"pull": 3.0})
    for name, value in _outputs(b).items():
        assert _outputs(a)[name] == pytest.approx(value, rel=1e-10, abs=1e-14), name


def test_a_file_that_kept_its_cells_apart_answers_the_same(built, tmp_path_factory):
    """A model file written before bodies shared nodes (each cell with nodes of its own:
    ``body/order`` alone) loads, cells apart, and answers as one with shared nodes."""
    comm = MPI.COMM_WORLD
    path = comm.bcast(str(tmp_path_factory.mktemp("apart") / "m.npz") if comm.rank == 0 else None)
    if comm.rank == 0:
        metadata, arrays = store.read(built / "m.npz")
        del arrays[body.PREFIX + "node_numbers"]
        metadata.pop("sha256")
        metadata["sha256"] = store.digest(metadata, arrays)
        np.savez(path, metadata=json.dumps(metadata), **arrays)
    comm.barrier()
    apart, shared = reduce_app.load(path), reduce_app.load(built / "m.npz")
    mesh = apart.model.geometry.mesh
    cells = mesh.comm.allreduce(mesh.topology.index_map(3).size_local, op=MPI.SUM)
    assert (
        mesh.geometry.index_map().size_global == 4 * cells > shared.model.geometry.mesh.geometry.index_map().size_global
    )
    a, b = apart.solve(POINT), shared.solve(POINT)
    for name, value in _outputs(b).items():
        assert _outputs(a)[name] == pytest.approx(value, rel=1e-10, abs=1e-14), name
    assert a.indicator == pytest.approx(b.indicator, rel=1e-8)
