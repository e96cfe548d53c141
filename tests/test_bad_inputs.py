"""Every bad input gets one clear line naming the key or file, a non-zero exit, no traceback,
and nothing that existed before is lost or changed.

Each case runs the command line in a workspace holding the user's files: a scene, notes, a
folder of their own, a result lungmech wrote earlier, meshes, images and a reduced model. The
check is the same for all: exit code 2, one line on standard error that starts with
``lungmech: error:`` and says what is wrong, nothing on standard error that looks like a
traceback, every file of the workspace unchanged (same bytes), and no staging folder left.

On one rank only (``serial``): each case builds and compares a workspace of files, which is one
process's work. The refusals under ``mpiexec -n 2`` (an output that is a file, ``-o .``, a bad
value, a folder of the user's, an interrupt) are tests/test_interrupts.py's.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import subprocess
import zipfile
from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest
from fem import TINY_SCENE

from lungmech import mesh as geometry
from lungmech import meshes
from lungmech.app.cli import main
from lungmech.rom import store

pytestmark = pytest.mark.serial
TINY = TINY_SCENE
LUNG = """title = "lung cube"
[geometry]
builder = "box"
cells = [2, 2, 2]
[material]
law = "lung_skeleton"
alpha = 160.0
gamma = 0.5
c1 = 200.0
c2 = 400.0
[formulation]
type = "poromechanics"
kappa = 1.0e4
phi_s0 = 0.3
[[constraints]]
type = "clamp"
boundary = "x0"
[[loads]]
type = "follower_pressure"
boundary = ["x1", "y0", "y1", "z0", "z1"]
value = -300.0
[output]
fields = false
"""
REFERENCE = str(meshes.reference("lung_phantom_right"))


def swap(old: str, new: str, base: str = TINY) -> str:
    assert old in base, old
    return base.replace(old, new, 1)


# (scene text, what the message must say). The scene is written to scene.toml and run into out/.
SCENES = {
    # 2-D bodies
    "2-D mesh without a plane": (
        swap(
            "value = [0.0, 0.0, -10.0]",
            "value = [0.0, -10.0]",
            swap('builder = "box"\ncells = [2, 1, 1]\nlengths = [2.0, 1.0, 1.0]', 'builder = "rectangle"'),
        ),
        "a 2-D mesh needs plane = 'strain' (a long body) or 'stress' (a thin plate) (got None; in a scene: [formulation] plane)",
    ),
    "unknown plane": (
        swap("[[constraints]]", '[formulation]\nplane = "diagonal"\n[[constraints]]'),
        "formulation.plane: 'strain' or 'stress'",
    ),
    "plane on a 3-D mesh": (
        swap("[[constraints]]", '[formulation]\nplane = "strain"\n[[constraints]]'),
        "plane = 'strain' is for 2-D meshes; this mesh is 3-D",
    ),
    # numbers where numbers belong
    "traction is a word": (
        swap("value = [0.0, 0.0, -10.0]", 'value = "abc"'),
        "loads[0]: value must be 2 or 3 numbers",
    ),
    "traction component is a word": (
        swap("[0.0, 0.0, -10.0]", '["a", 0.0, -10.0]'),
        "loads[0]: value[0]: unknown name 'a' in 'a' (known: x, y, z, t, pi, e)",
    ),
    "traction formula not a formula": (
        swap("[0.0, 0.0, -10.0]", '["10 kPa", 0.0, -10.0]'),
        "'10 kPa' is not a formula",
    ),
    "traction of 2 components": (
        swap("[0.0, 0.0, -10.0]", "[0.0, -10.0]"),
        "its value has 2 components, the mesh is 3-D",
    ),
    "traction of 4 components": (swap("[0.0, 0.0, -10.0]", "[0.0, 0.0, -10.0, 1.0]"), "value must be 2 or 3 numbers"),
    "traction is true": (swap("value = [0.0, 0.0, -10.0]", "value = true"), "value must be 2 or 3 numbers"),
    "pressure is a word": (
        swap(
            'type = "traction"\nboundary = "x1"\nvalue = [0.0, 0.0, -10.0]',
            'type = "follower_pressure"\nboundary = "x1"\nvalue = "abc"',
        ),
        "loads[0]: value: unknown name 'abc'",
    ),
    "pressure on no boundary": (
        swap(
            'type = "traction"\nboundary = "x1"\nvalue = [0.0, 0.0, -10.0]',
            'type = "follower_pressure"\nboundary = []\nvalue = 1.0',
        ),
        "boundary must be",
    ),
    "probes a word": (swap("fields = false", 'fields = false\nprobes = "abc"'), "probes must be a list of points"),
    "probe coordinate a word": (
        swap("fields = false", 'fields = false\nprobes = [["a", 0.0, 0.0]]'),
        "probes[0][0] must be a number",
    ),
    "probe of 2 coordinates": (
        swap("fields = false", "fields = false\nprobes = [[1.0, 0.5]]"),
        "probe points need 3 coordinates each on a 3-D mesh",
    ),
    "probes a table": (swap("fields = false", "fields = false\nprobes = { x = 1.0 }"), "probes must be a list"),
    "probe outside the body": (
        swap("fields = false", "fields = false\nprobes = [[9.0, 0.5, 0.5]]"),
        "probe point (9, 0.5, 0.5) lies outside the mesh",
    ),
    "E a word": (swap("E = 1.0e3", 'E = "1 kPa"'), "must be a number"),
    "nu nan": (swap("nu = 0.3", "nu = nan"), "material.nu: nan is not a value"),
    "E inf": (swap("E = 1.0e3", "E = inf"), "material.E: inf is not allowed"),
    "E negative": (swap("E = 1.0e3", "E = -1.0"), "E must be > 0"),
    "nu too large": (swap("nu = 0.3", "nu = 0.5"), "-1 < nu < 0.5"),
    "mu inf": (swap("E = 1.0e3\nnu = 0.3", "mu = inf\nlmbda = 1.0"), "material.mu: inf is not allowed"),
    "lambda a bool": (swap("E = 1.0e3\nnu = 0.3", "mu = 1.0\nlmbda = true"), "parameter 'lmbda' must be a number"),
    "unknown law": (swap('"neo_hookean"', '"rubber"'), "material.law: unknown law 'rubber'"),
    "unknown material key": (swap("nu = 0.3", "nu = 0.3\nnuu = 0.2"), "material.nuu: unknown key"),
    "incompressible without mixed": (
        swap("E = 1.0e3\nnu = 0.3", "incompressible = true\nmu = 1.0"),
        "needs the mixed formulation",
    ),
    "empty sum": (
        swap('law = "neo_hookean"\nE = 1.0e3\nnu = 0.3', 'law = "sum"\nterms = []'),
        "non-empty list of laws",
    ),
    "kappa inf": (swap("kappa = 1.0e4", "kappa = inf", LUNG), "formulation.kappa: inf is not allowed"),
    "kappa a missing file": (swap("kappa = 1.0e4", 'kappa = "abc"', LUNG), "formulation.kappa: file"),
    "kappa a list": (
        swap("kappa = 1.0e4", "kappa = [1.0, 2.0]", LUNG),
        "kappa must be a number or a file of cell values",
    ),
    "phi_s0 above one": (swap("phi_s0 = 0.3", "phi_s0 = 1.5", LUNG), "phi_s0 must lie in (0, 1)"),
    "phi_s0 nan": (swap("phi_s0 = 0.3", "phi_s0 = nan", LUNG), "formulation.phi_s0: nan is not a value"),
    "scaling unknown": (
        swap("phi_s0 = 0.3", 'phi_s0 = 0.3\nscaling = "yes"', LUNG),
        "scaling must be one of 'none', 'skeleton', 'linear' (got 'yes')",
    ),
    "pore exponent one": (
        swap("phi_s0 = 0.3", "phi_s0 = 0.3\npore_exponent = 1.0", LUNG),
        "pore_exponent must be > 1",
    ),
    "phi_s0 and imaged porosity": (
        swap("phi_s0 = 0.3", "phi_s0 = 0.3\nimaged_porosity = 0.7", LUNG) + "\n[inverse]\n",
        "needs exactly one of phi_s0 (the reference solid fraction) or imaged_porosity",
    ),
    "imaged porosity without an inverse problem": (
        swap("phi_s0 = 0.3", "imaged_porosity = 0.7", LUNG),
        "formulation.imaged_porosity: the porosity of an imaged lung needs [inverse]",
    ),
    "imaged porosity of one": (
        swap("phi_s0 = 0.3", "imaged_porosity = 1.0", LUNG) + "\n[inverse]\n",
        "imaged porosity imaged_porosity must lie in (0, 1) (got 1.0)",
    ),
    "pore_range of one number": (
        swap("phi_s0 = 0.3", "phi_s0 = 0.3\npore_range = [0.5]", LUNG),
        "pore_range must be two numbers",
    ),
    "pore barrier negative": (
        swap("phi_s0 = 0.3", "phi_s0 = 0.3\npore_barrier = -1.0", LUNG),
        "pore_barrier must be >= 0",
    ),
    "skeleton alpha negative": (
        swap("alpha = 160.0", "alpha = -1.0", LUNG),
        "material (law 'lung_skeleton'): alpha must be > 0",
    ),
    "skeleton gamma a word": (swap("gamma = 0.5", 'gamma = "abc"', LUNG), "gamma must be a number"),
    "skeleton without shear": (swap("c1 = 200.0\nc2 = 400.0", "c1 = 0.0\nc2 = 0.0", LUNG), "c1 + c2 must be > 0"),
    "skeleton missing keys": (
        swap("gamma = 0.5\nc1 = 200.0\nc2 = 400.0\n", "", LUNG),
        "material (law 'lung_skeleton'): missing key(s) gamma, c1, c2",
    ),
    "unknown formulation": (
        swap('type = "poromechanics"', 'type = "poro"', LUNG),
        "formulation.type: unknown type 'poro'",
    ),
    "degree a word": (TINY + '[formulation]\ndegree = "2"\n', "formulation.degree: expected int"),
    "degree zero": (TINY + "[formulation]\ndegree = 0\n", "degree must be an integer >= 1"),
    "mixed at degree one": (TINY + '[formulation]\ntype = "mixed"\n', "it needs degree >= 2"),
    "gravity density inf": (
        TINY + '[[loads]]\ntype = "gravity"\ndensity = inf\nacceleration = [0.0, 0.0, -9.81]\n',
        "loads[1].density: inf is not allowed",
    ),
    "gravity in 2-D": (
        TINY + '[[loads]]\ntype = "gravity"\ndensity = 1.0\nacceleration = [0.0, -9.81]\n',
        "load 'gravity': its value has 2 components, the mesh is 3-D",
    ),
    "gravity nan": (
        TINY + '[[loads]]\ntype = "gravity"\ndensity = 1.0\nacceleration = [0.0, 0.0, nan]\n',
        "loads[1].acceleration[2]: nan is not a value",
    ),
    "gravity unbalanceable": (
        TINY + '[[loads]]\ntype = "gravity"\ndensity = 1.0\nacceleration = [0.0, 0.0, -9.81]\nbalanced_on = ["x1"]\n',
        "no pressure on x1 can balance",
    ),
    "pressure nan": (swap("[0.0, 0.0, -10.0]", "[0.0, 0.0, nan]"), "loads[0].value[2]: nan is not a value"),
    "pressure -inf": (swap("[0.0, 0.0, -10.0]", "[0.0, 0.0, -inf]"), "loads[0].value[2]: -inf is not allowed"),
    "unknown load type": (swap('type = "traction"', 'type = "wind"'), "loads[0].type: unknown type 'wind'"),
    "unknown load key": (swap('boundary = "x1"', 'boundary = "x1"\npressure = 3.0'), "loads[0].pressure: unknown key"),
    "loads not a list": (
        swap('[[loads]]\ntype = "traction"\nboundary = "x1"\nvalue = [0.0, 0.0, -10.0]\n', "").replace(
            'title = "tiny"', 'title = "tiny"\nloads = 3'
        ),
        "loads: expected a list of tables",
    ),
    "empty ramp": (
        swap("value = [0.0, 0.0, -10.0]", "value = [0.0, 0.0, -10.0]\nramp = { times = [], values = [] }"),
        "at least one (time, value) point",
    ),
    "ramp time a word": (
        swap("value = [0.0, 0.0, -10.0]", 'value = [0.0, 0.0, -10.0]\nramp = { times = ["a"], values = [1.0] }'),
        "ramp times[0] must be a number",
    ),
    "ramp going back": (
        swap(
            "value = [0.0, 0.0, -10.0]", "value = [0.0, 0.0, -10.0]\nramp = { times = [1.0, 0.0], values = [0.0, 1.0] }"
        ),
        "ramp times must increase strictly",
    ),
    "ramp lengths differ": (
        swap("value = [0.0, 0.0, -10.0]", "value = [0.0, 0.0, -10.0]\nramp = { times = [0.0, 1.0], values = [0.0] }"),
        "as many times as values",
    ),
    "ramp not a table": (
        swap("value = [0.0, 0.0, -10.0]", "value = [0.0, 0.0, -10.0]\nramp = 3"),
        "loads[0].ramp: expected a table",
    ),
    "constraint component w": (
        swap('type = "clamp"\nboundary = "x0"', 'type = "displacement"\nboundary = "x0"\ncomponent = "w"'),
        "component must be 0, 1, 2 or x, y, z",
    ),
    "constraint value nan": (
        swap('type = "clamp"\nboundary = "x0"', 'type = "displacement"\nboundary = "x0"\nvalue = nan'),
        "constraints[0].value: nan is not a value",
    ),
    "constraint value of 2 components": (
        swap('type = "clamp"\nboundary = "x0"', 'type = "displacement"\nboundary = "x0"\nvalue = [1.0, 2.0]'),
        "imposed displacement on 'x0' needs 3 components",
    ),
    "unknown boundary": (swap('boundary = "x0"', 'boundary = "hilum"'), "unknown boundary 'hilum'"),
    "stepping end inf": (TINY + "[stepping]\nend = inf\n", "stepping.end: inf is not allowed"),
    "stepping start -inf": (TINY + "[stepping]\nstart = -inf\n", "stepping.start: -inf is not allowed"),
    "stepping end before start": (TINY + "[stepping]\nstart = 2.0\nend = 1.0\n", "end (1.0) must be after start (2.0)"),
    "output time after the end": (TINY + "[stepping]\ntimes = [1.5]\n", "times [1.5] lie outside (start, end]"),
    "output time before the start": (TINY + "[stepping]\ntimes = [-0.5]\n", "times [-0.5] lie outside (start, end]"),
    "output times not a list": (TINY + "[stepping]\ntimes = 0.5\n", "times must be a list of output times"),
    "output time nan": (TINY + "[stepping]\ntimes = [nan]\n", "stepping.times[0]: nan is not a value"),
    "initial step zero": (TINY + "[stepping]\ninitial_step = 0.0\n", "need 0 < min_step <= initial_step <= max_step"),
    "min step above initial": (TINY + "[stepping]\nmin_step = 0.5\ninitial_step = 0.1\n", "need 0 < min_step"),
    "growth below one": (TINY + "[stepping]\ngrowth = 0.5\n", "growth must be >= 1"),
    "growth inf": (TINY + "[stepping]\ngrowth = inf\n", "stepping.growth: inf is not allowed"),
    "easy iterations fractional": (TINY + "[stepping]\neasy_iterations = 1.5\n", "easy_iterations must be an integer"),
    "easy iterations nan": (TINY + "[stepping]\neasy_iterations = nan\n", "stepping.easy_iterations: nan"),
    "unknown stepping key": (TINY + "[stepping]\ndt = 0.1\n", "stepping.dt: unknown key"),
    "rtol zero": (TINY + "[solver]\nrtol = 0.0\n", "rtol must be > 0"),
    "atol inf": (TINY + "[solver]\natol = inf\n", "solver.atol: inf is not allowed"),
    "max iterations zero": (TINY + "[solver]\nmax_iterations = 0\n", "max_iterations must be >= 1"),
    "max iterations fractional": (TINY + "[solver]\nmax_iterations = 2.5\n", "max_iterations must be an integer"),
    "unknown line search": (TINY + '[solver]\nline_search = "fast"\n', "line_search must be"),
    "unknown linear solver": (TINY + '[solver]\nlinear_solver = "cg"\n', "linear_solver must be"),
    "iterative plane stress P2": (
        swap(
            "value = [0.0, 0.0, -10.0]",
            "value = [0.0, -10.0]",
            swap('builder = "box"\ncells = [2, 1, 1]\nlengths = [2.0, 1.0, 1.0]', 'builder = "rectangle"'),
        )
        + '[formulation]\nplane = "stress"\ndegree = 2\n[solver]\nlinear_solver = "iterative"\n',
        "the iterative linear solver has no preconditioner for the fields u, thickness_stretch yet",
    ),
    "petsc options a word": (TINY + '[solver]\npetsc_options = "fast"\n', "petsc_options must be a table"),
    "petsc option a table": (
        TINY + "[solver]\npetsc_options = { snes_type = { a = 1 } }\n",
        "petsc_options.snes_type: expected a string, number or boolean",
    ),
    "unknown SNES type": (
        TINY + '[solver]\npetsc_options = { snes_type = "nonsense" }\n',
        "PETSc refused them: Unable to find requested SNES type nonsense",
    ),
    "non-integer PETSc value": (
        TINY + '[solver]\npetsc_options = { snes_max_it = "abc" }\n',
        "PETSc refused them: Input string abc has no integer value",
    ),
    "unknown KSP type": (
        TINY + '[solver]\npetsc_options = { ksp_type = "bogus" }\n',
        "Unable to find requested KSP type bogus",
    ),
    "unknown PETSc option": (
        TINY + "[solver]\npetsc_options = { nonsense_option = 1 }\n",
        "PETSc does not use nonsense_option",
    ),
    "SNES tolerance": (
        TINY + "[solver]\npetsc_options = { snes_rtol = 1e-8 }\n",
        "lungmech stops Newton with its own test",
    ),
    "bad MUMPS setting": (
        TINY + '[solver]\npetsc_options = { mat_mumps_icntl_14 = "abc" }\n',
        "PETSc refused the solver settings (solver.petsc_options?): Input string abc has no integer value",
    ),
    "nothing holds the body": (
        swap('[[constraints]]\ntype = "clamp"\nboundary = "x0"\n', ""),
        "nothing holds the body",
    ),
    "fields a word": (swap("fields = false", 'fields = "no"'), "fields must be true or false"),
    "unknown field format": (swap("fields = false", 'fields = true\nformat = "bp5"'), "format must be one of vtk, vtx"),
    "inverse tolerance": (TINY + "[inverse]\ntolerance = 2.0\n", "inverse: tolerance must lie in (0, 1)"),
    "inverse iterations zero": (TINY + "[inverse]\nmax_iterations = 0\n", "max_iterations must be a positive integer"),
    "inverse unknown key": (TINY + "[inverse]\ntol = 1e-6\n", "inverse.tol: unknown key"),
    "title a number": (swap('title = "tiny"', "title = 3"), "title: expected str"),
    "unknown section": (TINY + "[physics]\ngravity = 1\n", "scene.physics: unknown key"),
    "missing material": (TINY.split("[material]")[0], "missing section [material]"),
    "unknown builder": (swap('builder = "box"', 'builder = "torus"'), "geometry.builder: unknown builder 'torus'"),
    "box cells a word": (swap("cells = [2, 1, 1]", 'cells = ["a", 1, 1]'), "geometry: bad value for the box builder"),
    "builder and file": (swap('builder = "box"', 'builder = "box"\nfile = "m.msh"'), "give exactly one of 'builder'"),
    "mesh file a number": (
        swap('builder = "box"\ncells = [2, 1, 1]\nlengths = [2.0, 1.0, 1.0]', "file = 3"),
        "geometry.file: expected str",
    ),
    "boundary names a word": (
        swap('builder = "box"\ncells = [2, 1, 1]\nlengths = [2.0, 1.0, 1.0]', 'file = "box.xdmf"\nboundaries = "x0"'),
        "geometry.boundaries: expected a table",
    ),
    # every parameter acts, or the scene is refused
    "two parameters on one target": (
        TINY
        + '[parameters.a]\ntarget = "material.E"\nrange = [500.0, 2000.0]\n'
        + '[parameters.b]\ntarget = "material.E"\nrange = [800.0, 1500.0]\n',
        "parameters: parameters 'a' and 'b' all set material.E: only the last would act; keep one",
    ),
    "two parameters on one load": (
        swap("-10.0]", '-10.0]\nname = "pull"')
        + '[parameters.a]\ntarget = "loads.pull.amplitude"\nrange = [0.5, 2.0]\n'
        + '[parameters.b]\ntarget = "loads.pull.amplitude"\nrange = [0.5, 3.0]\n',
        "parameters 'a' and 'b' all set loads.pull.amplitude",
    ),
    "an outside value that another parameter sets": (
        TINY
        + '[parameters.a]\ntarget = "material.E"\nrange = [500.0, 2000.0]\n'
        + '[parameters.b]\ntarget = "material.E"\nrange = [800.0, 1500.0]\noutside = 900.0\n'
        + "region = { normal = [1.0, 0.0, 0.0], position = 1.0, width = 0.1 }\n",
        "parameter 'b': its value outside the region would be ignored: parameter 'a' sets material.E there",
    ),
    "two regions that disagree outside": (
        TINY
        + '[parameters.a]\ntarget = "material.E"\nrange = [500.0, 2000.0]\noutside = 700.0\n'
        + "region = { normal = [1.0, 0.0, 0.0], position = 1.0, width = 0.1 }\n"
        + '[parameters.b]\ntarget = "material.E"\nrange = [800.0, 1500.0]\noutside = 900.0\n'
        + "region = { normal = [-1.0, 0.0, 0.0], position = -1.0, width = 0.1 }\n",
        "with different values outside them",
    ),
    "two parameters on one region": (
        TINY
        + '[parameters.a]\ntarget = "material.E"\nrange = [500.0, 2000.0]\n'
        + "region = { normal = [1.0, 0.0, 0.0], position = 1.0, width = 0.1 }\n"
        + '[parameters.b]\ntarget = "material.E"\nrange = [800.0, 1500.0]\n'
        + "region = { normal = [1.0, 0.0, 0.0], position = 1.0, width = 0.1 }\n",
        "parameters 'a' and 'b' set material.E on the same region",
    ),
    "a half-space beside the body": (
        TINY
        + '[parameters.a]\ntarget = "material.E"\nrange = [500.0, 2000.0]\n'
        + "region = { normal = [1.0, 0.0, 0.0], position = -0.5, width = 0.1 }\n",
        "their half-space region (n·x < s, n = (1, 0, 0), s = -0.5 m) holds no cell of the mesh",
    ),
    "a moving half-space that never reaches the body": (
        TINY
        + '[parameters.a]\ntarget = "material.E"\nrange = [500.0, 2000.0]\n'
        + 'region = { normal = [0.0, 0.0, 1.0], position = "front", width = 0.1 }\n'
        + '[parameters.front]\ntarget = "interface"\ndefault = -1.0\nrange = [-2.0, -0.5]\n',
        "s = -2 to -0.5 m) holds no cell of the mesh",
    ),
    "an interface that moves nothing": (
        TINY + '[parameters.front]\ntarget = "interface"\ndefault = 0.5\nrange = [0.0, 1.0]\n',
        "parameter 'front' moves an interface that no region's position names: it would act on nothing",
    ),
    "a shape mode in a scene without shape modes": (
        TINY + '[parameters.a1]\ntarget = "shape.mode_1"\nrange = [-2.0, 2.0]\n',
        "parameters.a1.target: shape.mode_1 is a shape mode's coefficient: name the library's shape modes in",
    ),
    "a boundary named twice": (
        swap(
            'type = "traction"\nboundary = "x1"\nvalue = [0.0, 0.0, -10.0]',
            'type = "follower_pressure"\nboundary = ["x1", "y0", "x1"]\nvalue = 1.0',
        ),
        "loads[0]: boundary names x1 more than once",
    ),
    "a balancing boundary named twice": (
        TINY
        + '[[loads]]\ntype = "gravity"\ndensity = 1.0\nacceleration = [0.0, 0.0, -9.81]\n'
        + 'balanced_on = ["x1", "y0", "y0"]\n',
        "balanced_on names y0 more than once",
    ),
    # formulas that leave the reals, and solver options that solve nothing
    "formula beyond the floats": (
        swap("[0.0, 0.0, -10.0]", '["1e308*10", 0.0, -10.0]'),
        "loads[0]: value[0]: '1e308*10': a part of it is inf (outside the floating-point range)",
    ),
    "formula of an infinite number": (swap("[0.0, 0.0, -10.0]", '["1e309", 0.0, -10.0]'), "a part of it is inf"),
    "formula of nothing times infinity": (swap("[0.0, 0.0, -10.0]", '["0*1e309", 0.0, -10.0]'), "a part of it is inf"),
    "formula of a complex number": (
        swap("[0.0, 0.0, -10.0]", '["(-8)**(1/3)", 0.0, -10.0]'),
        "'(-8)**(1/3)': a part of it is not a real number",
    ),
    "formula of 100,000 terms": (
        swap("[0.0, 0.0, -10.0]", '["' + "+".join(["1"] * 100_000) + '", 0.0, -10.0]'),
        "a formula of 199999 characters; at most 2000 are read",
    ),
    "formula of too many parts": (
        swap("[0.0, 0.0, -10.0]", '["' + "+".join(["x"] * 300) + '", 0.0, -10.0]'),
        "parts; at most 400 are read",
    ),
    "formula infinite where it acts": (
        swap("[0.0, 0.0, -10.0]", '[0.0, 0.0, "1/(x-x)"]'),
        "load 'traction on x1': value[2] = '1/(x-x)' is inf at x = (2, ",
    ),
    "formula undefined where it acts": (
        swap("[0.0, 0.0, -10.0]", '[0.0, 0.0, "ln(x-5)"]'),
        "value[2] = 'ln(x-5)' is nan at x = (2, ",
    ),
    "formula overflowing where it acts": (
        swap("[0.0, 0.0, -10.0]", '[0.0, 0.0, "exp(1000*x)"]'),
        "value[2] = 'exp(1000*x)' is inf at x = (2, ",
    ),
    "a Jacobi sweep for the direct solver": (
        TINY + '[solver]\nlinear_solver = "direct"\npetsc_options = { pc_type = "jacobi" }\n',
        "with the linear solver that solver.petsc_options set (pc_type = 'jacobi')",
    ),
    "a misspelt parameter target": (
        TINY + '[parameters.a]\ntarget = "material.EE"\nrange = [1.0, 2.0]\n',
        "parameters.a.target: the scene has no material.EE ([material] keys: E, nu)",
    ),
    "a parameter on a load that is not there": (
        TINY + '[parameters.a]\ntarget = "loads.pull.value"\nrange = [1.0, 2.0]\n',
        "parameters.a.target: no load named 'pull' (named loads: none)",
    ),
    "the lung skeleton in the mixed formulation": (
        swap("kappa = 1.0e4\nphi_s0 = 0.3\n", "degree = 2\n", swap('type = "poromechanics"', 'type = "mixed"', LUNG)),
        "law 'lung_skeleton' has no volumetric split",
    ),
    "not TOML": ("[geometry\nbuilder = 1", "not valid TOML"),
    "empty scene": ("", "missing section [geometry]"),
}


@pytest.fixture(scope="module")
def assets(tmp_path_factory) -> Path:
    """Files the cases read: meshes, images, a reduced model, a lungmech result; made once."""
    from lungmech.mesh.lung_shape import LungShape
    from lungmech.registration import image, phantom

    root = tmp_path_factory.mktemp("assets")
    (root / "scene.toml").write_text(TINY)
    comm = MPI.COMM_SELF
    geometry.write(geometry.box(comm, (2.0, 1.0, 1.0), (2, 1, 1)), root / "box.xdmf")
    _square(root / "square.msh")
    image.write(phantom.voxelise(LungShape(), 4e-3), root / "lung.nii.gz")
    assert (
        main(
            [
                "rom",
                "build",
                str(root / "scene.toml"),
                "-o",
                str(root / "model.npz"),
                "--scales",
                "0.5,1.5",
                "--size",
                "4",
                "-q",
            ]
        )
        == 0
    )
    assert main(["run", str(root / "scene.toml"), "-o", str(root / "result"), "-q"]) == 0
    assert (
        main(
            [
                "shape-modes",
                "--synthetic",
                "3",
                "--latent",
                "1",
                "--spacing",
                "5",
                "--reference",
                REFERENCE,
                "-o",
                str(root / "modes"),
                "-q",
            ]
        )
        == 0
    )
    return root


def _square(path: Path) -> None:
    """A unit square of triangles with named edges: a 2-D mesh."""
    import gmsh

    gmsh.initialize(interruptible=False)
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.model.add("square")
    gmsh.model.occ.addRectangle(0, 0, 0, 1, 1)
    gmsh.model.occ.synchronize()
    gmsh.model.addPhysicalGroup(1, [1, 2, 3, 4], 10, "x0")
    gmsh.model.addPhysicalGroup(2, [1], 1, "square")
    gmsh.option.setNumber("Mesh.MeshSizeMax", 0.5)
    gmsh.model.mesh.generate(2)
    gmsh.write(str(path))
    gmsh.finalize()


@pytest.fixture
def workspace(tmp_path, assets, monkeypatch) -> Path:
    """The user's folder: their scene and notes, a folder of theirs, an earlier lungmech result."""
    for name in ("box.xdmf", "box.h5", "box.tags.json", "square.msh", "lung.nii.gz", "model.npz"):
        shutil.copy(assets / name, tmp_path / name)
    shutil.copytree(assets / "result", tmp_path / "result")
    shutil.copytree(assets / "modes", tmp_path / "modes")
    (tmp_path / "scene.toml").write_text(TINY)
    (tmp_path / "notes.txt").write_text("patient 7: do not lose\n")
    (tmp_path / "mydata").mkdir()
    (tmp_path / "mydata" / "notes.txt").write_text("mine\n")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _snapshot(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "folder"
        for p in root.rglob("*")
    }


