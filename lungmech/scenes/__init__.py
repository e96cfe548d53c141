"""The scenes bundled with lungmech, which a command names without a path (``lungmech run
lung_breathing_parameters``): a file of that name, where there is one, is the user's and comes
first."""

from __future__ import annotations

from importlib import resources
from importlib.resources.abc import Traversable

__all__ = ["bundled", "names"]


def names() -> list[str]:
    """The bundled scenes' names (their file names without ``.toml``), sorted."""
    return sorted(p.name.removesuffix(".toml") for p in resources.files(__name__).iterdir() if p.name.endswith(".toml"))


def bundled(name: str) -> Traversable | None:
    """The bundled scene ``name`` (with or without ``.toml``), or None if there is none."""
    stem = name.removesuffix(".toml")
    return resources.files(__name__) / f"{stem}.toml" if stem in names() else None
