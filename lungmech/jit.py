"""Forms and expressions compiled by FFCx, waited for as long as a compile can take.

FFCx keeps compiled forms in one cache per user. When a process finds the form it needs being
compiled by another (the C file there, the library not yet), it waits for it, by default
10 s, and then fails with ``TimeoutError``. Processes that compile the same form at once do meet:
an ensemble's groups or a cohort's workers on a cold cache, pytest-xdist's workers. A
hyper-reduced lung's forms run to megabytes of C, minutes to compile on a busy core, so
every form lungmech compiles waits up to :data:`TIMEOUT` instead. The wait is no part of a
form's signature.

lungmech's modules are kept in a folder of their own within DOLFINx's cache
(``<cache_dir>/lungmech``), spread over 256 subfolders by the first two hex digits of their
signature. FFCx looks a compiled module up by listing its folder (a new
``importlib.machinery.FileFinder`` for every form): in one folder of some ten thousand modules
that listing was a quarter of a personalisation's time (38 s of 162 s in
tests/test_personalise.py, 997 lookups). A subfolder holds a 256th of them.

An expression is compiled without its ``ufl.variable`` labels. FFCx names an expression's
compiled module by a signature that numbers its coefficients and constants canonically but its
labels by their count in the process, so an expression holding a variable (a stress
P = ∂ψ/∂F) got a new name, and a new compile, in every process, and the cache grew by one
module each time. A form's signature numbers its labels too: forms are compiled as they are.
"""

from __future__ import annotations

import errno
import functools
from pathlib import Path
from typing import Any

import ffcx.naming
import ufl
from dolfinx import fem
from dolfinx import jit as dolfinx_jit
from ufl.algorithms import expand_derivatives
from ufl.corealg.map_dag import map_expr_dag
from ufl.corealg.multifunction import MultiFunction

TIMEOUT = 3600  # s: a compile that takes an hour has failed
OPTIONS: dict[str, Any] = {"timeout": TIMEOUT}  # DOLFINx's jit_options


@functools.cache
def _root() -> Path:
    """lungmech's folder in DOLFINx's JIT cache (its ``cache_dir``: the user's JIT options, or
    ``$XDG_CACHE_HOME/fenics``)."""
    cache = Path(dolfinx_jit.get_options()["cache_dir"])
    if cache.exists() and not cache.is_dir():  # named as the user set it, not as lungmech's folder in it
        raise NotADirectoryError(errno.ENOTDIR, "DOLFINx's JIT cache_dir is not a folder", str(cache))
    return cache / "lungmech"


def options(signature: str) -> dict[str, Any]:
    """The JIT options of a form or an expression of UFL signature ``signature``: the wait,
    and the cache subfolder its first two hex digits name."""
    return OPTIONS | {"cache_dir": _root() / signature[:2]}


def form(expression: ufl.Form, **keywords: Any) -> Any:  # a fem.Form; Any as DOLFINx's own is unannotated
    """``dolfinx.fem.form(expression)``, in lungmech's cache, waiting for another process's
    compile of it."""
    return fem.form(expression, jit_options=options(expression.signature()), **keywords)


def expression(expression: ufl.core.expr.Expr, points: Any, **keywords: Any) -> fem.Expression:
    """``dolfinx.fem.Expression(expression, points)``, its derivatives applied and its variables
    replaced by what they stand for (the same values, a signature the same in every process),
    waiting for another process's compile."""
    plain = unlabelled(expression)
    signature = ffcx.naming.compute_signature([(plain, points)], "")  # FFCx's own, as it names the module
    return fem.Expression(plain, points, jit_options=options(signature), **keywords)


class _Unlabelled(MultiFunction):
    """Each ``Variable`` node replaced by the expression it labels; the rest kept."""

    expr = MultiFunction.reuse_if_untouched

    def variable(self, o: ufl.core.expr.Expr, labelled: ufl.core.expr.Expr, label: Any) -> ufl.core.expr.Expr:
        return labelled


def unlabelled(expression: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """``expression`` with its derivatives applied (d/dv of a variable v needs the label) and then
    without labels: v = variable(e) becomes e."""
    return map_expr_dag(_Unlabelled(), expand_derivatives(expression))