def refused(argv: list[str], message: str, capsys, root: Path) -> None:
    """``argv`` fails with exit 2 and one line saying ``message``; nothing in ``root`` changes."""
    before = _snapshot(root)
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert code == 2, (code, err, out)
    assert len(lines) == 1 and lines[0].startswith("lungmech: error: "), err
    assert message in lines[0], lines[0]
    assert "Traceback" not in out + err
    after = _snapshot(root)
    assert {k: v for k, v in after.items() if k in before} == before, "a file of the user's was lost or changed"
    assert not [k for k in after if "lungmech-staging" in k or "lungmech-old" in k], "a staging folder was left"


@pytest.mark.parametrize("case", SCENES)
def test_bad_scene(case, workspace, capsys):
    text, message = SCENES[case]
    (workspace / "scene.toml").write_text(text)
    refused(["run", "scene.toml", "-o", "out", "-q"], message, capsys, workspace)
    assert not (workspace / "out").exists()


def _write(name: str, data: bytes | str):
    def make(root: Path) -> None:
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data if isinstance(data, bytes) else data.encode())

    return make


def _mesh_scene(mesh: str, extra: str = "") -> str:
    return swap('builder = "box"\ncells = [2, 1, 1]\nlengths = [2.0, 1.0, 1.0]', f'file = "{mesh}"{extra}')


