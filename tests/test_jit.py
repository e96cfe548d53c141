"""Every form lungmech compiles waits for another process's compile of it (lungmech.jit):
processes compiling the same form into one cache at once (an ensemble's groups on a cold cache)
must not give up after DOLFINx's 10 s."""

import re
from pathlib import Path

from mpi4py import MPI

import ffcx.codegeneration.jit
import ffcx.naming
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


def test_an_expression_holding_a_variable_compiles_to_one_module_in_any_process():
    """A stress P = ∂ψ/∂F made twice (its label counted anew each time, as in another process)
    is one compiled module, and has the values of the expression as written (FFCx numbers an
    expression's labels by count: a new module in every process before)."""
    domain = mesh.create_unit_cube(MPI.COMM_WORLD, 2, 2, 2)
    u = fem.Function(fem.functionspace(domain, ("Lagrange", 1, (3,))))
    u.interpolate(lambda x: 0.1 * x**2)
    points = np.array([[0.25, 0.25, 0.25]])

    def stress():
        F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
        return ufl.diff(ufl.tr(F.T * F) + ufl.ln(ufl.det(F)), F)

    names = {ffcx.naming.compute_signature([(jit.unlabelled(stress()), points)], "") for _ in range(2)}
    assert len(names) == 1
    assert len({ffcx.naming.compute_signature([(stress(), points)], "") for _ in range(2)}) == 2  # as FFCx names them
    cells = np.arange(domain.topology.index_map(3).size_local, dtype=np.int32)
    compiled = jit.expression(stress(), points).eval(domain, cells)
    F = ufl.Identity(3) + ufl.grad(u)
    by_hand = fem.Expression(2 * F + ufl.inv(F).T, points).eval(domain, cells)  # ∂/∂F (tr FᵀF + ln det F)
    assert np.allclose(compiled, by_hand, rtol=1e-13, atol=0.0)
