"""Scenes and the command line: bad input gives one clear message and a non-zero exit."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fem import TINY_SCENE

from lungmech.app import scene as scenes
from lungmech.app.cli import main
from lungmech.app.run import run
from lungmech.errors import SceneError

pytestmark = (
    pytest.mark.serial
)  # the command line's printed lines, read by capsys (rank 0 prints); runs under MPI: tests/test_mpi.py

TINY = TINY_SCENE


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return path


GRAVITY = """
[[loads]]
type = "gravity"
density = 1.0
acceleration = [0.0, 0.0, -9.81]
"""


BAD = {
    "unknown law": (TINY.replace('"neo_hookean"', '"rubber"'), "material.law: unknown law 'rubber'"),
    "nu too large": (TINY.replace("nu = 0.3", "nu = 0.5"), "-1 < nu < 0.5"),
    "E not positive": (TINY.replace("E = 1.0e3", "E = -1.0"), "E must be > 0"),
    "unknown key": (TINY.replace("nu = 0.3", "nu = 0.3\nnuu = 0.2"), "material.nuu: unknown key"),
    "missing mesh file": (
        TINY.replace('builder = "box"\ncells = [2, 1, 1]\nlengths = [2.0, 1.0, 1.0]', 'file = "nowhere.msh"'),
        "nowhere.msh' not found",
    ),
    "unknown boundary": (TINY.replace('boundary = "x0"', 'boundary = "hilum"'), "unknown boundary 'hilum'"),
    "unknown section": (TINY + "\n[physics]\ngravity = 1\n", "scene.physics: unknown key"),
    "bad load type": (TINY.replace('type = "traction"', 'type = "wind"'), "loads[0].type: unknown type 'wind'"),
    "incompressible without mixed": (
        TINY.replace("E = 1.0e3\nnu = 0.3", "incompressible = true\nmu = 1.0"),
        "needs the mixed formulation",
    ),
    "bad ramp": (
        TINY.replace("value = [0.0, 0.0, -10.0]", "value = [0.0, 0.0, -10.0]\nramp = { times = [0, 1], values = [0] }"),
        "loads[0].ramp",
    ),
    "not toml": ("[geometry\nbuilder = 1", "not valid TOML"),
    "inverse tolerance": (TINY + "[inverse]\ntolerance = 2.0\n", "inverse: tolerance must lie in (0, 1)"),
    "inverse unknown key": (TINY + "[inverse]\ntol = 1e-6\n", "inverse.tol: unknown key"),
    "formula with an unknown name": (
        TINY.replace("value = [0.0, 0.0, -10.0]", 'value = [0.0, 0.0, "-10 * w"]'),
        "loads[0]: value[2]: unknown name 'w' in '-10 * w' (known: x, y, z, t, pi, e)",
    ),
    "force given by a formula": (
        TINY.replace('type = "traction"', 'type = "force"').replace(
            "value = [0.0, 0.0, -10.0]", 'value = [0.0, 0.0, "t"]'
        ),
        "loads[0]: value[2] must be a number",
    ),
    "gravity in 2-D": (
        TINY + GRAVITY.replace("[0.0, 0.0, -9.81]", "[0.0, -9.81]"),
        "load 'gravity': its value has 2 components, the mesh is 3-D",
    ),
}


@pytest.mark.parametrize("case", BAD)
def test_bad_scene_gives_one_clear_error(case, tmp_path, capsys):
    text, message = BAD[case]
    code = main(["run", str(write(tmp_path, text)), "-o", str(tmp_path / "out"), "-q"])
    err = capsys.readouterr().err
    assert code == 2
    assert message in err, err
    assert "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_missing_scene_file(tmp_path, capsys):
    assert main(["run", str(tmp_path / "none.toml")]) == 2
    assert "scene file" in capsys.readouterr().err


def test_run_writes_outputs(tmp_path):
    summary = run(scenes.load(write(tmp_path, TINY)), tmp_path / "out")
    written = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert written == json.loads(json.dumps(summary))
    assert summary["steps"] >= 1 and summary["newton_iterations"] >= summary["steps"]
    assert (tmp_path / "out" / "history.csv").read_text().startswith("time [s],volume [m^3],strain_energy [J]")


PLANE_STRAIN = (
    TINY.replace(
        'builder = "box"\ncells = [2, 1, 1]\nlengths = [2.0, 1.0, 1.0]',
        'builder = "rectangle"\ncells = [2, 1]\nlengths = [2.0, 1.0]',
    )
    .replace("value = [0.0, 0.0, -10.0]", "value = [0.0, -10.0]")
    .replace("[[constraints]]", '[formulation]\nplane = "strain"\n[[constraints]]')
    .replace("fields = false", "fields = true\nprobes = [[2.0, 1.0]]")
)


def test_a_two_dimensional_scene_reports_per_metre_of_thickness(tmp_path):
    summary = run(scenes.load(write(tmp_path, PLANE_STRAIN)), tmp_path / "out")
    assert summary["plane"] == "strain" and summary["units"]["deformed_volume"] == "m^3/m"
    assert summary["start_volume"] == pytest.approx(2.0)  # the 2 m × 1 m rectangle, per metre of thickness
    header = (tmp_path / "out" / "history.csv").read_text().splitlines()[0]
    assert header.startswith("time [s],volume [m^3/m],strain_energy [J/m]") and "probe0_uy [m]" in header
    assert "probe0_uz" not in header and (tmp_path / "out" / "fields_000001.vtu").is_file()
    assert (tmp_path / "out" / "deformed.png").is_file()  # seen from +z, y up


def test_the_colour_bar_shows_a_nearly_incompressible_body_s_spread_of_j():
    from lungmech.app.plot import _colour_format

    assert _colour_format(0.9998, 1.0007) % 0.9998 != _colour_format(0.9998, 1.0007) % 1.0007
    assert _colour_format(0.8, 1.6) == "%.3g"


def test_failed_run_keeps_previous_results(tmp_path):
    good = tmp_path / "out"
    run(scenes.load(write(tmp_path, TINY)), good)
    before = (good / "summary.json").read_text()
    impossible = TINY.replace("-10.0]", "-1.0e6]") + "\n[stepping]\ninitial_step = 0.5\nmin_step = 0.1\n"
    assert main(["run", str(write(tmp_path, impossible)), "-o", str(good), "-q"]) == 2
    assert (good / "summary.json").read_text() == before
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".out")] == []


def _built(text: str):
    """The model a scene builds, and what its residual integrates over: {(type, subdomain)}."""
    from lungmech.app.run import build_model

    model = build_model(scenes.parse(scenes.tomllib.loads(text)))
    domains = {(i.integral_type(), i.subdomain_id()) for i in model.residual.integrals()}
    return model, domains


def test_only_declared_physics_is_built():
    model, domains = _built(TINY)
    x1 = model.geometry.tag("x1")
    # A pure-displacement box: one unknown field, the volume and the loaded face, nothing else.
    assert list(model.fields) == ["u"] and not model.multi_field and not model.state_dependent
    assert domains == {("cell", "everywhere"), ("exterior_facet", x1)}
    assert len(model.loads) == 1 and model.constraints[0].boundary == "x0"

    # Gravity declared: its potential joins the volume integral; no pressure unless balanced_on.
    model, domains = _built(TINY + GRAVITY)
    assert domains == {("cell", "everywhere"), ("exterior_facet", x1)} and not model.state_dependent
    balanced = GRAVITY + 'balanced_on = ["x1", "y0", "y1", "z0", "z1"]\n'
    model, domains = _built(TINY + balanced)
    assert len(model.state_dependent) == 1
    assert domains == {("cell", "everywhere")} | {
        ("exterior_facet", model.geometry.tag(b)) for b in ("x1", "y0", "y1", "z0", "z1")
    }

    # The lung model adds exactly one field (Φs), and no porosity barrier unless asked for.
    lung = TINY.replace(
        'law = "neo_hookean"\nE = 1.0e3\nnu = 0.3',
        'law = "lung_skeleton"\nalpha = 1.0\ngamma = 0.5\nc1 = 1.0\nc2 = 1.0',
    )
    lung += '[formulation]\ntype = "poromechanics"\nkappa = 100.0\nphi_s0 = 0.3\n'
    model, _ = _built(lung)
    assert list(model.fields) == ["u", "phi_s"]
    assert "conditional" not in repr(model.energy_density).lower()
    model, _ = _built(lung + "pore_barrier = 1.0\n")
    assert "conditional" in repr(model.energy_density).lower()


LUNG_CUBE = """
title = "lung cube imaged at 0.5 Pa"
[geometry]
builder = "box"
cells = [2, 2, 2]
[material]
law = "lung_skeleton"
alpha = 0.16
gamma = 0.5
c1 = 0.2
c2 = 0.4
[formulation]
type = "poromechanics"
kappa = 100.0
scaling = "linear"
imaged_porosity = "porosity.txt"
[[constraints]]
type = "symmetry"
boundary = "x0"
component = "x"
[[constraints]]
type = "symmetry"
boundary = "y0"
component = "y"
[[constraints]]
type = "symmetry"
boundary = "z0"
component = "z"
[[loads]]
type = "alveolar_pressure"
value = 0.5
ramp = {times = [0.0, 1.0, 2.0], values = [1.0, 1.2, 1.0]}
[stepping]
end = 2.0
[inverse]
tolerance = 1e-10
"""


def test_a_lung_imaged_with_its_porosity_is_unloaded_then_breathes(tmp_path):
    """[inverse] with imaged_porosity from a file (one value per cell): the reference and Φs0
    are found together, and the breath starts from the imaged state and porosity."""
    values = np.linspace(0.6, 0.8, 48)  # 2 × 2 × 2 hexahedra of 6 tetrahedra
    np.savetxt(tmp_path / "porosity.txt", values)
    summary = run(scenes.load(write(tmp_path, LUNG_CUBE)), tmp_path / "out")
    inverse = summary["inverse"]
    assert inverse["porosity_mismatch"][-1] <= 1e-10
    assert inverse["iterations"] <= 15
    assert summary["start_volume"] == pytest.approx(1.0, rel=1e-9)  # the imaged cube
    assert inverse["reference_volume"] < 0.95
    # The reference it found is a mesh file every tool opens, and a scene's [geometry] file.
    import meshio

    from lungmech.mesh import from_file

    reference = tmp_path / "out" / "reference.vtu"
    assert {"x0", "x1"} <= set(meshio.read(reference).field_data)
    assert from_file(reference).volume() == pytest.approx(inverse["reference_volume"], rel=1e-9)


def test_loads_as_formulas_force_and_dead_pressure_from_a_scene(tmp_path):
    """A traction formula of x and t equals its numbers at the probe's end state; a total force
    and a dead normal pressure run from a scene."""
    formula = TINY.replace(
        "value = [0.0, 0.0, -10.0]",
        'value = [0.0, 0.0, "-10 * t * (1 + 0 * x)"]\nramp = {times = [0.0], values = [1.0]}',
    )
    by_formula = run(scenes.load(write(tmp_path, formula)), tmp_path / "a")
    by_numbers = run(scenes.load(write(tmp_path, TINY)), tmp_path / "b")
    assert by_formula["deformed_volume"] == pytest.approx(by_numbers["deformed_volume"], rel=1e-12)
    assert by_formula["strain_energy"] == pytest.approx(by_numbers["strain_energy"], rel=1e-10)
    others = TINY.replace(
        'type = "traction"\nboundary = "x1"\nvalue = [0.0, 0.0, -10.0]',
        'type = "force"\nboundary = "x1"\nvalue = [0.0, 0.0, -10.0]',
    )
    others += '[[loads]]\ntype = "normal_pressure"\nboundary = "x1"\nvalue = "100 * y"\n'
    summary = run(scenes.load(write(tmp_path, others)), tmp_path / "c")
    assert summary["steps"] >= 1


def test_every_bundled_scene_parses():
    from importlib import resources

    for path in resources.files("lungmech.scenes").iterdir():
        if path.name.endswith(".toml"):
            scenes.load(path)


def test_the_parameter_scene_is_the_breathing_scene_over_three_parameters():
    """lung_breathing_parameters is lung_breathing with its loads named and a [parameters]
    table, nothing else (the two files cannot drift apart)."""
    import tomllib

    from lungmech.scenes import bundled, names

    assert {"lung_breathing", "lung_breathing_parameters"} <= set(names())
    breathing, over = (
        tomllib.loads(bundled(n).read_text()) for n in ("lung_breathing", "lung_breathing_parameters.toml")
    )
    assert sorted(over.pop("parameters")) == ["breath", "posture", "stiffness"]
    assert [load.pop("name") for load in over["loads"]] == ["pleural", "gravity"]
    assert over.pop("title").startswith(breathing.pop("title").split(" (")[0])
    assert over == breathing
    assert bundled("no_such_scene") is None


@pytest.mark.slow
def test_a_bundled_scene_is_named_without_a_path(tmp_path, monkeypatch, capsys):
    """A command names a bundled scene by its name; a file of that name in the folder is the
    user's and comes first; a name that is neither is refused in one line listing the bundled."""
    monkeypatch.chdir(tmp_path)
    assert main(["run", "lung_breathing_parameters", "--at", "0", "-o", "bundled", "-q"]) == 0
    summary = json.loads((tmp_path / "bundled" / "summary.json").read_text())
    assert "stiffness" in summary["parameters"]
    (tmp_path / "lung_breathing_parameters").write_text(TINY)
    assert main(["run", "lung_breathing_parameters", "-o", "mine", "-q"]) == 0
    assert "stiffness" not in json.loads((tmp_path / "mine" / "summary.json").read_text()).get("parameters", {})
    capsys.readouterr()
    assert main(["run", "lung_breathing_parameter", "-o", "none"]) != 0
    said = capsys.readouterr()
    line = (said.out + said.err).strip()
    assert line.count("\n") == 0 and "'lung_breathing_parameter' not found" in line
    assert "lung_breathing_parameters" in line and not (tmp_path / "none").exists()


