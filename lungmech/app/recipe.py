"""The recipe of a patient's reduced model, read from a model file: rebuilt for the patient.

A reduced model is built for one mesh, and a patient's lung is a new mesh (the reference lung
registered onto its image), so ``lungmech personalise --model FILE`` does not reuse the file's
basis: it reads how the file was made — a POD basis of ``size`` vectors from ``training`` full
breaths, hyper-reduced by ECSW at τ (or not) — and on which scene (its physics, its reference
lung at its mesh size h), and builds the same for the patient. The file is what ``lungmech
trade`` chose for a tolerance (its ``model.npz``), or any ``lungmech rom build`` of the scene.

Refused in one line: a file that is not a reduced model, a basis kind other than POD (the
patient's model is trained on its own breaths), and a file built for other physics than the
scene given beside it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from mpi4py import MPI

from lungmech.app.model_file import embedded_scene
from lungmech.app.reduce import check_physics
from lungmech.app.scene import Scene, physics
from lungmech.errors import ModelFileError
from lungmech.rom import store

__all__ = ["Recipe", "recipe_scene"]


@dataclass(frozen=True)
class Recipe:
    """How a reduced model was made: a POD basis of ``size`` vectors from ``training`` full
    solves, ECSW at ``tau`` (None: Galerkin on the whole mesh), read from ``source``."""

    size: int
    training: int
    tau: float | None
    source: str

    def describe(self) -> dict:
        return {"basis_size": self.size, "training": self.training, "tau": self.tau, "from": self.source}


@contextlib.contextmanager
def recipe_scene(
    path: str | Path, scene: Scene | None, comm: MPI.Comm = MPI.COMM_WORLD
) -> Iterator[tuple[Recipe, Scene]]:
    """The recipe of the model file ``path`` and the scene to personalise with it: ``scene``
    (which must model the file's physics), or else the file's own (its reference lung at its
    mesh size), for the duration of the block. Collective."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"model file '{path}' not found")
    content = store.read_on_root(path, comm)
    metadata = content[0]
    record = metadata.get("extra", {}).get("reduced")
    if record is None or not record.get("training"):
        raise ModelFileError(f"'{path}' is not a reduced model built from training solves (lungmech rom build, trade)")
    if metadata["kind"] != "pod":
        raise ModelFileError(
            f"'{path}' holds a {metadata['kind']} basis; a patient's model is a POD of its own breaths: give a POD model"
        )
    hyper = record.get("hyper") or {}
    recipe = Recipe(int(metadata["size"]), len(record["training"]), hyper.get("tolerance"), str(path))
    with embedded_scene(path, comm, content=content) as built:
        if scene is None:
            yield recipe, built
            return
        check_physics(path, physics(built), scene)
    yield recipe, scene
