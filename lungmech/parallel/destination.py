"""Where results go: output folders and files that lungmech may create or replace.

A user's files are never at risk. Results are written into a staging folder next to the target
and moved into place only when the whole job has succeeded; an error or an interrupt removes the
staging folder (and any parent folder the job created) and leaves the target as it was.

* A **folder** may be replaced only if it is empty, or if lungmech wrote it and it still holds
  nothing but what lungmech wrote there: the marker file ``.lungmech.json`` lists every file with
  its size and SHA-256, and any other entry, or any changed file, makes the folder the user's.
  Never the current folder or a folder holding it, and never a folder holding an input.
* A **file** (a reduced model, a mesh, an image) may be replaced only if lungmech wrote it and it
  is unchanged (the writer records a digest of what it wrote and says how to check it), and never
  if it is an input. Files written alongside it (an ``.xdmf``'s ``.h5``) move with it.
* What a killed run left next to a target — its staging folder, or a replaced result not yet
  removed — is recognised by its exact name *and* its marker, and cleaned up by the next run into
  the same place (or reported, if that run may still be alive or ran on another host). A folder
  of the user's that merely looks like one is never touched.

Every check happens before the work starts, on rank 0, and its error is raised on every rank.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import json
import logging
import os
import re
import secrets
import shutil
import signal
import socket
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

from mpi4py import MPI

from lungmech.errors import Interrupted, OutputError
from lungmech.parallel import deferred, on_root

__all__ = ["MARKER", "check_folder", "digest", "hold_signals_until_swap", "output_file", "output_folder", "resolve"]

MARKER = ".lungmech.json"
_STAGING, _OLD = "lungmech-staging", "lungmech-old"

log = logging.getLogger("lungmech")


def resolve(path: str | os.PathLike) -> Path:
    """The absolute path, symbolic links and ``~`` resolved (the path need not exist)."""
    return Path(path).expanduser().resolve()


def digest(path: str | os.PathLike) -> str:
    """The SHA-256 of a file's bytes (hex)."""
    sha = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            sha.update(block)
    return sha.hexdigest()


# --- checks (local, on one rank) -------------------------------------------------------------


def check_location(target: Path, inputs: Iterable[str | os.PathLike], what: str = "output folder") -> None:
    """Refuse a target that is, or holds, the current folder or one of ``inputs``."""
    target = resolve(target)
    here = Path.cwd().resolve()
    if _within(here, target):
        where = "is the current folder" if here == target else f"holds the current folder '{here}'"
        raise OutputError(f"{what} '{target}' {where}; lungmech will not replace it: name a folder of its own")
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
        shown = ", ".join(f"'{e}'" for e in entries[:3]) + (f" and {len(entries) - 3} more" if len(entries) > 3 else "")
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
        if not folder and (path.stat().st_size != files[entry][0] or digest(path) != files[entry][1]):
            raise OutputError(
                f"'{path}' was changed after lungmech wrote it; move it away or name another output folder"
            )