def test_scene_error_names_nested_key():
    with pytest.raises(SceneError, match=r"material.terms\[1\].law"):
        scenes.material({"law": "sum", "terms": [{"law": "ciarlet_geymonat", "c0": 1.0}, {"law": "x"}]})


def test_cli_subprocess_exit_code_and_info(tmp_path):
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    bad = write(tmp_path, TINY.replace("nu = 0.3", "nu = 0.7"))
    result = subprocess.run(
        [sys.executable, "-m", "lungmech.app.cli", "run", str(bad)], capture_output=True, text=True, env=env
    )
    assert result.returncode == 2
    assert result.stderr.strip().startswith("lungmech: error:") and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    info = subprocess.run([sys.executable, "-m", "lungmech.app.cli", "info"], capture_output=True, text=True, env=env)
    assert info.returncode == 0 and "DOLFINx 0.11" in info.stdout and "neo_hookean" in info.stdout


def test_hyper_reduced_model_from_the_command_line(tmp_path, capsys):
    """rom build --hyper ecsw → rom solve at an unseen load scale: the full run's outputs within
    the basis' and τ's error, the same files; the build says what it sampled."""
    tiny = TINY.replace("cells = [2, 1, 1]", "cells = [8, 4, 4]").replace(
        "fields = false", "fields = false\nprobes = [[2.0, 1.0, 1.0]]"
    )
    scene = write(tmp_path, tiny)
    model = tmp_path / "tiny.npz"
    args = ["--scales", "0.5,1.5", "--size", "8", "--hyper", "ecsw", "--ecsw-tolerance", "1e-5", "-q"]
    assert main(["rom", "build", str(scene), "-o", str(model), *args]) == 0
    built = capsys.readouterr().out
    assert "hyper-reduced by ECSW at τ = 1e-05 on" in built and "of the mesh's 768" in built
    assert main(["rom", "solve", str(model), "-o", str(tmp_path / "reduced"), "--scale", "1.2", "-q", "--fields"]) == 0
    assert main(["run", str(scene), "-o", str(tmp_path / "full"), "--scale", "1.2", "-q"]) == 0
    reduced, full = (json.loads((tmp_path / name / "summary.json").read_text()) for name in ("reduced", "full"))
    assert reduced["solver"].startswith("hyper-reduced (ECSW, τ = 1e-05): pod basis of")
    assert reduced["deformed_volume"] == pytest.approx(full["deformed_volume"], rel=1e-5)
    tip, exact = (np.array(summary["probes"]["displacement"]) for summary in (reduced, full))
    assert np.abs(tip - exact).max() <= 1e-3 * np.abs(exact).max()
    assert sorted(os.listdir(tmp_path / "reduced")) == sorted(os.listdir(tmp_path / "full"))


