"""What only the whole body gives a hyper-reduced model: computed offline, kept, given back online.

A hyper-reduced model works on a few sampled cells, but some of its operators are integrals over
the whole body, exact in its reduced coordinates z = (q, imposed factors): the volume (a cubic
of z), the probes (linear), the affine integrals of state-dependent loads (balanced gravity's
mass moments, and their constant derivatives), the Gram matrices of its error indicator; and a
few numbers: the smallest cell size h of the round-off floor, which constraints impose
displacements. Each is asked for by name with the function that computes it:

* :class:`OnMesh` computes it on the full model (O(k) assemblies, offline) and keeps it;
  :meth:`OnMesh.arrays` gives all it kept as named arrays of reduced size, for a model file;
* :class:`Stored` gives it back from those arrays, with no full mesh, and refuses a name the
  file does not hold (a file of another build).

The imposed displacements x₀ = r + D a on the sampled dofs are mesh-sized and cell-wise: they
travel with the body (:mod:`lungmech.rom.body`), and :meth:`imposed` gives them on the model's
own dofs in both cases.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Protocol

import numpy as np

from lungmech.errors import ModelFileError

__all__ = ["OnMesh", "Stored", "Whole"]

Arrays = tuple[np.ndarray, ...]


class Whole(Protocol):
    """What a hyper-reduced solver and its outputs ask of the whole body."""

    def imposed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(r, D, constraints): x₀ = r + D a on the model's local dofs, a the factors of
        ``constraints`` (:func:`lungmech.rom.outputs.imposed_directions`)."""
        ...

    def get(self, name: str, compute: Callable[[], Arrays]) -> Arrays:
        """The arrays named ``name``, which ``compute()`` gives on the full model."""
        ...


class OnMesh:
    """Computed on the full ``model``; ``imposed`` its :func:`~lungmech.rom.outputs.imposed_directions`."""

    def __init__(self, imposed: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        self._imposed = imposed
        self._kept: dict[str, Arrays] = {}

    def imposed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self._imposed

    def get(self, name: str, compute: Callable[[], Arrays]) -> Arrays:
        """``compute()`` (a tuple of arrays), once; kept under ``name``."""
        if name not in self._kept:
            self._kept[name] = tuple(np.asarray(a, dtype=float) for a in compute())
        return self._kept[name]

    def arrays(self) -> dict[str, np.ndarray]:
        """Everything computed so far, as arrays named ``<name>/<i>``, and the constraints."""
        named = {f"{name}/{i}": a for name, values in self._kept.items() for i, a in enumerate(values)}
        return named | {"constraints": np.asarray(self._imposed[2], dtype=np.int64)}


class Stored:
    """Given back from :meth:`OnMesh.arrays` (every rank holds them), with the body's r and D
    (local arrays of its model's space); ``source`` names the file in messages."""

    def __init__(
        self, arrays: Mapping[str, np.ndarray], start: np.ndarray, directions: np.ndarray, source: str
    ) -> None:
        self._imposed = (start, directions, np.asarray(arrays["constraints"], dtype=int))
        self._arrays, self._source = arrays, source

    def imposed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self._imposed

    def get(self, name: str, compute: Callable[[], Arrays]) -> Arrays:
        """The arrays kept under ``name``; ``compute`` is not called (it needs the full mesh)."""
        count = 0
        while f"{name}/{count}" in self._arrays:
            count += 1
        if not count:
            raise ModelFileError(f"'{self._source}' holds no '{name}' of its reduced model: rebuild it")
        return tuple(np.asarray(self._arrays[f"{name}/{i}"]) for i in range(count))
