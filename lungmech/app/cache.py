"""A folder of results kept by their content: what was computed once is read back the next time.

An entry's name is the SHA-256 of what determines it (:func:`key`: a scene's physics, the
parameter values, the discretisation, the version of the code that computed it), so a second
trade with another tolerance or other candidates finds the reference solves of the first, and
an interrupted one resumes from the last entry written. An entry is whole or absent: it is
written beside its place and moved there in one rename.

The folder is lungmech's: it holds a ``CACHEDIR.TAG`` (the cache directory standard, which
backup tools skip), and a folder that exists without one is refused rather than written into.
Its entries can be deleted at any time. Entries are written by rank 0; every rank reads them.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from mpi4py import MPI

import numpy as np

import lungmech
from lungmech.errors import OutputError
from lungmech.parallel import on_root

__all__ = ["ANSWERING", "BUILDING", "Cache", "code_version", "default_folder", "key"]

TAG = "CACHEDIR.TAG"
SIGNATURE = "Signature: 8a477f597d28d172789f06886806bc55"  # what the standard asks the tag to begin with
SOLVING = ("fem", "lung", "mesh", "parallel", "rom")  # the sub-packages a solve runs in
# the application's modules that say what a full answer is: the scene read, its model built at
# a discretisation, the solve's numbers
ANSWERING = (
    *SOLVING,
    "app/answers.py",
    "app/run.py",
    "app/ladder.py",
    "app/scene.py",
    "app/scene_parameters.py",
    "app/table_checks.py",
)
BUILDING = (*ANSWERING, "app/reduce.py", "app/model_file.py")  # and a reduced model's build, and its file
DISPATCH = ("parallel/ensemble.py", "parallel/engine.py")  # where a solve runs, not what it answers


def default_folder() -> Path:
    """``$LUNGMECH_CACHE``, else ``$XDG_CACHE_HOME/lungmech``, else ``~/.cache/lungmech``."""
    if given := os.environ.get("LUNGMECH_CACHE"):
        return Path(given)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "lungmech"


def code_version(parts: tuple[str, ...] = ANSWERING) -> str:
    """The SHA-256 (16 hex digits) of lungmech's version and of the sources of ``parts`` —
    sub-packages ("fem") and modules ("app/run.py") — but :data:`DISPATCH`'s, which only say
    where a solve runs: a result computed by other code is another entry."""
    root = Path(lungmech.__file__).parent
    sha = hashlib.sha256(str(getattr(lungmech, "__version__", "")).encode())
    for part in parts:
        sources = [root / part] if part.endswith(".py") else sorted((root / part).rglob("*.py"))
        for source in sources:
            if source.relative_to(root).as_posix() in DISPATCH:
                continue
            sha.update(source.relative_to(root).as_posix().encode())
            sha.update(source.read_bytes())
    return sha.hexdigest()[:16]


def key(content: Any) -> str:
    """The name of an entry: the SHA-256 of ``content`` as canonical JSON (sorted keys)."""
    text = json.dumps(content, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


class Cache:
    """The content-keyed folder ``root`` (see the module's doc). Collective: make it, and call
    its methods but :meth:`path`, on all ranks of ``comm``."""

    def __init__(self, root: str | Path, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
        self.root = Path(root).expanduser().resolve()
        self.comm = comm
        on_root(comm, self._claim)

    def _claim(self) -> None:
        tag = self.root / TAG
        if self.root.exists() and not self.root.is_dir():
            raise OutputError(f"cache '{self.root}' is a file, not a folder")
        if self.root.is_dir() and any(self.root.iterdir()) and not tag.is_file():
            raise OutputError(
                f"cache '{self.root}' is a folder lungmech did not make (it has no {TAG}); "
                "name an empty or new folder for the cache"
            )
        self.root.mkdir(parents=True, exist_ok=True)
        if not tag.is_file():
            tag.write_text(f"{SIGNATURE}\n# lungmech's cache of computed results (see lungmech.app.cache)\n")

    def path(self, kind: str, name: str) -> Path:
        """Where the entry ``name`` of ``kind`` ("answers", "levels", …) lives."""
        return self.root / kind / name

    def read_json(self, kind: str, name: str) -> dict | None:
        """The JSON entry as rank 0 reads it, or None if absent (or unreadable: then it is
        computed again). Collective."""

        def read() -> dict | None:
            try:
                return json.loads(self.path(kind, f"{name}.json").read_text())
            except (OSError, ValueError):
                return None

        return self.comm.bcast(read() if self.comm.rank == 0 else None, root=0)

    def write_json(self, kind: str, name: str, content: dict) -> None:
        """Keep ``content`` as the entry ``name`` (rank 0 writes; whole or not at all)."""

        def write() -> None:
            target = self.path(kind, f"{name}.json")
            target.parent.mkdir(parents=True, exist_ok=True)
            with _beside(target) as partial:
                partial.write_text(json.dumps(content, indent=1) + "\n")

        on_root(self.comm, write)

    def array_names(self, kind: str, name: str) -> list[str] | None:
        """The names of the arrays the entry ``name`` (.npz) holds, as rank 0 reads its index;
        None if it is absent or unreadable (then it is computed again). Collective."""

        def names() -> list[str] | None:
            try:
                with np.load(self.path(kind, f"{name}.npz"), allow_pickle=False) as data:
                    return list(data.files)
            except (OSError, ValueError, zipfile.BadZipFile):
                return None

        return self.comm.bcast(names() if self.comm.rank == 0 else None, root=0)

    def read_arrays(self, kind: str, name: str) -> dict[str, np.ndarray] | None:
        """The arrays of the entry ``name`` (.npz) on rank 0 (None elsewhere, or if absent or
        unreadable). Not collective: rank 0 alone reads."""
        if self.comm.rank != 0:
            return None
        try:
            with np.load(self.path(kind, f"{name}.npz"), allow_pickle=False) as data:
                return {field: data[field] for field in data.files}
        except (OSError, ValueError, zipfile.BadZipFile):
            return None

    def write_arrays(self, kind: str, name: str, arrays: dict[str, np.ndarray] | None) -> None:
        """Keep ``arrays`` (given on rank 0) as the entry ``name`` (.npz; rank 0 writes, whole
        or not at all). Collective."""

        def write() -> None:
            assert arrays is not None  # (given on rank 0)
            target = self.path(kind, f"{name}.npz")
            target.parent.mkdir(parents=True, exist_ok=True)
            with _beside(target) as partial, partial.open("wb") as stream:
                np.savez(stream, allow_pickle=False, **arrays)

        on_root(self.comm, write)

    def folder(self, kind: str, name: str, fill: Callable[[Path], None]) -> Path:
        """The entry ``name``: a folder ``fill(staging)`` writes (collective; called on every
        rank with rank 0's staging folder) unless it exists already."""
        target = self.path(kind, name)
        if self.comm.bcast(target.is_dir() if self.comm.rank == 0 else None, root=0):
            return target
        staging = self.comm.bcast(_staging(target) if self.comm.rank == 0 else None, root=0)
        try:
            fill(Path(staging))
        except BaseException:
            on_root(self.comm, lambda: shutil.rmtree(staging, ignore_errors=True))
            raise
        on_root(self.comm, lambda: _publish(Path(staging), target))
        return target


def _staging(target: Path) -> str:
    target.parent.mkdir(parents=True, exist_ok=True)
    return tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent)


def _publish(staging: Path, target: Path) -> None:
    try:
        staging.rename(target)
    except OSError:  # another run put it there first: the same content
        shutil.rmtree(staging, ignore_errors=True)


@contextmanager
def _beside(target: Path) -> Iterator[Path]:
    """A file beside ``target`` that replaces it when the block ends without an error."""
    partial = target.with_name(f".{target.name}.{os.getpid()}.partial")
    try:
        yield partial
        partial.replace(target)
    finally:
        partial.unlink(missing_ok=True)
