"""Python 3.13.0 and 3.13.1 keep alive every object a ``functools.singledispatchmethod`` was
called on (CPython gh-127750): the method's per-instance cache is a WeakKeyDictionary whose
values close over the instance. UFL's derivative and replacement algorithms dispatch that way
(``ufl.corealg.dag_traverser``), so on those versions every differentiated form kept its
coefficients, their function spaces and meshes, and each mesh's MPI communicators, for the
life of the process: a long session (a sweep, a cohort, the test suite under ``mpiexec``) ran
out of communicators ("Too many communicators", an MPI abort).

:func:`install` checks whether this Python's ``singledispatchmethod`` leaks, and only then
gives it the ``__get__`` of Python 3.12 and of the releases that fixed it: dispatch on each
call, no cache. Nothing changes on a Python that does not leak.
"""

from __future__ import annotations

import functools
import gc
import sys
import weakref
from collections.abc import Callable
from typing import Any

__all__ = ["install", "leaks"]


def leaks() -> bool:
    """Whether an object a ``singledispatchmethod`` was called on outlives its last reference."""

    class Probe:
        @functools.singledispatchmethod
        def method(self, value: object) -> object:
            return value

    probe = Probe()
    probe.method(1)
    alive = weakref.ref(probe)
    del probe
    gc.collect()
    return alive() is not None


def _get(self: functools.singledispatchmethod, obj: Any, cls: type | None = None) -> Callable[..., Any]:
    """``singledispatchmethod.__get__`` without a cache: a bound dispatcher per access."""
    dispatch = self.dispatcher.dispatch
    name = getattr(self.func, "__name__", "singledispatchmethod method")

    def method(*args: Any, **kwargs: Any) -> Any:
        if not args:
            raise TypeError(f"{name} requires at least 1 positional argument")
        return dispatch(args[0].__class__).__get__(obj, cls)(*args, **kwargs)

    method.__isabstractmethod__ = self.__isabstractmethod__  # type: ignore[attr-defined]  # as functools sets it
    method.register = self.register  # type: ignore[attr-defined]  # as functools sets it
    functools.update_wrapper(method, self.func)
    return method


def install() -> None:
    """Give a leaking ``singledispatchmethod`` the non-caching ``__get__`` (once; idempotent).

    Only Python 3.13 has the per-instance cache: elsewhere ``import lungmech`` skips the probe
    (and its full garbage collection)."""
    if sys.version_info[:2] == (3, 13) and leaks():
        functools.singledispatchmethod.__get__ = _get  # type: ignore[method-assign]  # the stdlib's own bug, gh-127750
