"""Where results go: output folders and files that lungmech may create or replace.

A user's files are never at risk. Results are written into a staging folder next to the target
and moved into place only when the whole job has succeeded; an error or an interrupt removes the
staging folder and leaves the target as it was.

* A **folder** may be replaced only if it is empty, or if lungmech wrote it and it still holds
  nothing but what lungmech wrote there: the marker file ``.lungmech.json`` lists every file with
  its size and SHA-256, and any other entry, or any changed file, makes the folder the user's.
  Never the current folder or a folder holding it, and never a folder holding an input.
* A **file** (a reduced model, a mesh, an image) may be replaced only if lungmech wrote it (the
  writer says how to recognise its own files), and never if it is an input.
* A staging folder left by a killed run is removed by the next run into the same place (or
  reported, if its run may still be alive or ran on another host).

Every check happens before the work starts, on rank 0, and its error is raised on every rank.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import json
import logging
import os
import secrets
import shutil
import signal
import socket
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

from mpi4py import MPI

from lungmech.errors import OutputError
from lungmech.parallel import on_root

__all__ = ["MARKER", "check_folder", "output_file", "output_folder", "resolve"]

MARKER = ".lungmech.json"
_STAGING = "lungmech-staging"
_OLD = "lungmech-old"

log = logging.getLogger("lungmech")


def resolve(path: str | os.PathLike) -> Path:
    """The absolute path, symbolic links and ``~`` resolved (the path need not exist)."""
    return Path(path).expanduser().resolve()


# --- checks (local, on one rank) -------------------------------------------------------------


def check_location(target: Path, inputs: Iterable[Path], what: str = "output folder") -> None:
    """Refuse a target that is, or holds, the current folder or one of ``inputs``."""
    target = resolve(target)
    here = Path.cwd().resolve()
    if _within(here, target):
        where = "is the current folder" if here == target else f"holds the current folder '{here}'"
        raise OutputError(
            f"{what} '{target}' {where}; lungmech will not replace it: name a folder of its own"
        )
    for source in inputs:
        source = resolve(source)
        if _within(source, target):
            where = "is" if source == target else "holds"
            raise OutputError(f"{what} '{target}' {where} the input '{source}'; name another output")


def check_folder(target: Path) -> None:
    """Refuse to replace ``target`` unless it is absent, empty, or lungmech's and unchanged."""
    target = resolve(target)
    if not (target.exists() or target.is_symlink()):
        return
    if not target.is_dir():
        raise OutputError(f"output folder '{target}' exists and is not a folder; name a folder")
    entries = list(_entries(target))
    if not entries:
        return
    manifest = _manifest(target)
    if manifest is None:
        shown = ", ".join(f"'{e}'" for e in entries[:3]) + (
            f" and {len(entries) - 3} more" if len(entries) > 3 else ""
        )
        raise OutputError(
            f"output folder '{target}' is not empty and was not written by lungmech (it holds {shown}); "
            "lungmech replaces only empty folders and its own: name another output folder"
        )
    files, folders = manifest
    for entry in entries:
        path = target / entry
        if entry == MARKER:
            continue
        folder = path.is_dir() and not path.is_symlink()
        if entry not in (folders if folder else files) or path.is_symlink():
            raise OutputError(
                f"output folder '{target}' holds '{entry}', which lungmech did not write; "
                "move it away or name another output folder"
            )
        if folder:
            continue
        size, digest = files[entry]
        if path.stat().st_size != size or _sha256(path) != digest:
            raise OutputError(
                f"'{path}' was changed after lungmech wrote it; move it away or name another output folder"
            )


