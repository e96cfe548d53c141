"""lungmech: finite-strain continuum mechanics for lung digital twins, on DOLFINx 0.11."""

try:  # The PyPI wheel must order MPI before the compiled bindings; Debian's build has no such module.
    import dolfinx_solver  # noqa: F401
except ImportError:
    pass

from lungmech.errors import GeometryError, LungmechError, ParameterError, SceneError, SolverError

__version__ = "0.1.0"

__all__ = ["GeometryError", "LungmechError", "ParameterError", "SceneError", "SolverError", "__version__"]