@pytest.mark.slow
def test_reduced_model_from_the_command_line(tmp_path, capsys):
    """rom build → rom solve at an unseen load scale = the full run at that scale; same outputs."""
    scene = write(tmp_path, TINY.replace("cells = [2, 1, 1]", "cells = [4, 2, 2]"))
    model = tmp_path / "tiny.npz"
    args = ["--scales", "0.5,1.5", "--size", "8", "-q"]
    assert main(["rom", "build", str(scene), "-o", str(model), *args]) == 0
    assert main(["rom", "solve", str(model), "-o", str(tmp_path / "reduced"), "--scale", "1.2", "-q", "--fields"]) == 0
    assert main(["run", str(scene), "-o", str(tmp_path / "full"), "--scale", "1.2", "-q"]) == 0
    reduced, full = (json.loads((tmp_path / name / "summary.json").read_text()) for name in ("reduced", "full"))
    assert reduced["solver"].startswith("reduced Galerkin: pod") and full["solver"] == "full order"
    assert reduced["deformed_volume"] == pytest.approx(full["deformed_volume"], rel=1e-8)
    assert reduced["probes"] == full["probes"] and reduced["load_scale"] == 1.2
    assert sorted(os.listdir(tmp_path / "reduced")) == sorted(os.listdir(tmp_path / "full"))
    assert (
        main(["rom", "build", str(scene), "-o", str(tmp_path / "modal.npz"), "--basis", "modal", "--size", "4", "-q"])
        == 0
    )
    capsys.readouterr()
    assert main(["rom", "solve", str(model), "-o", str(tmp_path / "deep"), "--scale", "2.5", "-q"]) == 0
    assert "lies outside the trained range [[0.5], [1.5]]: the reduced model extrapolates" in capsys.readouterr().out
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:  # default outputs: the full and the reduced run of one scene do not share a folder
        assert main(["run", str(scene), "-q"]) == main(["rom", "solve", str(model), "-q"]) == 0
    finally:
        os.chdir(cwd)
    assert (tmp_path / "results" / "scene" / "summary.json").is_file()
    assert (tmp_path / "results" / "tiny-reduced" / "summary.json").is_file()
    capsys.readouterr()

    other = tmp_path / "other" / "scene.toml"
    other.parent.mkdir()
    other.write_text(TINY)
    errors = {
        (
            "rom",
            "solve",
            str(model),
            str(other),
            "-o",
            str(tmp_path / "x"),
        ): "other physics than this scene's: geometry.cells",
        ("rom", "solve", str(tmp_path / "none.npz"), "-o", str(tmp_path / "x")): "not found",
        ("rom", "build", str(scene), "-o", str(tmp_path / "y.npz"), "--basis", "wavelet"): "basis kind must be",
        (
            "rom",
            "build",
            str(scene),
            "-o",
            str(tmp_path / "y.npz"),
            "--scales",
            "1:2",
        ): "one finite factor or one per load",
        ("run", str(scene), "-o", str(tmp_path / "x"), "--scale", "1,2"): "--scale takes one value",
    }
    for command, message in errors.items():
        assert main(list(command)) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y.npz").exists()