def _check_file(target: Path, others: Sequence[Path], ours: Callable[[Path], bool]) -> None:
    for path in (target, *others):
        if path.is_dir():
            raise OutputError(f"output '{path}' is a folder; name a file")
    mine = target.is_file() and ours(target)
    if (target.exists() or target.is_symlink()) and not mine:
        raise OutputError(
            f"'{target}' exists and was not written by lungmech, or was changed since: lungmech never "
            "overwrites it: name another file or move it away"
        )
    for path in others:
        if (path.exists() or path.is_symlink()) and not mine:
            raise OutputError(
                f"'{path}' exists and does not belong to a file lungmech wrote: name another file or move it away"
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


def _marker(folder: Path) -> dict | None:
    """A folder's lungmech marker, if it has a valid one."""
    try:
        marker = json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return marker if isinstance(marker, dict) and marker.get("written_by") == "lungmech" else None


def _manifest(folder: Path) -> tuple[dict[str, tuple[int, str]], set[str]] | None:
    """(files: name -> (size, sha256), folders) from the marker of a finished lungmech folder."""
    marker = _marker(folder)
    if marker is None or marker.get("state") != "complete":
        return None
    try:
        files = {str(name): (int(size), str(sha)) for name, (size, sha) in marker["files"].items()}
        return files, {str(name) for name in marker["folders"]}
    except (KeyError, TypeError, ValueError, AttributeError):
        return None


def _write_marker(folder: Path, state: str, **extra: object) -> None:
    marker = {"written_by": "lungmech", "state": state, "host": socket.gethostname(), "pid": os.getpid(), **extra}
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
            files[entry] = [path.stat().st_size, digest(path)]
    from lungmech import __version__

    _write_marker(
        folder,
        "complete",
        lungmech=__version__,
        command=command,
        files=files,
        folders=folders,
        written=datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
    )


# --- staging, and what killed runs leave -------------------------------------------------------


def _leftovers(target: Path) -> Iterator[tuple[str, Path, int]]:
    """(kind, folder, pid) of the folders a run into ``target`` makes next to it, by exact name."""
    pattern = re.compile(rf"\.{re.escape(target.name)}\.({_STAGING}|{_OLD})-(\d+)-[0-9a-f]{{6}}")
    if not target.parent.is_dir():
        return
    for sibling in sorted(target.parent.iterdir()):
        if (match := pattern.fullmatch(sibling.name)) and sibling.is_dir() and not sibling.is_symlink():
            yield match.group(1), sibling, int(match.group(2))


def _recover(target: Path) -> None:
    """Deal with what killed runs left next to ``target`` (recognised by name and marker):
    remove their staging folders, finish an interrupted swap; refuse while another live run is
    writing there. Anything else is left alone."""
    for kind, sibling, pid in _leftovers(target):
        marker = _marker(sibling)
        if kind == _OLD:  # a result moved away by a swap that stopped before removing it
            if marker is None or marker.get("state") != "complete":
                continue
            if not (target.exists() or target.is_symlink()):
                os.rename(sibling, target)
                log.warning("lungmech: restored '%s' from an interrupted replacement", target)
            else:
                shutil.rmtree(sibling, ignore_errors=True)
            continue
        if marker is None:  # killed between making the folder and marking it: it is still empty
            if not any(sibling.iterdir()):
                sibling.rmdir()
            continue
        host, owner = marker.get("host"), marker.get("pid", pid)
        if host != socket.gethostname():
            raise OutputError(f"'{sibling}' was left by a lungmech run on host {host}; remove it if that run has ended")
        if owner != os.getpid() and _alive(int(owner)):
            raise OutputError(
                f"another lungmech run (process {owner}) is writing '{target}' (into '{sibling.name}'); "
                "wait for it to finish, or name another output"
            )
        shutil.rmtree(sibling, ignore_errors=True)
        log.warning("lungmech: removed '%s', left by an interrupted run", sibling.name)


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
    # An empty command line is a process between fork and exec (or exiting): not known to be
    # someone else's, so its staging is kept.
    return not command or b"python" in command or b"lungmech" in command


class _Staging:
    """A new, marked staging folder next to ``target`` (made on rank 0), and the parent
    folders it had to create, which go again if the job fails."""

    def __init__(self, target: Path):
        missing = [p for p in [target.parent, *target.parent.parents] if not p.exists()]
        self.created = missing[::-1]  # outermost first
        self.path = target.parent / f".{target.name}.{_STAGING}-{os.getpid()}-{secrets.token_hex(3)}"
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            self.path.mkdir()
            _write_marker(self.path, "staging", target=str(target))
        except OSError as e:
            self.remove()
            raise OutputError(f"cannot write into '{target.parent}': {e.strerror or e}") from None

    def remove(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)
        for folder in reversed(self.created):
            with contextlib.suppress(OSError):  # only if still empty
                folder.rmdir()


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


PAUSE = "LUNGMECH_TEST_PAUSE_BEFORE_SWAP"  # seconds: a test hook (signals sent between the solve and the swap)


def _test_pause(comm: MPI.Comm) -> None:
    """Wait ``$LUNGMECH_TEST_PAUSE_BEFORE_SWAP`` seconds, saying so on standard output (rank 0),
    when the environment sets it: the moment where a test sends signals."""
    seconds = float(os.environ.get(PAUSE, "0") or 0)
    if seconds > 0:
        if comm.rank == 0:
            print(f"lungmech: test pause before the swap ({seconds:g} s)", flush=True)
        time.sleep(seconds)


def _signal_name() -> str:
    return signal.Signals(Interrupted.pending).name if Interrupted.pending else "a signal"


def _unwritable(error: OSError, staging: Path, target: Path) -> str:
    """The message of a failed write, naming the file as the user will know it."""
    name = error.filename
    if name is not None:
        with contextlib.suppress(ValueError):
            name = target / Path(name).resolve().relative_to(staging.resolve())
    return f"cannot write '{name if name is not None else target}': {error.strerror or error}"


@contextlib.contextmanager
def _staged(
    comm: MPI.Comm, base: Path, prepare: Callable[[], _Staging], publish: Callable[[Path], None], name: str = ""
) -> Iterator[Path]:
    """Collective: the shared life of a staged output. ``prepare`` checks and makes the staging
    (rank 0); the block writes into it (it gets the staging folder, or the file ``name`` in it);
    ``publish`` moves the result into place (rank 0). An error or an interrupt removes the
    staging folder. ``base`` is where the staging folder's content goes (for messages)."""
    _all_here(comm)
    staging = comm.bcast(on_root(comm, prepare), root=0)
    depth = Interrupted.deferring  # the block may hold signals until the swap (hold_signals_until_swap)
    try:
        yield staging.path / name if name else staging.path
        with deferred(comm) as agree:  # a signal now stops every rank before the swap, or none
            _test_pause(comm)
            comm.Barrier()  # every rank has finished writing
            agree()
            on_root(comm, lambda: publish(staging.path))
            if Interrupted.pending is not None:  # during the swap itself: the results are whole and in place
                log.warning("lungmech: %s arrived as the results were put in place; they are complete", _signal_name())
                Interrupted.pending = None
    except OSError as error:  # a full or read-only disk, say: name the file it would have been
        if comm.rank == 0:
            staging.remove()
        raise OutputError(_unwritable(error, staging.path, base)) from None
    except BaseException:
        # Not collective: a failing or interrupted rank may be alone here, and the command line
        # then ends the run, rank 0 with it, wherever rank 0 is (a collective call, say): so
        # every rank removes the staging folder (they share it; removing it twice is harmless).
        staging.remove()
        raise
    finally:
        Interrupted.deferring = depth


def _all_here(comm: MPI.Comm) -> None:
    """Collective: wait until every rank is here, in Python, where signals are handled, before
    rank 0 makes a staging folder. A rank that failed alone before its outputs (on its own
    scene, say) never comes; the command line then ends the run, and no staging folder is left."""
    if comm.size == 1:
        return
    request = comm.Ibarrier()
    while not request.Test():
        time.sleep(0.005)


def hold_signals_until_swap() -> None:
    """From now until the enclosing output's swap (:func:`output_folder`, :func:`output_file`),
    SIGINT and SIGTERM wait, and the ranks agree on them just before the swap: for a job whose
    computing is done and whose outputs (collective writes) begin, so that no signal cuts one
    rank alone between its last write and the swap."""
    Interrupted.deferring += 1


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

    def prepare() -> _Staging:
        check_location(target, inputs)
        _recover(target)
        check_folder(target)
        return _Staging(target)

    def publish(staging: Path) -> None:
        try:
            _seal(staging, command)
            check_folder(target)  # again: it may have changed during the run
        except OutputError as e:
            raise OutputError(f"{e}; this run's results are in '{_keep(staging, target)}'") from None
        try:
            with _signals_held():
                _swap(staging, target)
        except OSError as e:
            raise OutputError(
                f"cannot put the results in '{target}' ({e.strerror or e}); they are in '{_keep(staging, target)}'"
            ) from None

    with _staged(comm, target, prepare, publish) as staging:
        yield staging


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

    ``ours(path)`` tells whether an existing file is lungmech's and unchanged (only then is it
    replaced). ``companions`` are the names of the files written next to it (an ``.xdmf``'s
    ``.h5``, a MetaImage's data), which move with it; writing any other file is an error.
    """
    target = resolve(target)
    others = [target.with_name(name) for name in companions]

    def prepare() -> _Staging:
        check_location(target, inputs, "output file")
        _check_file(target, others, ours)
        _recover(target)
        return _Staging(target)

    def publish(staging: Path) -> None:
        names = {target.name, *companions}
        written = {p.name for p in staging.iterdir()} - {MARKER}
        if target.name not in written or written - names:
            raise OutputError(f"'{target}' was not written as expected (found {sorted(written)} in the staging folder)")
        _check_file(target, others, ours)  # again: it may have appeared during the run
        with _signals_held():
            for name in sorted(written, key=lambda n: n == target.name):  # the main file last
                os.replace(staging / name, target.with_name(name))
        shutil.rmtree(staging, ignore_errors=True)

    with _staged(comm, target.parent, prepare, publish, target.name) as path:
        yield path


def _swap(staging: Path, target: Path) -> None:
    """Put the staging folder's content at ``target``: a rename swap, or, where ``target``
    cannot be renamed (a mount point), its entries moved in after the old ones are removed."""
    old = target.parent / f".{target.name}.{_OLD}-{os.getpid()}-{secrets.token_hex(3)}"
    exists = target.exists() or target.is_symlink()
    try:
        if exists:
            os.rename(target, old)
        os.rename(staging, target)
    except OSError:
        if old.exists():  # undo the first rename before the other way
            os.rename(old, target)
        if not target.is_dir():
            raise
        for entry in list(target.iterdir()):  # all lungmech's, as check_folder has just said
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()
        for entry in list(staging.iterdir()):
            shutil.move(entry, target / entry.name)  # across file systems too
        staging.rmdir()
        return
    if exists:
        shutil.rmtree(old, ignore_errors=True)


def _keep(staging: Path, target: Path) -> Path:
    """Give a finished staging folder a visible name next to ``target`` and return it."""
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    kept = target.with_name(f"{target.name}-{stamp}-{secrets.token_hex(2)}")
    os.rename(staging, kept)
    return kept
