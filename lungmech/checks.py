"""Checks of the values people give, each failing with one error that names the value.

A scene file is read into lungmech's own objects (laws, loads, stepping), and those objects check
their values when they are made, so a Python script gets the same messages as the command line.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

import numpy as np

from lungmech.errors import ParameterError

__all__ = ["boolean", "integer", "names", "real", "vector"]


def real(
    name: str, value: object, *, positive: bool = False, nonnegative: bool = False, infinite: bool = False
) -> float:
    """``value`` as a float: a real number (not a bool or a string), finite unless ``infinite``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ParameterError(f"{name} must be a number (got {value!r})")
    value = float(value)
    if math.isnan(value) or (math.isinf(value) and not infinite):
        raise ParameterError(f"{name} must be a finite number (got {value})")
    if positive and not value > 0:
        raise ParameterError(f"{name} must be > 0 (got {value:g})")
    if nonnegative and not value >= 0:
        raise ParameterError(f"{name} must be >= 0 (got {value:g})")
    return value


def vector(name: str, value: object, size: int | tuple[int, ...] = 3) -> tuple[float, ...]:
    """``value`` as a tuple of ``size`` finite numbers (a list, tuple or 1-D array); ``size`` may
    list the lengths allowed."""
    sizes = (size,) if isinstance(size, int) else size
    if isinstance(value, np.ndarray) and value.ndim == 1:
        value = value.tolist()
    if isinstance(value, str | bytes) or not isinstance(value, Sequence) or len(value) not in sizes:
        raise ParameterError(f"{name} must be {' or '.join(map(str, sizes))} numbers (got {value!r})")
    return tuple(real(f"{name}[{i}]", v) for i, v in enumerate(value))


def integer(name: str, value: object, minimum: int | None = None) -> int:
    """``value`` as an int (not a bool, not a float), at least ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ParameterError(f"{name} must be an integer (got {value!r})")
    if minimum is not None and value < minimum:
        raise ParameterError(f"{name} must be >= {minimum} (got {value})")
    return int(value)


def boolean(name: str, value: object) -> bool:
    """``value`` as a bool (true or false, not 0, 1 or a string)."""
    if not isinstance(value, bool):
        raise ParameterError(f"{name} must be true or false (got {value!r})")
    return value


def names(name: str, value: object, empty: bool = False) -> tuple[str, ...]:
    """``value`` — a name, or a list of names — as a tuple of distinct non-empty strings (none
    only if ``empty``). A name given twice is refused: on a list of boundaries it would count
    that boundary twice (twice the pressure), not once."""
    listed = (value,) if isinstance(value, str) else value
    if (
        isinstance(listed, bytes)
        or not isinstance(listed, Sequence)
        or not (listed or empty)
        or not all(isinstance(n, str) and n for n in listed)
    ):
        raise ParameterError(f"{name} must be a name or a list of them (got {value!r})")
    if repeated := sorted({n for n in listed if listed.count(n) > 1}):
        raise ParameterError(f"{name} names {', '.join(repeated)} more than once (got {list(listed)})")
    return tuple(listed)
