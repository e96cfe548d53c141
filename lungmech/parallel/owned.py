"""The entries of a function this rank owns.

A DOLFINx function's array holds the rank's owned entries first, then its ghosts' copies:
``index_map.size_local`` blocks of ``index_map_bs`` values each, then the ghosts. Everything in
lungmech that works on distributed rows (bases, snapshots, kept fields, sensitivities) takes
the owned part alone, so that each global entry is counted once over the ranks.
"""

from __future__ import annotations

import numpy as np
from dolfinx import fem

__all__ = ["owned_size", "owned_values"]


def owned_size(space: fem.FunctionSpace) -> int:
    """The number of entries of a function on ``space`` this rank owns: size_local × bs."""
    return space.dofmap.index_map.size_local * space.dofmap.index_map_bs


def owned_values(function: fem.Function) -> np.ndarray:
    """A copy of the entries of ``function`` this rank owns (its ghosts' left out)."""
    return function.x.array[: owned_size(function.function_space)].copy()
