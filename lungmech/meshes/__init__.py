"""Meshes that ship with lungmech: gmsh ``.msh`` files with named boundaries (see README.md here).

``reference("lung_phantom_right")`` is the path of a bundled mesh; the command line accepts
these names wherever it takes a mesh file. Regenerate them with
``python -m lungmech.meshes.make_meshes``.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from lungmech.errors import GeometryError

__all__ = ["NAMES", "locate", "reference"]

NAMES = ("lung_phantom_right", "lung_phantom_left", "sphere_octant")


def reference(name: str) -> Path:
    """The path of the bundled mesh ``name`` (one of :data:`NAMES`)."""
    if name not in NAMES:
        raise GeometryError(f"no bundled mesh called {name!r} (bundled: {', '.join(NAMES)})")
    return Path(str(resources.files(__name__) / f"{name}.msh"))


def locate(given: str | Path) -> Path:
    """A mesh file by path, or a bundled mesh by its bare name (no folder, no suffix) when no
    file of that name exists here."""
    path = Path(given)
    return reference(str(given)) if str(given) in NAMES and not path.exists() else path
