"""Named parameters: ranges, what they act on, regions and interfaces, and no recompilation."""

from mpi4py import MPI

import dolfinx.jit
import numpy as np
import pytest
from fem import write_once

from lungmech.errors import ParameterError, SceneError
from lungmech.fem import FollowerPressure, Model, NeoHookean, NewtonSolver, Stepping, clamp, deformed_volume, solve
from lungmech.fem.binding import posture
from lungmech.fem.constraints import Displacement
from lungmech.fem.parameters import Cells, HalfSpace, Parameter, Parameters
from lungmech.mesh import box


def block(parameters, law=None, **kwargs):
    return Model(
        box(MPI.COMM_SELF, cells=(3, 2, 2)),
        law or (lambda c: NeoHookean.from_young(c["E"], 0.3)),
        constraints=[clamp("x0")],
        loads=[FollowerPressure("x1", 0.5, name="push")],
        parameters=parameters,
        **kwargs,
    )


def volume_at(model, **values):
    model.reset()
    model.set_parameters(values)
    solve(model, Stepping())
    return deformed_volume(model)()


STIFFNESS = Parameter("E", "material.E", 10.0, (5.0, 20.0), log=True, unit="Pa")


def test_a_parameter_is_the_law_built_at_its_value():
    """Setting E = 15 on a model built at E = 10 gives the model built at E = 15."""
    swept = block([STIFFNESS])
    built = block([Parameter("E", "material.E", 15.0, (5.0, 20.0))])
    assert volume_at(swept, E=15.0) == pytest.approx(volume_at(built), rel=1e-12)


def test_a_sweep_compiles_nothing(monkeypatch):
    """Nine points of stiffness × pressure after the first solve: no FFCx compilation."""
    model = block([STIFFNESS, Parameter("p", "loads.push.value", 0.5, (0.1, 1.0), unit="Pa")])
    solver, volume = NewtonSolver(model), deformed_volume(model)
    calls = []
    original = dolfinx.jit.ffcx_jit
    monkeypatch.setattr(dolfinx.jit, "ffcx_jit", lambda *a, **k: calls.append(1) or original(*a, **k))

    def at(E, p):
        model.reset()
        model.set_parameters(E=E, p=p)
        solve(model, Stepping(), solver=solver)
        return volume()

    volumes = {(E, p): at(E, p) for E in (5.0, 10.0, 20.0) for p in (0.1, 0.5, 1.0)}
    assert calls == []
    # The law is homogeneous of degree 1 in E: the answer depends on p/E only, and on nothing else.
    assert volumes[5.0, 0.5] == pytest.approx(volumes[10.0, 1.0], rel=1e-9)
    assert volumes[10.0, 0.5] == pytest.approx(volumes[20.0, 1.0], rel=1e-9)
    assert len({round(v, 9) for v in volumes.values()}) == 7


def test_out_of_range_and_unknown_names_are_refused_with_the_range():
    model = block([STIFFNESS])
    with pytest.raises(ParameterError, match=r"'E' = 30 Pa is outside its range \[5, 20\] Pa"):
        model.set_parameters(E=30.0)
    with pytest.raises(ParameterError, match="unknown parameter 'G'"):
        model.set_parameters(G=1.0)
    with pytest.raises(ParameterError, match="log scale needs a positive range"):
        Parameter("E", "material.E", 1.0, (0.0, 2.0), log=True)
    with pytest.raises(ParameterError, match="no load named 'pull'"):
        block([Parameter("q", "loads.pull.value", 1.0, (0.0, 2.0))], law=NeoHookean.from_young(10.0, 0.3))


def test_a_plain_law_is_parametrised_by_its_own_constants():
    law = NeoHookean.from_young(10.0, 0.3)
    model = block([Parameter("mu", "material.mu", law.mu, (1.0, 10.0))], law=law)
    model.set_parameters(mu=2.0)
    assert float(model.material.mu.value) == 2.0


