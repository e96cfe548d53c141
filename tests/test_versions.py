"""The installed packages are the tested set of ``requirements/lock.txt``.

``make demo`` and ``make test`` install the lock's versions (a pip constraints file); a result
that holds with them may move with another NumPy or SciPy (the registration demo's numbers did).
On the wheel route a version other than the locked one fails here, so a green run says which set
it was. ``make test-latest`` (``LUNGMECH_UNLOCKED=1``) tests the newest allowed versions instead,
and Debian's route has Debian's versions: both are told, not failed.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import os
import re
import tomllib
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LOCK = ROOT / "requirements" / "lock.txt"


def canonical(name: str) -> str:
    """A distribution's name as PEP 503 compares them: lower case, runs of -_. as one -."""
    return re.sub(r"[-_.]+", "-", name).lower()


def locked() -> dict[str, str]:
    """name -> version of every ``name==version`` line of the lock."""
    pins = {}
    for number, line in enumerate(LOCK.read_text().splitlines(), 1):
        line = line.split("#")[0].strip()
        if not line:
            continue
        name, equals, version = line.partition("==")
        assert equals and name.strip() and version.strip(), f"{LOCK.name}:{number}: not name==version: {line!r}"
        pins[canonical(name.strip())] = version.strip()
    return pins


def installed(name: str) -> str | None:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def test_the_lock_pins_every_dependency():
    """Every package pyproject.toml names (with the test, docs and wheel extras) has its locked version."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    named = [
        *project["dependencies"],
        *project["optional-dependencies"]["test"],
        *project["optional-dependencies"]["docs"],
    ]
    named += project["optional-dependencies"]["wheel"]
    names = {canonical(re.match(r"[A-Za-z0-9_.-]+", spec).group()) for spec in named}
    assert not names - set(locked()), f"not in {LOCK.name}: {sorted(names - set(locked()))} (run 'make lock')"


def test_installed_versions_are_the_locked_ones():
    pins = locked()
    differ = {name: (version, installed(name)) for name, version in pins.items() if installed(name) != version}
    shown = ", ".join(f"{name} {have or 'missing'} (locked {want})" for name, (want, have) in sorted(differ.items()))
    if not differ:
        return
    if os.environ.get("LUNGMECH_UNLOCKED"):
        pytest.skip(f"make test-latest: the newest allowed versions, not the lock: {shown}")
    if importlib.util.find_spec("dolfinx_solver") is None:  # Debian's DOLFINx and its site packages
        warnings.warn(f"Debian's route: versions other than the lock's: {shown}", stacklevel=1)
        return
    pytest.fail(f"installed versions are not the lock's: {shown}; 'make test' reinstalls them (rm -r .venv)")