def _phi(content: bytes | str, name: str = "phi.txt") -> tuple:
    scene = swap("phi_s0 = 0.3", f'phi_s0 = "{name}"', LUNG.replace("cells = [2, 2, 2]", "cells = [1, 1, 1]"))
    return [_write(name, content), _write("scene.toml", scene)]


def _truncated(source: str, name: str, keep: int):
    return lambda root: (root / name).write_bytes((root / source).read_bytes()[:keep])


def _damaged_model(root: Path) -> None:
    with np.load(root / "model.npz") as data:
        arrays = {k: data[k] for k in data.files}
    arrays["vectors"] = np.full_like(arrays["vectors"], np.nan)
    np.savez(root / "nan_model.npz", **arrays)


def _edited_model(change, digest: bool = True, name: str = "edited.npz"):
    """model.npz, changed by ``change(root, metadata, arrays)`` and saved as ``name``; with
    ``digest`` its digest is recomputed, as anyone who edits a file can (it is no signature)."""

    def make(root: Path) -> None:
        with np.load(root / "model.npz") as data:
            arrays = {k: data[k] for k in data.files}
        metadata = json.loads(str(arrays.pop("metadata")))
        change(root, metadata, arrays)
        if digest:
            metadata["sha256"] = store.digest(metadata, arrays)
        np.savez(root / name, metadata=json.dumps(metadata), **arrays)

    return make


