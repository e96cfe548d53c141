"""Checks of a scene's tables as they are read: each bad key or value is one :class:`SceneError`
naming it (``material.nuu: unknown key (expected one of: E, nu)``)."""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from lungmech.errors import LungmechError, SceneError

__all__ = ["call", "check_signature", "finite_numbers", "no_unknown_keys", "section", "typed", "with_tuple"]


# Keys where TOML's inf is meaningful (an open range); nan is never a value.
_INFINITY_ALLOWED = ("formulation.pore_range", "stepping.max_step")

T = TypeVar("T")


def finite_numbers(table: Any, where: str = "") -> None:
    """Refuse nan anywhere in the scene, and inf except where it means 'no bound'."""
    if isinstance(table, dict):
        for key, value in table.items():
            finite_numbers(value, f"{where}.{key}" if where else str(key))
    elif isinstance(table, list):
        for i, value in enumerate(table):
            finite_numbers(value, f"{where}[{i}]")
    elif isinstance(table, float) and not math.isfinite(table):
        if math.isnan(table):
            raise SceneError(f"{where}: nan is not a value; give a number")
        if not (where.startswith(_INFINITY_ALLOWED) and table > 0):
            raise SceneError(f"{where}: {table} is not allowed here; give a finite number")


def section(table: dict[str, Any], name: str) -> dict[str, Any]:
    section = table.get(name, {})
    if not isinstance(section, dict):
        raise SceneError(f"{name}: expected a table [{name}]")
    return section


def with_tuple(table: dict[str, Any], key: str) -> dict[str, Any]:
    if key in table and isinstance(table[key], list):
        return {**table, key: tuple(tuple(v) if isinstance(v, list) else v for v in table[key])}
    return table


def typed(value: object, kind: type[T], where: str) -> T:
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise SceneError(f"{where}: expected {kind.__name__} (got {value!r})")
    return value


def no_unknown_keys(table: dict[str, Any], allowed: Sequence[str], where: str) -> None:
    for key in table:
        if key not in allowed:
            expected = f"expected one of: {', '.join(allowed)}" if allowed else f"[{where}] takes no keys"
            raise SceneError(f"{where}.{key}: unknown key ({expected})")


def check_signature(func: Callable[..., object], kwargs: dict[str, Any], where: str, skip: Sequence[str] = ()) -> None:
    parameters = inspect.signature(func).parameters
    allowed = [p for p in parameters if p not in skip and p != "self"]
    no_unknown_keys(kwargs, allowed, where)
    missing = [
        p
        for p, spec in parameters.items()
        if p not in skip and spec.default is inspect.Parameter.empty and p not in kwargs
    ]
    if missing:
        raise SceneError(f"{where}: missing key(s) {', '.join(missing)}")


def call(func: Callable[..., T], kwargs: dict[str, Any], where: str) -> T:
    """``func(**kwargs)``, with unknown/missing keys and bad values reported against ``where``."""
    check_signature(func, kwargs, where)
    try:
        return func(**kwargs)
    except LungmechError as error:
        raise SceneError(f"{where}: {error}") from None
    except (TypeError, ValueError) as error:
        raise SceneError(f"{where}: bad value ({error})") from None
