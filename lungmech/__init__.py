"""lungmech: finite-strain continuum mechanics for lung digital twins, on DOLFINx 0.11.

The library: ``fem`` (laws, loads, model, solver), ``mesh`` (geometries), ``lung`` (the
poromechanical lung, gravity, the inverse problem), ``parallel``, ``rom`` (reduced models) and
``registration``. The application (scenes, runs, CLI) is ``lungmech.app``. The names users
reach for first are importable from here, e.g. ``from lungmech import Model, NeoHookean, box``;
they load on first use, so ``import lungmech`` stays light.
"""

# Before NumPy loads OpenBLAS: under mpiexec, N ranks of N threads each stall one another.
from lungmech import _threads  # noqa: F401, I001  (one BLAS thread per rank, unless the user set one)

try:  # The PyPI wheel must order MPI before the compiled bindings; Debian's build has no such module.
    import dolfinx_solver  # noqa: F401
except ImportError:
    pass

import importlib

from lungmech import _dispatch, _moved
from lungmech.errors import GeometryError, LungmechError, ParameterError, SceneError, SolverError

__version__ = "0.2.0"

_moved.install()
_dispatch.install()  # before UFL's algorithms run: Python 3.13.0-3.13.1 leak every form (gh-127750)

_PUBLIC = {
    "lungmech.fem": (
        "BodyForce",
        "CiarletGeymonat",
        "Displacement",
        "ExponentialCiarletGeymonat",
        "FollowerPressure",
        "LinearElastic",
        "Model",
        "MooneyRivlin",
        "NeoHookean",
        "NewtonOptions",
        "NewtonSolver",
        "Ramp",
        "SaintVenantKirchhoff",
        "StableNeoHookean",
        "Stepping",
        "Sum",
        "TaylorHood",
        "Traction",
        "clamp",
        "deformed_volume",
        "solve",
        "strain_energy",
        "symmetry",
    ),
    "lungmech.mesh": ("Geometry", "box", "ellipsoid", "from_file", "lung_phantom", "sphere"),
    "lungmech.lung": ("AlveolarPressure", "Gravity", "Poromechanics", "unloaded_reference"),
}
_WHERE = {name: module for module, names in _PUBLIC.items() for name in names}

__all__ = ["GeometryError", "LungmechError", "ParameterError", "SceneError", "SolverError", "__version__", *_WHERE]


def __getattr__(name: str) -> object:
    if name in _WHERE:
        return getattr(importlib.import_module(_WHERE[name]), name)
    raise AttributeError(f"module 'lungmech' has no attribute {name!r}")