def _embedding(name, content: bytes = b"overwritten by a model file\n", listed: bool = True, stored: bool = True):
    """A model file that carries a file under ``name`` (a function of the workspace, or a string)."""

    def change(root: Path, metadata: dict, arrays: dict) -> None:
        embedded = name(root) if callable(name) else name
        if listed:
            metadata["extra"]["files"][embedded] = "somewhere/mesh.msh"
        if stored:
            arrays[f"file:{embedded}"] = np.frombuffer(content, dtype=np.uint8)

    return _edited_model(change)


def _relaw(root: Path, metadata: dict, arrays: dict) -> None:
    metadata["extra"]["scene_table"]["material"]["law"] = "saint_venant_kirchhoff"


def _nan_basis(root: Path, metadata: dict, arrays: dict) -> None:
    arrays["vectors"] = np.full_like(arrays["vectors"], np.nan)


def _lung_result_with(change) -> callable:
    def make(root: Path) -> None:
        change(root / "result")

    return make


def _copy_mesh(folder: str):
    def make(root: Path) -> None:
        (root / folder).mkdir()
        for suffix in (".xdmf", ".h5", ".tags.json"):
            shutil.copy(root / f"box{suffix}", root / folder / f"box{suffix}")

    return make


def _symlink(root: Path) -> None:
    (root / "link").symlink_to(root / "mydata")


