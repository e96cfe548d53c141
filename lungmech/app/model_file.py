"""What a model file holds of its scene: the scene itself and every file it reads, as data.

A model file (:mod:`lungmech.rom.store`) built by ``lungmech rom build`` carries its scene's table
and the bytes of the files the scene reads (the mesh and its companions, cell data, label
images), so that ``lungmech rom solve model.npz`` needs nothing else. :func:`embedded_scene`
unpacks them into a private temporary folder for the duration of a block; every embedded name
must be one lungmech writes (:func:`embedded_name`), and nothing is ever written outside that
folder.
"""

from __future__ import annotations

import contextlib
import copy
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import cast

from mpi4py import MPI

import numpy as np

from lungmech.app import scene as scenes
from lungmech.app.scene import ImageLabel, Scene
from lungmech.errors import ModelFileError
from lungmech.mesh.files import companions
from lungmech.parallel import on_root
from lungmech.registration.image import companions as image_companions
from lungmech.rom import store

__all__ = ["embedded_name", "embedded_names", "embedded_scene", "file_bytes", "scene_record"]


def embedded_names(scene: Scene) -> dict[str, str]:
    """Where each file the scene reads goes inside the model file: the mesh (with its companions)
    under mesh/, a library's shape modes under shape/, a file of cell values (Φs0, κ, …) under
    data/<key>/."""
    names = {}
    if "file" in scene.geometry:
        mesh = Path(scene.geometry["file"])
        for part in [mesh, *(p for p in companions(mesh) if p.exists())]:
            names[f"mesh/{part.name}"] = str(part)
    if "shape_modes" in scene.geometry:
        names[f"shape/{Path(scene.geometry['shape_modes']).name}"] = scene.geometry["shape_modes"]
    for key, path in scenes.cell_data(scene.formulation).items():
        names[f"data/{key}/{path.name}"] = str(path)
    for parameter in scene.parameters:  # label images of regions, with their data files
        marker = getattr(parameter.region, "marker", None)
        if isinstance(marker, ImageLabel):
            data = [Path(marker.path).with_name(name) for name in image_companions(marker.path)]
            for file in [marker.path, *(str(d) for d in data if d.exists())]:
                names[f"regions/{Path(file).name}"] = str(file)
    return names


def scene_record(scene: Scene, fingerprint: str, parameters: list[dict]) -> dict:
    """What a model file's metadata says of its scene: its file and title, the fingerprint of
    the mesh the model was built on (an imaged body's: the image's), its loads' count, its
    parameters (described), its table and the embedded names of the files it reads."""
    return {
        "scene": str(Path(scene.source).resolve()) if scene.source else None,
        "title": scene.title,
        "imaged_fingerprint": fingerprint,
        "loads": len(scene.loads),
        "parameters": parameters,
        "scene_table": scene.table,
        "files": embedded_names(scene),
    }


def file_bytes(scene: Scene, comm: MPI.Comm) -> dict[str, np.ndarray | None]:
    """The bytes of the scene's files (rank 0; None on the others)."""
    names = embedded_names(scene)
    if comm.rank != 0:
        return dict.fromkeys(names)
    return {name: np.frombuffer(Path(source).read_bytes(), dtype=np.uint8) for name, source in names.items()}


@contextlib.contextmanager
def embedded_scene(
    path: str | Path, comm: MPI.Comm = MPI.COMM_WORLD, content: tuple[dict, dict] | None = None
) -> Iterator[Scene]:
    """The scene a model file holds, with its files unpacked into a private temporary folder for
    the duration of the block (rank 0 unpacks; the ranks must share that folder's file system).
    Collective. ``content``: what :func:`lungmech.rom.store.read_on_root` gave, when the caller
    has read the file already.

    The file is data: each embedded file's name must be one lungmech writes (:func:`embedded_name`),
    and it is created new inside the folder, never followed through a link; anything else refuses
    the model file before a byte is written.
    """
    metadata, arrays = content if content is not None else store.read_on_root(path, comm)
    extra = metadata["extra"]
    if "scene_table" not in extra:
        raise ModelFileError(f"{path} holds no scene (built before lungmech 0.2); name the scene after the model file")
    files = extra.get("files")
    if not isinstance(files, dict) or not isinstance(extra["scene_table"], dict):
        raise ModelFileError(f"'{path}' is damaged: its scene or its list of files is not a table")
    for name in files:
        embedded_name(path, name, arrays)
    folder = comm.bcast(tempfile.mkdtemp(prefix="lungmech-model-") if comm.rank == 0 else None)  # mode 0700
    try:

        def unpack() -> None:
            for name in files:
                target = Path(folder, *name.split("/"))
                target.parent.mkdir(parents=True, exist_ok=True)
                # O_EXCL | O_NOFOLLOW: a new file, not one a link points to (none can be there).
                flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW
                with os.fdopen(os.open(target, flags, 0o600), "wb") as stream:
                    stream.write(cast(np.ndarray, arrays[f"file:{name}"]).tobytes())  # rank 0 holds the bytes

        on_root(comm, unpack)
        table = copy.deepcopy(extra["scene_table"])
        for name, source in files.items():
            unpacked = str(Path(folder, *name.split("/")))
            if name.startswith("mesh/") and Path(str(source)).name == Path(table["geometry"].get("file", "")).name:
                table["geometry"]["file"] = unpacked
            if name.startswith("shape/"):  # a library's shape modes
                table["geometry"]["shape_modes"] = unpacked
            if name.startswith("data/"):  # data/<key>/<file>: a file of cell values (Φs0, κ, …)
                table["formulation"][name.split("/")[1]] = unpacked
            for entry in table.get("parameters", {}).values():
                region = entry.get("region")
                if isinstance(region, dict) and Path(str(region.get("image", ""))).name == Path(str(source)).name:
                    region["image"] = unpacked
        yield scenes.parse(table, folder=Path(folder))
    except BaseException:
        # Not collective: a failure (or Ctrl-C) may have reached this rank alone, and a barrier
        # here would hang it; the folder is temporary, so rank 0 removes it as it can.
        if comm.rank == 0:
            shutil.rmtree(folder, ignore_errors=True)
        raise
    comm.barrier()  # every rank is done with the files
    if comm.rank == 0:
        shutil.rmtree(folder, ignore_errors=True)


_PLACES = {
    "mesh": 2,
    "regions": 2,
    "shape": 2,
    "data": 3,
}  # where lungmech puts a scene's files, and the parts of their names


def embedded_name(path: str | Path, name: object, arrays: dict) -> None:
    """Refuse, in one line, a model file whose embedded file ``name`` is not one lungmech writes —
    ``mesh/<file>``, ``regions/<file>``, ``shape/<file>`` or ``data/<key>/<file>``, with plain names: relative, no ``..``, no empty part, no backslash or NUL — or has no bytes."""
    parts = name.split("/") if isinstance(name, str) else []
    plain = all(part not in ("", ".", "..") and "\\" not in part and "\0" not in part for part in parts)
    expected = _PLACES.get(parts[0]) if parts else None
    if not (plain and len(parts) == expected and (expected == 2 or parts[1].isidentifier())):
        raise ModelFileError(
            f"'{path}' is refused: it names an embedded file {name!r}, which is not a name lungmech writes "
            "(mesh/<file>, regions/<file>, shape/<file>, data/<key>/<file>); a model file never writes outside its own folder"
        )
    if f"file:{name}" not in arrays:
        raise ModelFileError(f"'{path}' is damaged: it lists the embedded file '{name}' but holds no bytes for it")
