"""Finite-element set-ups shared by the tests (homogeneous states on a box)."""

from __future__ import annotations

from pathlib import Path

from mpi4py import MPI

import numpy as np
import ufl

import lungmech.meshes
from lungmech.fem.constraints import Displacement, clamp, symmetry
from lungmech.fem.loads import FollowerPressure
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.parameters import Parameter
from lungmech.fem.parametric import FullOrderModel
from lungmech.fem.quantities import integral
from lungmech.fem.ramp import Ramp
from lungmech.fem.solver import NewtonOptions, Stepping, solve
from lungmech.mesh import box, sphere

MESHES = Path(lungmech.meshes.__file__).parent  # the bundled meshes


def bundled_lung(loads, comm: MPI.Comm = MPI.COMM_WORLD, **keywords) -> Model:
    """The bundled right lung phantom, poromechanical (the bundled scene's skeleton, κ = 1e4 Pa,
    Φs0 = 0.3), held at its hilum, under ``loads``; ``keywords`` to the Model (parameters, image)."""
    from lungmech.lung import Poromechanics, skeleton
    from lungmech.mesh import from_file

    return Model(
        from_file(MESHES / "lung_phantom_right.msh", comm),
        skeleton(160.0, 0.5, 200.0, 400.0),
        formulation=Poromechanics(1e4, 0.3),
        loads=loads,
        constraints=[clamp("hilum")],
        **keywords,
    )


# A small scene: a 2 × 1 × 1 box of neo-Hookean rubber, clamped at x0 and pulled down at x1.
TINY_SCENE = """title = "tiny"
[geometry]
builder = "box"
cells = [2, 1, 1]
lengths = [2.0, 1.0, 1.0]
[material]
law = "neo_hookean"
E = 1.0e3
nu = 0.3
[[constraints]]
type = "clamp"
boundary = "x0"
[[loads]]
type = "traction"
boundary = "x1"
value = [0.0, 0.0, -10.0]
[output]
fields = false
"""


# The tiny scene on a finer mesh, its pull named, over a box of stiffness and pull amplitude.
PARAMETRIC_SCENE = (
    TINY_SCENE.replace("cells = [2, 1, 1]", "cells = [6, 2, 2]").replace("-10.0]", '-10.0]\nname = "pull"')
    + """
[parameters.stiffness]
target = "material.E"
range = [500.0, 2000.0]
scale = "log"
[parameters.pull]
target = "loads.pull.amplitude"
range = [0.5, 5.0]
"""
)


def write_once(path: Path, content: str | bytes) -> Path:
    """Write ``content`` to ``path`` from rank 0, the others waiting: under MPI ``tmp_path`` is
    one folder for all ranks (tests/conftest.py)."""
    if MPI.COMM_WORLD.rank == 0:
        path.write_bytes(content.encode() if isinstance(content, str) else content)
    MPI.COMM_WORLD.Barrier()
    return path


def mean_cauchy(model: Model) -> np.ndarray:
    """Volume average of the Cauchy stress over the reference configuration."""
    comm = model.geometry.mesh.comm
    sigma = model.cauchy()
    volume = model.geometry.volume()
    return np.array([[integral(sigma[i, j] * model.dx, comm)() / volume for j in range(3)] for i in range(3)])


def imposed_gradient(F: np.ndarray):
    """u(X) = (F − I) X, as a callable for an imposed displacement."""
    G = np.asarray(F, dtype=float) - np.eye(3)
    return lambda x: G @ x


def homogeneous(law, F: np.ndarray, degree: int = 1, mixed: bool = False, comm=MPI.COMM_WORLD) -> Model:
    """u = (F − I)X imposed on the whole boundary of the unit cube, solved."""
    geometry = box(comm, cells=(2, 2, 2))
    constraints = [Displacement(name, imposed_gradient(F)) for name in ("x0", "x1", "y0", "y1", "z0", "z1")]
    model = Model(geometry, law, degree=degree, mixed=mixed, constraints=constraints)
    solve(model, Stepping(initial_step=1.0))
    return model


def uniaxial(
    law,
    stretch: float,
    degree: int = 1,
    mixed: bool = False,
    biaxial: bool = False,
    stepping: Stepping | None = None,
    comm=MPI.COMM_WORLD,
) -> Model:
    """Stretch along x (and y when ``biaxial``) with symmetry planes; the other faces are free."""
    geometry = box(comm, cells=(1, 1, 1))
    constraints = [
        symmetry("x0", "x"),
        symmetry("y0", "y"),
        symmetry("z0", "z"),
        Displacement("x1", stretch - 1.0, "x"),
    ]
    if biaxial:
        constraints.append(Displacement("y1", stretch - 1.0, "y"))
    model = Model(geometry, law, degree=degree, mixed=mixed, constraints=constraints)
    solve(model, stepping or Stepping(initial_step=0.25), NewtonOptions())
    return model


def lateral_stretch(model: Model) -> float:
    """1 + u_y at the corner (1, 1, 1) of a box model."""
    comm = model.geometry.mesh.comm
    u = model.u
    area = model.geometry.area("y1")
    return 1.0 + integral(u[1] * model.geometry.ds("y1"), comm)() / area


def relative_error(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(np.asarray(b)))


def inflated_sphere(comm, mesh_size: float, pressure: float, stepping: Stepping) -> Model:
    """Octant of the thick sphere A = 1, B = 2, incompressible neo-Hookean (μ = 1), P2–P1, solved."""
    model = Model(
        sphere(comm, 1.0, 2.0, mesh_size=mesh_size, octant=True, order=2),
        NeoHookean.incompressible(1.0),
        degree=2,
        mixed=True,
        constraints=[symmetry("x0", "x"), symmetry("y0", "y"), symmetry("z0", "z")],
        loads=[FollowerPressure("inner", pressure)],
    )
    solve(model, stepping)
    return model


def mean_inner_radius(model: Model) -> float:
    """Mean deformed distance from the centre of the points of the cavity surface."""
    geometry = model.geometry
    x = ufl.SpatialCoordinate(geometry.mesh)
    radius = ufl.sqrt(ufl.dot(x + model.u, x + model.u))
    return integral(radius * geometry.ds("inner"), geometry.mesh.comm)() / geometry.area("inner")


BOX = [
    Parameter("E", "material.E", 10.0, (5.0, 20.0), log=True),
    Parameter("nu", "material.nu", 0.3, (0.2, 0.45)),
    Parameter("p", "loads.push.value", 1.0, (0.2, 2.0)),
]


def pushed_block(comm=MPI.COMM_SELF, cells=(6, 2, 2)) -> FullOrderModel:
    """A clamped neo-Hookean block under a follower pressure that rises and falls, over a box of
    stiffness, Poisson's ratio and pressure."""
    model = Model(
        box(comm, cells=cells),
        lambda c: NeoHookean.from_young(c["E"], c["nu"]),
        constraints=[clamp("x0")],
        loads=[FollowerPressure("x1", 1.0, name="push", ramp=Ramp((0, 1, 2), (0, 1, 0)))],
        parameters=BOX,
    )
    return FullOrderModel(model, Stepping(end=2.0, times=(0.5, 1.5)), probes=[(1.0, 0.5, 0.5)])