def _label_map(root: Path) -> None:
    from lungmech.registration import image

    mask = np.zeros((16, 16, 16), dtype=np.uint8)
    mask[2:8, 2:8, 2:8], mask[9:14, 9:14, 9:14] = 1, 2
    import nibabel

    nibabel.save(nibabel.Nifti1Image(mask, np.diag([4.0, 4.0, 4.0, 1.0])), root / "labels.nii.gz")
    assert image  # the module writes only binary masks: the label map is written with nibabel


def _few_voxels(root: Path) -> None:
    import nibabel

    mask = np.zeros((32, 32, 32), dtype=np.uint8)
    mask[10, 10, 10:13] = 1
    nibabel.save(nibabel.Nifti1Image(mask, np.diag([2.0, 2.0, 2.0, 1.0])), root / "speck.nii.gz")


def _four_d(root: Path) -> None:
    import nibabel

    nibabel.save(nibabel.Nifti1Image(np.ones((4, 4, 4, 2), dtype=np.uint8), np.eye(4)), root / "movie.nii.gz")


def _other_physics(change: str, into: str) -> list:
    return [_write("other/scene.toml", swap(change, into))]


# (files to make, command line, what the message must say)
COMMANDS = {
    # scene files
    "binary scene": (
        [_write("scene.toml", b"\x89PNG\r\n\x1a\n\0\0\0")],
        ["run", "scene.toml", "-o", "out"],
        "is not a text file",
    ),
    "latin-1 scene": (
        [_write("scene.toml", TINY.replace("tiny", "poumon é").encode("latin-1"))],
        ["run", "scene.toml", "-o", "out"],
        "is not UTF-8 text (byte 0xe9 on line 1)",
    ),
    "scene is a folder": ([lambda r: (r / "scenes").mkdir()], ["run", "scenes", "-o", "out"], "is a folder"),
    "scene missing": ([], ["run", "none.toml", "-o", "out"], "scene file 'none.toml' not found"),
    # meshes
    "2-D mesh file without a plane": (
        [_write("scene.toml", _mesh_scene("square.msh"))],
        ["run", "scene.toml", "-o", "out"],
        "a 2-D mesh needs plane = 'strain' (a long body) or 'stress' (a thin plate)",
    ),
    "xdmf without its data": (
        [lambda r: (r / "box.h5").rename(r / "elsewhere.h5"), _write("scene.toml", _mesh_scene("box.xdmf"))],
        ["run", "scene.toml", "-o", "out"],
        "its data file",
    ),
    "xdmf without boundary names": (
        [lambda r: (r / "box.tags.json").rename(r / "names.json"), _write("scene.toml", _mesh_scene("box.xdmf"))],
        ["run", "scene.toml", "-o", "out"],
        "its boundary names, 'box.tags.json', are missing",
    ),
    "truncated msh": (
        [_truncated("square.msh", "cut.msh", 300), _write("scene.toml", _mesh_scene("cut.msh"))],
        ["run", "scene.toml", "-o", "out"],
        "mesh file",
    ),
    "mesh of another format": (
        [_write("lung.stl", "solid x\nendsolid x\n"), _write("scene.toml", _mesh_scene("lung.stl"))],
        ["run", "scene.toml", "-o", "out"],
        "suffix '.stl' is not .msh, .vtu or .xdmf",
    ),
    "mesh file is a folder": (
        [lambda r: (r / "dir.msh").mkdir(), _write("scene.toml", _mesh_scene("dir.msh"))],
        ["run", "scene.toml", "-o", "out"],
        "is a folder; name a mesh file",
    ),
    "mesh file missing": (
        [_write("scene.toml", _mesh_scene("nowhere.msh"))],
        ["run", "scene.toml", "-o", "out"],
        "mesh file",
    ),
    "unknown tag name": (
        [_write("scene.toml", _mesh_scene("box.xdmf", "\nboundaries = { x0 = 99 }"))],
        ["run", "scene.toml", "-o", "out"],
        "boundary 'x0' has tag 99, which no facet carries",
    ),
    "phi_s0 file with nan": (
        _phi(b"0.3\n" * 5 + b"nan\n"),
        ["run", "scene.toml", "-o", "out"],
        "holds values that are not finite numbers",
    ),
    "phi_s0 file too short": (
        _phi(b"0.3\n0.3\n"),
        ["run", "scene.toml", "-o", "out"],
        "has 2 values; the mesh has 6 cells",
    ),
    "phi_s0 file of words": (_phi(b"zero\none\n"), ["run", "scene.toml", "-o", "out"], "is not a list of numbers"),
    "phi_s0 file empty": (_phi(b""), ["run", "scene.toml", "-o", "out"], "has 0 values"),
    "phi_s0 pickled": (
        _phi(
            b"\x93NUMPY\x01\x00v\x00{'descr': '|O', 'fortran_order': False, 'shape': (1,), }" + b" " * 60 + b"\n",
            "phi.npy",
        ),
        ["run", "scene.toml", "-o", "out"],
        "is not a list of numbers",
    ),
    "phi_s0 file missing": (
        [_write("scene.toml", swap("phi_s0 = 0.3", 'phi_s0 = "none.npy"', LUNG))],
        ["run", "scene.toml", "-o", "out"],
        "phi_s0: file",
    ),
    "phi_s0 out of range": (_phi(b"0.3\n" * 5 + b"1.2\n"), ["run", "scene.toml", "-o", "out"], "must lie in (0, 1)"),
    # outputs
    "-o .": ([], ["run", "scene.toml", "-o", "."], "is the current folder"),
    "-o empty": ([], ["run", "scene.toml", "-o", ""], "is the current folder"),
    "-o a parent of the current folder": ([], ["run", "scene.toml", "-o", ".."], "holds the current folder"),
    "-o the scene's folder": (
        [_write("proj/scene.toml", TINY)],
        ["run", "proj/scene.toml", "-o", "proj"],
        "holds the input",
    ),
    "-o the mesh's folder": (
        [_copy_mesh("m2"), _write("meshdir/scene.toml", _mesh_scene("../m2/box.xdmf"))],
        ["run", "meshdir/scene.toml", "-o", "m2"],
        "holds the input",
    ),
    "-o the user's folder": ([], ["run", "scene.toml", "-o", "mydata"], "is not empty and was not written by lungmech"),
    "-o a link to the user's folder": ([_symlink], ["run", "scene.toml", "-o", "link"], "was not written by lungmech"),
    "-o an existing file": ([], ["run", "scene.toml", "-o", "notes.txt"], "exists and is not a folder"),
    "-o below a file": ([], ["run", "scene.toml", "-o", "notes.txt/out"], "cannot write into"),
    "-o a result with a note added": (
        [_write("result/my_note.txt", "keep")],
        ["run", "scene.toml", "-o", "result"],
        "holds 'my_note.txt', which lungmech did not write",
    ),
    "-o a result with a changed file": (
        [lambda r: (r / "result" / "history.csv").write_text("edited\n")],
        ["run", "scene.toml", "-o", "result"],
        "was changed after lungmech wrote it",
    ),
    "-o a result with a folder added": (
        [lambda r: (r / "result" / "extra").mkdir()],
        ["run", "scene.toml", "-o", "result"],
        "holds 'extra', which lungmech did not write",
    ),
    "rom build over a user file": (
        [_write("m.npz", b"mine")],
        ["rom", "build", "scene.toml", "-o", "m.npz"],
        "exists and was not written by lungmech",
    ),
    "rom build over a folder": (
        [lambda r: (r / "dir.npz").mkdir()],
        ["rom", "build", "scene.toml", "-o", "dir.npz"],
        "is a folder",
    ),
    "rom build over the scene": ([], ["rom", "build", "scene.toml", "-o", "scene.toml"], "saved as .npz"),
    "rom build of no scales": (
        [],
        ["rom", "build", "scene.toml", "-o", "m2.npz", "--scales", "1,nan"],
        "load scales must be finite numbers",
    ),
    "rom build of a wrong basis": (
        [],
        ["rom", "build", "scene.toml", "-o", "m2.npz", "--basis", "wavelet"],
        "basis kind must be",
    ),
    "rom build of an unknown hyper-reduction": (
        [],
        ["rom", "build", "scene.toml", "-o", "m2.npz", "--hyper", "deim"],
        "hyper-reduction must be one of ecsw",
    ),
    "rom build of an ECSW tolerance above 1": (
        [],
        ["rom", "build", "scene.toml", "-o", "m2.npz", "--hyper", "ecsw", "--ecsw-tolerance", "2"],
        "the ECSW tolerance must lie in (0, 1)",
    ),
    "rom build of an ECSW tolerance of nan": (
        [],
        ["rom", "build", "scene.toml", "-o", "m2.npz", "--hyper", "ecsw", "--ecsw-tolerance", "nan"],
        "ECSW tolerance",
    ),
    "rom build to a tolerance above 1": (
        [],
        ["rom", "build", "scene.toml", "-o", "m2.npz", "--tolerance", "2"],
        "the tolerance (a relative energy-norm error) must lie in (0, 1)",
    ),
    "rom build to a tolerance of nan": (
        [],
        ["rom", "build", "scene.toml", "-o", "m2.npz", "--tolerance", "nan"],
        "tolerance must be a finite number",
    ),
    "rom build to a tolerance without parameters": (
        [],
        ["rom", "build", "scene.toml", "-o", "m2.npz", "--tolerance", "0.01"],
        "--tolerance trains over the scene's [parameters] box, and this scene has none",
    ),
    "rom build of a saddle point in the energy inner product": (
        [
            _write(
                "mixed.toml",
                TINY.replace("[[constraints]]", '[formulation]\ntype = "mixed"\ndegree = 2\n[[constraints]]', 1),
            )
        ],
        ["rom", "build", "mixed.toml", "-o", "m2.npz", "--size", "3"],
        "the energy inner product is not positive definite on this model's states",
    ),
    "rom build of an ECSW size without ECSW": (
        [],
        ["rom", "build", "scene.toml", "-o", "m2.npz", "--ecsw-size", "3"],
        "--ecsw-size and --ecsw-judge shape a hyper-reduction: give --hyper ecsw",
    ),
    "rom build judging without a greedy": (
        [],
        ["rom", "build", "scene.toml", "-o", "m2.npz", "--hyper", "ecsw", "--ecsw-judge", "1e-3"],
        "--ecsw-judge is the τ a greedy training judges at: give --tolerance",
    ),
    "rom build of size zero": (
        [],
        ["rom", "build", "scene.toml", "-o", "m2.npz", "--size", "0"],
        "basis size must be a positive integer",
    ),
    "phantom over a user image": (
        [lambda r: shutil.copy(r / "notes.txt", r / "patient.nii.gz")],
        ["phantom", "-o", "patient.nii.gz"],
        "exists and was not written by lungmech",
    ),
    "phantom of zero spacing": ([], ["phantom", "-o", "p.nii.gz", "--spacing", "0"], "--spacing must be a positive"),
    "phantom of another format": ([], ["phantom", "-o", "p.png"], "unknown suffix"),
    "shape over a user mesh": (
        [lambda r: [(r / f"user{s}").write_text("theirs") for s in (".xdmf", ".h5")]],
        ["shape", "modes/shape_modes.npz", "--reference", REFERENCE, "-c", "0.5", "-o", "user.xdmf"],
        "exists and was not written by lungmech",
    ),
    "shape over a user .vtu": (
        [_write("user.vtu", "theirs")],
        ["shape", "modes/shape_modes.npz", "--reference", REFERENCE, "-c", "0.5", "-o", "user.vtu"],
        "exists and was not written by lungmech",
    ),
    "shape next to a user h5": (
        [_write("new.h5", "theirs")],
        ["shape", "modes/shape_modes.npz", "--reference", REFERENCE, "-c", "0.5", "-o", "new.xdmf"],
        "does not belong to a file lungmech wrote",
    ),
    "shape as another format": (
        [],
        ["shape", "modes/shape_modes.npz", "--reference", REFERENCE, "-c", "0.5", "-o", "x.vtk"],
        "is written as a .vtu or .xdmf mesh",
    ),
    "shape of too many coefficients": (
        [],
        ["shape", "modes/shape_modes.npz", "--reference", REFERENCE, "-c", "1,1,1,1", "-o", "x.xdmf"],
        "give at most",
    ),
    "shape of nan": (
        [],
        ["shape", "modes/shape_modes.npz", "--reference", REFERENCE, "-c", "nan", "-o", "x.xdmf"],
        "must be finite numbers",
    ),
    "shape of a word": (
        [],
        ["shape", "modes/shape_modes.npz", "--reference", REFERENCE, "-c", "big", "-o", "x.xdmf"],
        "not a list of numbers",
    ),
    "shape modes that are not": (
        [],
        ["shape", "notes.txt", "--reference", REFERENCE, "-c", "1", "-o", "x.xdmf"],
        "is not a shape-modes file",
    ),
    "shape on another mesh": (
        [],
        ["shape", "modes/shape_modes.npz", "--reference", "lung_phantom_left", "-c", "1", "-o", "x.xdmf"],
        "not the reference these shape modes were built on",
    ),
    # reduced models
    "model missing": ([], ["rom", "solve", "none.npz", "scene.toml", "-o", "out"], "reduced model file not found"),
    "model truncated": (
        [_truncated("model.npz", "cut.npz", 200)],
        ["rom", "solve", "cut.npz", "scene.toml", "-o", "out"],
        "not an .npz archive, or a truncated one",
    ),
    "model of text": (
        [_write("text.npz", "hello")],
        ["rom", "solve", "text.npz", "scene.toml", "-o", "out"],
        "is not a lungmech reduced model",
    ),
    "model foreign": (
        [lambda r: np.savez(r / "foreign.npz", a=np.ones(3))],
        ["rom", "solve", "foreign.npz", "scene.toml", "-o", "out"],
        "is not a lungmech reduced model",
    ),
    "model is a folder": (
        [lambda r: (r / "m.npz").mkdir()],
        ["rom", "solve", "m.npz", "scene.toml", "-o", "out"],
        "is a folder",
    ),
    "model damaged": (
        [_damaged_model],
        ["rom", "solve", "nan_model.npz", "scene.toml", "-o", "out"],
        "was changed after lungmech wrote it (its SHA-256 digest does not match its content)",
    ),
    "model damaged with its digest redone": (
        [_edited_model(_nan_basis)],
        ["rom", "solve", "edited.npz", "scene.toml", "-o", "out"],
        "holds values that are not finite numbers",
    ),
    "model whose basis is not orthonormal, its digest redone": (
        [_edited_model(lambda root, metadata, arrays: arrays.update(vectors=2.0 * arrays["vectors"]))],
        ["rom", "solve", "edited.npz", "scene.toml", "-o", "out"],
        "is damaged: its basis is not orthonormal in its energy inner product",
    ),
    "model of an older format": (
        [_edited_model(lambda root, metadata, arrays: metadata.update(format="lungmech-rom/3"))],
        ["rom", "solve", "edited.npz", "-o", "out"],
        f"was written by another lungmech version (format lungmech-rom/3, this one reads {store.FORMAT}); "
        "rebuild it with 'lungmech rom build'",
    ),
    "model of an edited law": (
        [_edited_model(_relaw, digest=False)],
        ["rom", "solve", "edited.npz", "-o", "out"],
        "'edited.npz' was changed after lungmech wrote it",
    ),
    "model writing to an absolute path": (
        [_embedding(lambda root: str(root / "notes.txt"))],
        ["rom", "solve", "edited.npz", "-o", "out"],
        "names an embedded file '/",
    ),
    "model writing up the tree": (
        [_embedding("mesh/../../../notes.txt")],
        ["rom", "solve", "edited.npz", "-o", "out"],
        "names an embedded file 'mesh/../../../notes.txt', which is not a name lungmech writes",
    ),
    "model writing into a user folder": (
        [_embedding("mesh/../mydata/notes.txt")],
        ["rom", "solve", "edited.npz", "-o", "out"],
        "which is not a name lungmech writes",
    ),
    "model writing through a sweep": (
        [_embedding("data/../../notes.txt"), _write("points.csv", "a\n1\n")],
        ["rom", "solve", "edited.npz", "--sweep", "points.csv", "-o", "out"],
        "names an embedded file 'data/../../notes.txt'",
    ),
    "model writing to a backslash path": (
        [_embedding("mesh/..\\..\\notes.txt")],
        ["rom", "solve", "edited.npz", "-o", "out"],
        "which is not a name lungmech writes",
    ),
    "model writing where lungmech never does": (
        [_embedding("results/summary.json")],
        ["rom", "solve", "edited.npz", "-o", "out"],
        "names an embedded file 'results/summary.json'",
    ),
    "model listing a file it does not hold": (
        [_embedding("mesh/box.msh", stored=False)],
        ["rom", "solve", "edited.npz", "-o", "out"],
        "lists the embedded file 'mesh/box.msh' but holds no bytes for it",
    ),
    "model of a list of files that is not a table": (
        [_edited_model(lambda root, metadata, arrays: metadata["extra"].update(files=["mesh/a.msh"]))],
        ["rom", "solve", "edited.npz", "-o", "out"],
        "is damaged: its scene or its list of files is not a table",
    ),
    "model of another law": (
        _other_physics(
            'law = "neo_hookean"\nE = 1.0e3\nnu = 0.3', 'law = "saint_venant_kirchhoff"\nE = 1.0e3\nnu = 0.3'
        ),
        ["rom", "solve", "model.npz", "other/scene.toml", "-o", "out"],
        "material.law",
    ),
    "model of another clamp": (
        _other_physics('boundary = "x0"', 'boundary = "x1"'),
        ["rom", "solve", "model.npz", "other/scene.toml", "-o", "out"],
        "constraints[0].boundary",
    ),
    "model of another load": (
        _other_physics("[0.0, 0.0, -10.0]", "[0.0, -10.0, 0.0]"),
        ["rom", "solve", "model.npz", "other/scene.toml", "-o", "out"],
        "loads[0].value",
    ),
    "model of another stiffness": (
        _other_physics("E = 1.0e3", "E = 5.0e3"),
        ["rom", "solve", "model.npz", "other/scene.toml", "-o", "out"],
        "material.E: 1000.0",
    ),
    "model of another mesh": (
        _other_physics("cells = [2, 1, 1]", "cells = [4, 1, 1]"),
        ["rom", "solve", "model.npz", "other/scene.toml", "-o", "out"],
        "geometry.cells",
    ),
    "model with two scales": (
        [],
        ["rom", "solve", "model.npz", "scene.toml", "-o", "out", "--scale", "1,2"],
        "--scale takes one value",
    ),
    "model with two scales for one load": (
        [],
        ["rom", "solve", "model.npz", "scene.toml", "-o", "out", "--scale", "1:2"],
        "one finite factor or one per load",
    ),
    "model with a scale beyond any load": (
        [],
        ["run", "scene.toml", "-o", "out", "--scale", "1e300"],
        "the load path stopped at t = 0 s",
    ),
    "model with a scale of letters": (
        [],
        ["rom", "solve", "model.npz", "scene.toml", "-o", "out", "--scale", "deep"],
        "not a list of numbers",
    ),
    # images and registration
    "register -o .": ([], ["register", "lung.nii.gz", "--reference", REFERENCE, "-o", "."], "is the current folder"),
    "register into the image's folder": (
        [lambda r: (r / "ct").mkdir(), lambda r: shutil.copy(r / "lung.nii.gz", r / "ct")],
        ["register", "ct/lung.nii.gz", "--reference", REFERENCE, "-o", "ct"],
        "holds the input",
    ),
    "register onto a speck": (
        [_few_voxels],
        ["register", "speck.nii.gz", "--reference", REFERENCE, "-o", "fit"],
        "spans only [1, 1, 3] voxels",
    ),
    "register in the wrong unit": (
        [],
        ["register", "lung.nii.gz", "--reference", REFERENCE, "--unit", "m", "-o", "fit"],
        "is the image's length unit right",
    ),
    "register a 4-D image": ([_four_d], ["register", "movie.nii.gz", "--reference", REFERENCE, "-o", "fit"], "4-D"),
    "register a label map": (
        [_label_map],
        ["register", "labels.nii.gz", "--reference", REFERENCE, "-o", "fit"],
        "choose one with --label",
    ),
    "register an unknown format": (
        [_write("scan.png", b"png")],
        ["register", "scan.png", "--reference", REFERENCE, "-o", "fit"],
        "unknown suffix",
    ),
    "register without convergence": (
        [],
        ["register", "lung.nii.gz", "--reference", REFERENCE, "--max-iterations", "1", "--stages", "1", "-o", "fit"],
        "did not converge",
    ),
    "register onto a 2-D reference": (
        [],
        ["register", "lung.nii.gz", "--reference", "square.msh", "-o", "fit"],
        "holds a 2-D mesh (triangle cells); a 3-D body is needed here",
    ),
    "register onto no reference": (
        [],
        ["register", "lung.nii.gz", "--reference", "none.msh", "-o", "fit"],
        "not found",
    ),
    "register onto a missing path named like a bundled mesh": (
        [],
        ["register", "lung.nii.gz", "--reference", "mine/lung_phantom_left.msh", "-o", "fit"],
        "not found",
    ),
    "a cohort of negative spacing": (
        [],
        ["shape-modes", "--synthetic", "3", "--spacing", "-5", "-o", "modes2"],
        "--spacing must be a positive voxel size in mm",
    ),
    "a phantom too fine": ([], ["phantom", "-o", "fine.nii.gz", "--spacing", "1e-4"], "use a coarser spacing"),
    "register the user's folder": (
        [],
        ["register", "lung.nii.gz", "--reference", REFERENCE, "-o", "mydata"],
        "was not written by lungmech",
    ),
    # the command line itself
    "unknown command": ([], ["simulate", "scene.toml"], "invalid choice: 'simulate'"),
    "missing -o for a model": ([], ["rom", "build", "scene.toml"], "the following arguments are required: -o/--output"),
    "size of letters": (
        [],
        ["rom", "build", "scene.toml", "-o", "m2.npz", "--size", "big"],
        "invalid int value: 'big'",
    ),
}