@pytest.mark.slow
def test_a_region_covering_the_body_is_the_global_value():
    """A half-space that holds the whole block acts as the global parameter; one that holds none
    is refused, since its parameter would act nowhere."""
    everywhere = HalfSpace((1.0, 0.0, 0.0), 10.0, 0.01)
    nowhere = HalfSpace((1.0, 0.0, 0.0), -10.0, 0.01)
    reference = volume_at(block([STIFFNESS]), E=6.0)
    inside = volume_at(
        block([STIFFNESS, Parameter("soft", "material.E", 10.0, (1.0, 20.0), region=everywhere)]), soft=6.0
    )
    assert inside == pytest.approx(reference, rel=1e-10)
    with pytest.raises(ParameterError, match="holds no cell of the mesh, so they would act nowhere"):
        block([STIFFNESS, Parameter("soft", "material.E", 10.0, (1.0, 20.0), region=nowhere)])


def test_a_global_and_a_regional_parameter_share_a_target_by_design():
    """The global parameter is the value outside the region: the block's volume moves with it,
    and a regional 'outside', which it would override, is refused."""
    half = HalfSpace((1.0, 0.0, 0.0), 0.5, 0.01)
    model = block([STIFFNESS, Parameter("soft", "material.E", 10.0, (1.0, 20.0), region=half)])
    assert volume_at(model, soft=4.0, E=6.0) != pytest.approx(volume_at(model, soft=4.0, E=12.0), rel=1e-6)
    with pytest.raises(ParameterError, match="its value outside the region would be ignored: parameter 'E'"):
        Parameters([STIFFNESS, Parameter("soft", "material.E", 10.0, (1.0, 20.0), region=half, outside=8.0)])
    with pytest.raises(ParameterError, match="parameters 'E' and 'F' all set material.E"):
        Parameters([STIFFNESS, Parameter("F", "material.E", 10.0, (1.0, 20.0))])


def test_a_moving_interface_changes_the_answer_smoothly():
    soft = Parameter("soft", "material.E", 10.0, (1.0, 20.0), region=HalfSpace((1.0, 0.0, 0.0), "cut", 0.05))
    model = block([STIFFNESS, soft, Parameter("cut", "interface", 0.5, (0.2, 0.8), unit="m")])
    volumes = [volume_at(model, soft=2.0, cut=c) for c in (0.3, 0.4, 0.5)]
    assert volumes[0] > volumes[1] > volumes[2]  # the soft part (x < cut) grows: the pressed block shrinks more
    steps = np.diff(volumes)
    assert abs(steps[1] - steps[0]) < 0.5 * abs(steps[0])  # smooth, not a jump


def test_a_cell_region_needs_cells():
    with pytest.raises(ParameterError, match="no cell tags"):
        block([Parameter("soft", "material.E", 10.0, (1.0, 20.0), region=Cells(tag=3))])


def test_posture_turns_gravity():
    g = np.array([0.0, 0.0, -9.81])
    assert posture(-90.0, 0.0) @ g == pytest.approx([0.0, -9.81, 0.0], abs=1e-12)  # supine: towards the back
    assert posture(0.0, 90.0) @ g == pytest.approx([-9.81, 0.0, 0.0], abs=1e-12)  # on the left side


def test_a_plane_problems_gravity_turns_in_its_plane_by_its_angle():
    """``loads.<name>.angle``: g = (0, −g) turned counter-clockwise by θ is g (sin θ, −cos θ), the
    weight's constant as the model sets it; pitch and roll are refused in a plane problem, and
    the angle in 3-D, in one line each."""
    from lungmech.lung.gravity import Gravity
    from lungmech.mesh.structured import rectangle

    weight = Gravity(2.0, (0.0, -9.81), name="g")
    plate = Model(
        rectangle(MPI.COMM_SELF, cells=(2, 2)),
        NeoHookean.from_young(10.0, 0.3),
        constraints=[clamp("y0")],
        loads=[weight],
        parameters=[Parameter("theta", "loads.g.angle", 0.0, (0.0, 360.0))],
        plane="strain",
    )
    for theta in (0.0, 30.0, 90.0, 215.0):
        plate.set_parameters(theta=theta)
        plate.set_time(1.0)
        expected = 9.81 * np.array([np.sin(np.radians(theta)), -np.cos(np.radians(theta))])
        assert plate.loads[0].acceleration == pytest.approx(expected, abs=1e-12)
    with pytest.raises(ParameterError, match="pitch turns a 3-D problem's gravity, and load 'g' has 2 components"):
        Model(
            rectangle(MPI.COMM_SELF, cells=(1, 1)),
            NeoHookean.from_young(10.0, 0.3),
            loads=[weight],
            parameters=[Parameter("p", "loads.g.pitch", 0.0, (0.0, 90.0))],
            plane="strain",
        )
    with pytest.raises(ParameterError, match="angle turns a plane problem's gravity, and load 'g' has 3"):
        Model(
            box(MPI.COMM_SELF, cells=(1, 1, 1)),
            NeoHookean.from_young(10.0, 0.3),
            loads=[Gravity(2.0, (0.0, 0.0, -9.81), name="g")],
            parameters=[Parameter("p", "loads.g.angle", 0.0, (0.0, 90.0))],
        )


