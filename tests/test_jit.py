"""Every form lungmech compiles waits for another process's compile of it (lungmech.jit):
processes compiling the same form into one cache at once (an ensemble's groups on a cold cache)
must not give up after DOLFINx's 10 s."""

import re
from pathlib import Path

from mpi4py import MPI

import ffcx.codegeneration.jit
import numpy as np
import pytest
import ufl
from dolfinx import fem, mesh

import lungmech
from lungmech import jit

PACKAGE = Path(lungmech.__file__).parent


def test_a_form_waits_as_long_as_lungmechs_timeout(monkeypatch):
    waited = []
    original = ffcx.codegeneration.jit.get_cached_module

    def recorded(module_name, object_names, cache_dir, timeout):
        waited.append(timeout)
        return original(module_name, object_names, cache_dir, timeout)

    monkeypatch.setattr(ffcx.codegeneration.jit, "get_cached_module", recorded)
    domain = mesh.create_unit_interval(MPI.COMM_WORLD, 3)
    x = ufl.SpatialCoordinate(domain)
    value = fem.assemble_scalar(jit.form(x[0] ** 3 * ufl.dx))
    points = np.array([[0.5]])
    jit.expression(x[0] ** 2, points)
    assert MPI.COMM_WORLD.allreduce(value, op=MPI.SUM) == pytest.approx(0.25)
    if MPI.COMM_WORLD.rank == 0:  # DOLFINx compiles on the first rank; the others wait at a barrier
        assert waited == [jit.TIMEOUT, jit.TIMEOUT]


def test_no_module_compiles_past_it():
    direct = re.compile(r"\bfem\.form\(|\bfem\.Expression\(")
    found = []
    for path in PACKAGE.rglob("*.py"):
        if path == PACKAGE / "jit.py":
            continue
        for number, line in enumerate(path.read_text().splitlines(), start=1):
            if direct.search(line) and not line.lstrip().startswith("#"):
                found.append(f"{path.relative_to(PACKAGE)}:{number}")
    assert not found, "compiled without lungmech.jit: " + ", ".join(found)
