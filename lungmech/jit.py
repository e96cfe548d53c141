"""Forms and expressions compiled by FFCx, waited for as long as a compile can take.

FFCx keeps compiled forms in one cache per user. When a process finds the form it needs being
compiled by another (the C file there, the library not yet), it waits for it, by default
10 s, and then fails with ``TimeoutError``. Processes that compile the same form at once do meet:
an ensemble's groups or a cohort's workers on a cold cache, pytest-xdist's workers. A
hyper-reduced lung's forms run to megabytes of C, minutes to compile on a busy core, so
every form lungmech compiles waits up to :data:`TIMEOUT` instead. The wait is no part of a
form's signature: the cache is shared with forms compiled without it.
"""

from __future__ import annotations

from typing import Any

import ufl
from dolfinx import fem

TIMEOUT = 3600  # s: a compile that takes an hour has failed
OPTIONS: dict[str, Any] = {"timeout": TIMEOUT}  # DOLFINx's jit_options


def form(expression: ufl.Form, **keywords: Any) -> Any:  # a fem.Form; Any as DOLFINx's own is unannotated
    """``dolfinx.fem.form(expression)``, waiting for another process's compile of it."""
    return fem.form(expression, jit_options=OPTIONS, **keywords)


def expression(expression: ufl.core.expr.Expr, points: Any, **keywords: Any) -> fem.Expression:
    """``dolfinx.fem.Expression(expression, points)``, waiting for another process's compile."""
    return fem.Expression(expression, points, jit_options=OPTIONS, **keywords)