def test_an_imposed_displacement_has_an_amplitude():
    pulled = Model(
        box(MPI.COMM_SELF, cells=(2, 2, 2)),
        NeoHookean.from_young(10.0, 0.3),
        constraints=[clamp("x0"), Displacement("x1", 0.1, component=0, name="pull")],
        parameters=[Parameter("a", "constraints.pull.amplitude", 1.0, (0.0, 2.0))],
    )
    pulled.set_parameters(a=0.5)
    solve(pulled, Stepping())
    assert deformed_volume(pulled)() > 1.0  # stretched along x by 0.05
    assert pulled._imposed[1].target.x.array.max() == pytest.approx(0.05)


def test_samples_fill_the_box_and_repeat():
    space = Parameters([STIFFNESS, Parameter("p", "loads.push.value", 0.5, (0.0, 1.0))])
    first, again = space.sample(16, seed=3), space.sample(16, seed=3)
    assert first == again
    E = np.array([s["E"] for s in first])
    assert E.min() >= 5.0 and E.max() <= 20.0
    assert np.median(np.log(E)) == pytest.approx(np.log(10.0), abs=0.2)  # spread in log E
    assert space.to_unit(space.from_unit(np.array([0.25, 0.75]))) == pytest.approx([0.25, 0.75])


SCENE = """
[geometry]
builder = "box"
cells = [2, 2, 2]
[material]
law = "neo_hookean"
E = 10.0
nu = 0.3
[[constraints]]
type = "clamp"
boundary = "x0"
[[loads]]
type = "follower_pressure"
boundary = "x1"
value = 1.0
name = "push"
[parameters.stiffness]
target = "material.E"
range = [5.0, 20.0]
"""


def test_a_scene_declares_parameters_and_set_checks_them():
    import tomllib

    from lungmech.app import scene as scenes

    scene = scenes.parse(tomllib.loads(SCENE))
    assert scene.parameters[0].default == 10.0 and scene.parameters[0].unit == "Pa"
    assert scene.with_values({"stiffness": 12.0}).values == {"stiffness": 12.0}
    with pytest.raises(ParameterError, match="outside its range"):
        scene.with_values({"stiffness": 50.0})
    bad = tomllib.loads(SCENE.replace('target = "material.E"', 'target = "material.E"\nspeed = 1'))
    with pytest.raises(SceneError, match="parameters.stiffness.speed: unknown key"):
        scenes.parse(bad)
    amplitude = SCENE.replace('"material.E"', '"loads.push.amplitude"').replace("[5.0, 20.0]", "[0.5, 2.0]")
    assert scenes.parse(tomllib.loads(amplitude)).parameters[0].default == 1.0  # the scene's own value