@pytest.mark.parametrize("case", COMMANDS)
def test_bad_command(case, workspace, capsys):
    makers, argv, message = COMMANDS[case]
    for make in makers:
        make(workspace)
    refused(argv, message, capsys, workspace)


def test_the_suite_is_large_enough():
    assert len(SCENES) + len(COMMANDS) >= 100


def test_full_disk(workspace, capsys, monkeypatch):
    """A write that fails for lack of space (ENOSPC) is one error naming the file; the earlier
    result stays, and the staging folder goes."""
    import lungmech.app.output

    real = lungmech.app.output.write_json

    def full(path, data, comm=MPI.COMM_WORLD):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(lungmech.app.output, "write_json", full)
    monkeypatch.setattr("lungmech.app.run.write_json", full)
    refused(["run", "scene.toml", "-o", "result", "-q"], "cannot write", capsys, workspace)
    monkeypatch.setattr("lungmech.app.run.write_json", real)
    assert json.loads((workspace / "result" / "summary.json").read_text())["steps"] >= 1


def _mount(*args: str) -> bool:
    return subprocess.run(["mount", *args], capture_output=True).returncode == 0


@pytest.fixture
def tiny_disk(tmp_path):
    """A 64 kB file system (tmpfs), or a skip where mounting is not allowed."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if os.geteuid() != 0 or not _mount("-t", "tmpfs", "-o", "size=64k", "tmpfs", str(disk)):
        pytest.skip("mounting a small tmpfs needs root")
    yield disk
    subprocess.run(["umount", "-l", str(disk)])


def test_really_full_disk(workspace, tiny_disk, capsys):
    (tiny_disk / "keep.txt").write_text("the user's\n")
    scene = swap("fields = false", "fields = true")
    (workspace / "scene.toml").write_text(scene.replace("cells = [2, 1, 1]", "cells = [16, 8, 8]"))
    before = _snapshot(tiny_disk)
    refused(["run", "scene.toml", "-o", str(tiny_disk / "out"), "-q"], "No space left on device", capsys, workspace)
    assert _snapshot(tiny_disk) == before


@pytest.fixture
def read_only(tmp_path):
    """A read-only folder holding an earlier result (a read-only bind mount), or a skip."""
    folder = tmp_path / "ro"
    (folder / "old").mkdir(parents=True)
    (folder / "old" / "summary.json").write_text("{}")
    if os.geteuid() != 0 or not _mount("--bind", str(folder), str(folder)):
        pytest.skip("a read-only bind mount needs root")
    if not _mount("-o", "remount,ro,bind", str(folder)):
        subprocess.run(["umount", "-l", str(folder)])
        pytest.skip("cannot remount read-only")
    yield folder
    subprocess.run(["umount", "-l", str(folder)])


def test_read_only_folder(workspace, read_only, capsys):
    before = _snapshot(read_only)
    refused(["run", "scene.toml", "-o", str(read_only / "out"), "-q"], "Read-only file system", capsys, workspace)
    refused(
        ["rom", "build", "scene.toml", "-o", str(read_only / "m.npz"), "-q"], "Read-only file system", capsys, workspace
    )
    assert _snapshot(read_only) == before


def test_zipfile_is_not_enough_to_be_a_model(workspace, capsys):
    """An .npz with lungmech's keys but a foreign format tag is refused, and not overwritten."""
    with zipfile.ZipFile(workspace / "fake.npz", "w") as z:
        z.writestr("metadata.npy", b"not numpy")
    refused(
        ["rom", "solve", "fake.npz", "scene.toml", "-o", "out"], "is not a lungmech reduced model", capsys, workspace
    )
    refused(
        ["rom", "build", "scene.toml", "-o", "fake.npz"], "exists and was not written by lungmech", capsys, workspace
    )


def test_a_jit_cache_that_is_a_file_is_named(tmp_path):
    """DOLFINx's JIT cache set (dolfinx_jit_options.json) to a path that is a file: one line that
    names it, exit 2, the file unchanged. (A subprocess: the JIT options are read once a process.)"""
    import sys

    (tmp_path / "scene.toml").write_text(TINY)
    (tmp_path / "cachefile").write_text("mine\n")
    (tmp_path / "dolfinx_jit_options.json").write_text('{"cache_dir": "cachefile"}')
    before = _snapshot(tmp_path)
    done = subprocess.run(
        [str(Path(sys.executable).parent / "lungmech"), "run", "scene.toml", "-o", "out", "-q"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2 and len(lines) == 1 and "'cachefile'" in lines[0], done.stderr
    assert lines[0].startswith("lungmech: error: ") and _snapshot(tmp_path) == before
