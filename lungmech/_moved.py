"""Import paths of lungmech 0.1 that moved in 0.2, kept working for one release.

``import lungmech.geometry`` (say) still works: it warns once (DeprecationWarning, naming the new
path) and gives a module that forwards every attribute to the new one. Remove in 0.3.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings
from collections.abc import Sequence

MOVED = {
    "lungmech.cli": "lungmech.app.cli",
    "lungmech.console": "lungmech.app.console",
    "lungmech.constraints": "lungmech.fem.constraints",
    "lungmech.convergence": "lungmech.fem.convergence",
    "lungmech.destination": "lungmech.parallel.destination",
    "lungmech.dynamics": "lungmech.fem.dynamics",
    "lungmech.formulations": "lungmech.fem.formulations",
    "lungmech.geometry": "lungmech.mesh",
    "lungmech.gravity": "lungmech.lung.gravity",
    "lungmech.inverse": "lungmech.lung.inverse",
    "lungmech.kinematics": "lungmech.fem.kinematics",
    "lungmech.limits": "lungmech.fem.limits",
    "lungmech.linear": "lungmech.fem.linear",
    "lungmech.loads": "lungmech.fem.loads",
    "lungmech.lung_shape": "lungmech.mesh.lung_shape",
    "lungmech.materials": "lungmech.fem.materials",
    "lungmech.modal": "lungmech.fem.modal",
    "lungmech.model": "lungmech.fem.model",
    "lungmech.output": "lungmech.app.output",
    "lungmech.plot": "lungmech.app.plot",
    "lungmech.quantities": "lungmech.fem.quantities",
    "lungmech.ramp": "lungmech.fem.ramp",
    "lungmech.registration.commands": "lungmech.app.registration_cli",
    "lungmech.registration.nodes": "lungmech.mesh.nodes",
    "lungmech.registration.workflow": "lungmech.app.registration",
    "lungmech.rom.layout": "lungmech.parallel.layout",
    "lungmech.rom.scene": "lungmech.app.reduce",
    "lungmech.run": "lungmech.app.run",
    "lungmech.scene": "lungmech.app.scene",
    "lungmech.solver": "lungmech.fem.solver",
}


class _Forward(importlib.abc.Loader):
    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        return types.ModuleType(spec.name)

    def exec_module(self, module: types.ModuleType) -> None:
        target = MOVED[module.__name__]
        warnings.warn(
            f"{module.__name__} moved to {target}; the old path goes in lungmech 0.3", DeprecationWarning, stacklevel=2
        )
        new = importlib.import_module(target)
        module.__getattr__ = lambda name: getattr(new, name)  # type: ignore[method-assign]  # the alias forwards
        module.__dir__ = lambda: dir(new)  # type: ignore[method-assign]  # the alias lists the new module's names
        module.__doc__ = f"Deprecated alias of {target}."


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(
        self, name: str, path: Sequence[str] | None = None, target: types.ModuleType | None = None
    ) -> importlib.machinery.ModuleSpec | None:
        return importlib.machinery.ModuleSpec(name, _Forward()) if name in MOVED else None


def install() -> None:
    """Put the forwarding finder last on ``sys.meta_path`` (real modules always win)."""
    if not any(isinstance(finder, _Finder) for finder in sys.meta_path):
        sys.meta_path.append(_Finder())