def test_an_image_region_marks_the_cells_of_its_label(tmp_path):
    """A label image (NIfTI, metres) whose label 1 fills x < 0.5 marks exactly the cells there."""
    import tomllib

    import nibabel

    from lungmech.app import scene as scenes

    labels = np.ones((20, 10, 10), dtype=np.int16)
    labels[10:] = 2
    affine = np.diag([0.05, 0.1, 0.1, 1.0])
    affine[:3, 3] = [0.025, 0.05, 0.05]  # voxel centres; the label boundary is the plane x = 0.5
    image = nibabel.Nifti1Image(labels, affine)
    image.header.set_xyzt_units("meter")
    if MPI.COMM_WORLD.rank == 0:
        nibabel.save(image, tmp_path / "zones.nii.gz")
    MPI.COMM_WORLD.Barrier()
    table = tomllib.loads(SCENE.replace("[2, 2, 2]", "[4, 2, 2]"))
    table["parameters"]["soft"] = {
        "target": "material.E",
        "range": [1.0, 20.0],
        "region": {"image": "zones.nii.gz", "label": 1},
    }
    scene = scenes.parse(table, folder=tmp_path)
    assert tmp_path / "zones.nii.gz" in scene.inputs
    geometry = scenes.build_geometry(scene.geometry, MPI.COMM_SELF)
    marked = scene.parameters[1].region.marker(geometry)
    mesh = geometry.mesh
    midpoints = mesh.geometry.x[mesh.geometry.dofmaps[0]].mean(axis=1)
    assert marked.any() and np.array_equal(marked, midpoints[:, 0] < 0.5)
    missing = tomllib.loads(SCENE)
    missing["parameters"]["soft"] = {
        "target": "material.E",
        "range": [1.0, 20.0],
        "region": {"image": "no.nii", "label": 1},
    }
    with pytest.raises(SceneError, match="no.nii' not found"):
        scenes.parse(missing, folder=tmp_path)


@pytest.mark.slow
def test_a_sweep_through_set_compiles_once(tmp_path):
    """Three 'lungmech run --set' processes sharing a fresh FFCx cache: only the first one adds
    compiled forms; the answers differ (the values reached the forms)."""
    import json
    import os
    import subprocess
    import sys

    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE + "[output]\nfields = false\n")
    env = {**os.environ, "PYTHONWARNINGS": "ignore", "XDG_CACHE_HOME": str(tmp_path / "cache")}
    compiled, volumes = [], []
    for E in (6.0, 12.0, 18.0):
        out = tmp_path / f"E{E:g}"
        command = [sys.executable, "-m", "lungmech.app.cli", "run", str(scene), "-q", "-o", str(out)]
        subprocess.run([*command, "--set", f"stiffness={E}"], check=True, env=env, capture_output=True)
        compiled.append(sum(1 for _ in (tmp_path / "cache").rglob("*.so")))
        volumes.append(json.loads((out / "summary.json").read_text())["deformed_volume"])
    assert compiled[0] > 0 and compiled[1] == compiled[2] == compiled[0]
    assert len(set(volumes)) == 3


def test_new_parameters_keep_the_load_factor_and_its_reference_time():
    """set_parameters re-evaluates the loads at the current time with the last set_time's load
    factor and ``about``: changing a parameter on a scaled load path (an inner product assembled
    at the defaults and restored, say) does not move its loads back to the unscaled ones."""
    model = block(Parameters([STIFFNESS]))
    model.set_time(0.8, load_factor=2.5, about=0.2)
    scaled = model.scalar_loads()["push"]
    assert scaled == pytest.approx(0.5 * (0.2 + 2.5 * (0.8 - 0.2)))  # the ramp is t
    model.set_parameters(E=12.0)
    assert model.scalar_loads()["push"] == scaled
    model.set_time(0.8)
    assert model.scalar_loads()["push"] == pytest.approx(0.5 * 0.8)
    model.set_parameters(E=10.0)
    assert model.scalar_loads()["push"] == pytest.approx(0.5 * 0.8)


def test_a_sweep_file_may_start_with_a_byte_order_mark(tmp_path):
    """As spreadsheet programs write CSV: the mark is not part of the first column's name."""
    from lungmech.app.sweep import read_points

    path = tmp_path / "points.csv"
    write_once(path, "\ufeffE [Pa],p [Pa]\n6,0.2\n")
    box = Parameters([STIFFNESS, Parameter("p", "loads.push.value", 0.5, (0.1, 1.0), unit="Pa")])
    assert read_points(path, box, box.defaults) == [{"E": 6.0, "p": 0.2}]