def _within(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def _entries(folder: Path) -> Iterator[str]:
    """Every file and folder below ``folder`` (relative POSIX paths), links not followed."""
    try:
        for root, folders, files in os.walk(folder, onerror=_raise):
            relative = Path(root).relative_to(folder)
            for name in sorted(folders) + sorted(files):
                yield (relative / name).as_posix()
    except OSError as e:
        raise OutputError(f"cannot look into output folder '{folder}': {e.strerror or e}") from None


def _raise(error: OSError) -> None:
    raise error


def _manifest(folder: Path) -> tuple[dict[str, tuple[int, str]], set[str]] | None:
    """(files: name -> (size, sha256), folders) from the marker of a finished lungmech folder."""
    try:
        marker = json.loads((folder / MARKER).read_text())
        if marker.get("written_by") != "lungmech" or marker.get("state") != "complete":
            return None
        files = {str(name): (int(size), str(digest)) for name, (size, digest) in marker["files"].items()}
        return files, {str(name) for name in marker["folders"]}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _write_marker(folder: Path, state: str, **extra) -> None:
    marker = {
        "written_by": "lungmech",
        "state": state,
        "host": socket.gethostname(),
        "pid": os.getpid(),
        **extra,
    }
    (folder / MARKER).write_text(json.dumps(marker, indent=1) + "\n")


def _seal(folder: Path, command: str) -> None:
    """Write the marker of a finished folder: every file with its size and SHA-256."""
    files, folders = {}, []
    for entry in _entries(folder):
        path = folder / entry
        if entry == MARKER:
            continue
        if path.is_dir():
            folders.append(entry)
        else:
            files[entry] = [path.stat().st_size, _sha256(path)]
    from lungmech import __version__

    _write_marker(
        folder,
        "complete",
        lungmech=__version__,
        command=command,
        written=datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        files=files,
        folders=folders,
    )


# --- staging ---------------------------------------------------------------------------------


def _staging(target: Path) -> Path:
    """A new, empty staging folder next to ``target``, marked with this process."""
    name = f".{target.name}.{_STAGING}-{os.getpid()}-{secrets.token_hex(3)}"
    staging = target.parent / name
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        staging.mkdir()
        _write_marker(staging, "staging", target=str(target))
    except OSError as e:
        shutil.rmtree(staging, ignore_errors=True)
        raise OutputError(f"cannot write into '{target.parent}': {e.strerror or e}") from None
    return staging


def _recover(target: Path) -> None:
    """Deal with what killed runs left next to ``target``: remove their staging folders,
    finish an interrupted swap; refuse while another live run is writing there."""
    parent = target.parent
    if not parent.is_dir():
        return
    for sibling in sorted(parent.iterdir()):
        prefix = f".{target.name}."
        if not sibling.name.startswith(prefix):
            continue
        kind = sibling.name[len(prefix) :].rsplit("-", 2)[0]
        if kind not in (_STAGING, _OLD):
            continue
        if kind == _OLD:  # a swap stopped between its two renames
            if not target.exists():
                os.rename(sibling, target)
                log.warning("lungmech: restored '%s' from an interrupted replacement", target)
            else:
                shutil.rmtree(sibling, ignore_errors=True)
            continue
        host, pid = _owner(sibling)
        if host not in (None, socket.gethostname()):
            raise OutputError(
                f"'{sibling}' was left by a lungmech run on host {host}; remove it if that run has ended"
            )
        if pid is not None and pid != os.getpid() and _alive(pid):
            raise OutputError(
                f"another lungmech run (process {pid}) is writing '{target}' (into '{sibling.name}'); "
                "wait for it to finish, or name another output"
            )
        shutil.rmtree(sibling, ignore_errors=True)
        log.warning("lungmech: removed '%s', left by an interrupted run", sibling.name)


def _owner(staging: Path) -> tuple[str | None, int | None]:
    try:
        marker = json.loads((staging / MARKER).read_text())
        return str(marker["host"]), int(marker["pid"])
    except (OSError, ValueError, KeyError, TypeError):
        try:  # killed before its marker was written: the pid is in the name
            return None, int(staging.name.rsplit("-", 2)[1])
        except (IndexError, ValueError):
            return None, None


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs, and (where /proc tells) runs Python: a reused pid does not count."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    try:
        command = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return True  # no /proc here: assume the worst
    return b"python" in command or b"lungmech" in command


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM wait until the block is done (a swap is never left half-way)."""
    held = {signal.SIGINT, signal.SIGTERM}
    try:
        previous = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    except (ValueError, OSError):  # not the main thread: nothing to hold
        yield
        return
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _remove_staging(staging: Path | None, comm: MPI.Comm, everywhere: bool = False) -> None:
    """Not collective: a failing or interrupted rank may be alone here. Rank 0 removes the
    staging folder; on an interrupt any rank does (rank 0 may be stuck in a collective call)."""
    if staging is not None and (comm.rank == 0 or everywhere):
        shutil.rmtree(staging, ignore_errors=True)


def _unwritable(error: OSError, staging: Path, target: Path) -> str:
    """The message of a failed write, naming the file as the user will know it."""
    name = error.filename
    if name is not None:
        try:
            name = target / Path(name).resolve().relative_to(staging.resolve())
        except ValueError:
            pass
    what = f"'{name}'" if name is not None else f"'{target}'"
    return f"cannot write {what}: {error.strerror or error}"


# --- the two context managers ----------------------------------------------------------------


@contextlib.contextmanager
def output_folder(
    target: str | os.PathLike,
    comm: MPI.Comm = MPI.COMM_WORLD,
    inputs: Sequence[str | os.PathLike] = (),
    command: str = "",
) -> Iterator[Path]:
    """Collective: check ``target`` and yield an empty staging folder for the results, which
    replaces ``target`` when the block succeeds; on an error or interrupt it is removed and
    ``target`` stays as it was. ``inputs`` are the job's input files and folders."""
    target = resolve(target)

    def prepare() -> Path:
        check_location(target, inputs)
        _recover(target)
        check_folder(target)
        return _staging(target)

    staging = comm.bcast(on_root(comm, prepare), root=0)
    try:
        yield staging
    except OSError as error:  # a full or read-only disk, say: name the file it would have been
        _remove_staging(staging, comm)
        raise OutputError(_unwritable(error, staging, target)) from None
    except BaseException as error:
        _remove_staging(staging, comm, everywhere=isinstance(error, KeyboardInterrupt))
        raise

    def publish() -> None:
        try:
            _seal(staging, command)
            check_folder(target)  # again: it may have changed during the run
        except OutputError as e:
            stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
            kept = target.with_name(f"{target.name}-{stamp}-{secrets.token_hex(2)}")
            os.rename(staging, kept)
            raise OutputError(f"{e}; this run's results are in '{kept}'") from None
        except OSError as e:
            shutil.rmtree(staging, ignore_errors=True)
            raise OutputError(f"cannot write into '{staging}': {e.strerror or e}") from None
        old = target.parent / f".{target.name}.{_OLD}-{os.getpid()}-{secrets.token_hex(3)}"
        with _signals_held():
            moved = target.exists() or target.is_symlink()
            if moved:
                os.rename(target, old)
            os.rename(staging, target)
        if moved:
            shutil.rmtree(old, ignore_errors=True)

    _barrier_then(comm, publish, staging)


@contextlib.contextmanager
def output_file(
    target: str | os.PathLike,
    comm: MPI.Comm = MPI.COMM_WORLD,
    inputs: Sequence[str | os.PathLike] = (),
    ours: Callable[[Path], bool] = lambda path: False,
    companions: Sequence[str] = (),
) -> Iterator[Path]:
    """Collective: check ``target`` and yield the path to write it to (inside a staging folder,
    same name), moved into place when the block succeeds.

    ``ours(path)`` tells whether an existing file is lungmech's (only then is it replaced).
    ``companions`` are names of further files written next to it (an ``.xdmf``'s ``.h5``), which
    move with it; an existing companion is replaced only alongside a file of lungmech's.
    """
    target = resolve(target)
    others = [target.with_name(name) for name in companions]

    def prepare() -> Path:
        check_location(target, inputs, "output file")
        _check_file(target, others, ours)
        _recover(target)
        return _staging(target)

    staging = comm.bcast(on_root(comm, prepare), root=0)
    try:
        yield staging / target.name
    except OSError as error:
        _remove_staging(staging, comm)
        raise OutputError(_unwritable(error, staging, target.parent)) from None
    except BaseException as error:
        _remove_staging(staging, comm, everywhere=isinstance(error, KeyboardInterrupt))
        raise

    def publish() -> None:
        written = [p for p in (staging / target.name, *(staging / n for n in companions)) if p.exists()]
        if staging / target.name not in written:
            raise OutputError(f"nothing was written to '{target}'")
        _check_file(target, others, ours)  # again: it may have appeared during the run
        with _signals_held():
            for path in sorted(written, key=lambda p: p.name == target.name):  # the main file last
                os.replace(path, target.with_name(path.name))
        shutil.rmtree(staging, ignore_errors=True)

    _barrier_then(comm, publish, staging)


def _check_file(target: Path, others: Sequence[Path], ours: Callable[[Path], bool]) -> None:
    for path in (target, *others):
        if path.is_dir():
            raise OutputError(f"output '{path}' is a folder; name a file")
    mine = target.is_file() and ours(target)
    if (target.exists() or target.is_symlink()) and not mine:
        raise OutputError(
            f"'{target}' exists and was not written by lungmech, which never overwrites it: "
            "name another file or move it away"
        )
    for path in others:
        if (path.exists() or path.is_symlink()) and not mine:
            raise OutputError(
                f"'{path}' exists and does not belong to a file lungmech wrote: name another "
                "file or move it away"
            )


def _barrier_then(comm: MPI.Comm, publish: Callable[[], None], staging: Path) -> None:
    """Every rank has finished writing; rank 0 publishes; its error is raised everywhere."""
    comm.Barrier()
    try:
        on_root(comm, publish)
    except BaseException:
        _remove_staging(staging, comm)
        raise
