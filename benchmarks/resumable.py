"""Results of an hours-long benchmark kept between its runs, so that a run stopped (by the end of
a session, say) resumes where it stopped instead of starting again.

A result is kept under its name and the version of the code that computed it: the git tree of
``lungmech/`` as committed, less the sub-packages it does not depend on (a full model's solve
does not depend on ``lungmech/rom``). Code that differs from its last commit keeps nothing and
reuses nothing: a result is always that of a commit. The files live in
``benchmarks/results/raw/cache`` (not versioned) and can be deleted at any time.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import subprocess
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

from machine import RESULTS, say

CACHE = RESULTS / "raw" / "cache"
ROOT = Path(__file__).parent.parent
T = TypeVar("T")


def code_version(excluding: Sequence[str] = ()) -> str | None:
    """The committed tree of ``lungmech/`` without the sub-packages ``excluding`` (e.g. "rom"),
    as 12 hex digits; None where that code differs from the last commit (or git is absent)."""
    try:
        listing = _git("ls-tree", "HEAD", "lungmech/").splitlines()
        changed = _git("status", "--porcelain", "--", "lungmech/").splitlines()
    except (OSError, subprocess.CalledProcessError):
        return None
    skipped = {f"lungmech/{name}" for name in excluding}
    if any(not any(line[3:].startswith(f"{path}/") for path in skipped) for line in changed):
        return None
    kept = [line for line in listing if line.split("\t")[1] not in skipped]
    return hashlib.sha1("\n".join(kept).encode()).hexdigest()[:12]


def cached(name: str, version: str | None, compute: Callable[[], T]) -> T:
    """``compute()``, or what it returned before for ``name`` at code ``version`` (None: always
    computed, never kept)."""
    return kept(name, version, compute)[0]


def kept(name: str, version: str | None, compute: Callable[[], T], any_version: bool = False) -> tuple[T, str | None]:
    """(``compute()`` or what it returned before for ``name`` at code ``version``, the version
    it is of). With ``any_version``, the newest kept one of any code version serves too (say
    so where its result is reported)."""
    if version is None:
        return compute(), None
    path = CACHE / f"{name}-{version}.pickle"
    others = [other for other in CACHE.glob(f"{name}-*.pickle") if "-" not in other.stem[len(name) + 1 :]]
    others.sort(key=lambda other: other.stat().st_mtime)
    if not path.exists() and any_version and others:
        path = others[-1]
    if path.exists():
        say(f"  (kept from an earlier run: {path.name})")
        return pickle.loads(path.read_bytes()), path.stem[len(name) + 1 :]
    value = compute()
    CACHE.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(f".{os.getpid()}.partial")
    partial.write_bytes(pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))
    partial.replace(path)  # whole or not at all: a run stopped while writing leaves no result
    return value, version


def _git(*arguments: str) -> str:
    return subprocess.run(["git", *arguments], cwd=ROOT, capture_output=True, text=True, check=True).stdout
