"""Load values written as formulas of position and time, e.g. ``"-1e3 * y * sin(pi * t)"``.

A formula is a Python arithmetic expression of the reference coordinates ``x``, ``y``, ``z`` (m)
and the time ``t`` (s), with numbers, ``+ - * / **``, parentheses, the constants ``pi`` and
``e``, and the functions ``sin cos tan exp ln sqrt abs tanh``. It is read with Python's ``ast``
(nothing is executed) and becomes a UFL expression, evaluated exactly at the quadrature points:
the time is a ``fem.Constant`` of the model, so stepping recompiles nothing. Its constant parts
are computed when it is read and must be finite real numbers; :func:`evaluate` gives its values
at points (NumPy), to say where a formula leaves the reals.
"""

from __future__ import annotations

import ast
import math
import operator
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
import ufl
from ufl.core.expr import Expr

from lungmech.errors import ParameterError

__all__ = ["check", "evaluate", "to_ufl"]

LONGEST = 2000  # characters: a formula is a line of a scene, not a program
MOST_PARTS = 400  # numbers, names and operations: more would nest deeper than UFL and FFCx compile

_FUNCTIONS: dict[str, Callable[[Expr], Expr]] = {
    "sin": ufl.sin,
    "cos": ufl.cos,
    "tan": ufl.tan,
    "exp": ufl.exp,
    "ln": ufl.ln,
    "sqrt": ufl.sqrt,
    "abs": abs,  # type: ignore[dict-item]  # UFL sets Expr.__abs__ at import: its class declares none
    "tanh": ufl.tanh,
}
_NUMPY: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "sin": np.sin,
    "cos": np.cos,
    "tan": np.tan,
    "exp": np.exp,
    "ln": np.log,
    "sqrt": np.sqrt,
    "abs": np.abs,
    "tanh": np.tanh,
}
_CONSTANTS = {"pi": math.pi, "e": math.e}
_VARIABLES = ("x", "y", "z", "t")
_BINARY = {
    ast.Add: operator.add,
    ast.Sub: operator.sub,
    ast.Mult: operator.mul,
    ast.Div: operator.truediv,
    ast.Pow: operator.pow,
}
_UNARY: dict[type[ast.unaryop], Callable[[Any], Any]] = {ast.USub: operator.neg, ast.UAdd: operator.pos}


class _Symbol:
    """A variable for :func:`check`: every operation on it gives a symbol (nothing is computed)."""

    def _any(self, *_: object) -> _Symbol:
        return self

    __add__ = __radd__ = __sub__ = __rsub__ = __mul__ = __rmul__ = _any
    __truediv__ = __rtruediv__ = __pow__ = __rpow__ = __neg__ = __pos__ = __abs__ = _any


def check(text: str, where: str, dimension: int = 3) -> None:
    """Raise a :class:`ParameterError` naming ``where`` unless ``text`` is a formula of x, y, z, t
    (``z`` only in 3-D)."""
    _build(text, where, {name: _Symbol() for name in (*_VARIABLES[:dimension], "t")})


def to_ufl(text: str, where: str, position: Expr, time: Expr) -> Expr:
    """The formula ``text`` as a UFL expression of ``position`` (x, y[, z]) and ``time``."""
    names = {name: position[i] for i, name in enumerate(_VARIABLES[: position.ufl_shape[0]])} | {"t": time}
    return _build(text, where, names)


def evaluate(text: str, where: str, points: np.ndarray, time: float) -> np.ndarray:
    """The formula's values at ``points`` (n × gdim, m) and ``time`` (s); nan or inf where it is
    not defined (``ln`` of a negative number) or overflows, as IEEE arithmetic gives them."""
    points = np.atleast_2d(np.asarray(points, dtype=float))
    names = {name: points[:, i] for i, name in enumerate(_VARIABLES[: points.shape[1]])}
    names["t"] = np.full(len(points), float(time))
    with np.errstate(all="ignore"):
        value = _build(text, where, names, _NUMPY)
        return np.broadcast_to(np.asarray(value, dtype=float), (len(points),))


_Value = TypeVar("_Value")


def _finite(value: _Value, where: str, text: str) -> _Value:
    """A constant part of a formula, if it is a finite real number; the rest as it is."""
    if isinstance(value, complex):
        raise ParameterError(f"{where}: {text!r}: a part of it is not a real number ({value:g})")
    if isinstance(value, float) and not math.isfinite(value):
        raise ParameterError(
            f"{where}: {text!r}: a part of it is {value} (outside the floating-point range): give finite numbers"
        )
    return value


def _build(
    text: str, where: str, names: dict[str, Any], functions: dict[str, Callable[[Any], Any]] = _FUNCTIONS
) -> Any:
    if not isinstance(text, str):
        raise ParameterError(f"{where}: expected a number or a formula (got {text!r})")
    if len(text) > LONGEST:
        raise ParameterError(f"{where}: a formula of {len(text)} characters; at most {LONGEST} are read")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except (SyntaxError, RecursionError, MemoryError) as e:
        reason = e.msg if isinstance(e, SyntaxError) else "nested too deeply"
        raise ParameterError(f"{where}: {text!r} is not a formula ({reason})") from None
    if (parts := sum(1 for _ in ast.walk(tree))) > MOST_PARTS:
        raise ParameterError(f"{where}: a formula of {parts} parts; at most {MOST_PARTS} are read")
    try:
        return _node(tree, text, where, names, functions)
    except RecursionError:
        raise ParameterError(f"{where}: {text[:40]!r}…: the formula is nested too deeply") from None


def _node(
    tree: ast.AST, text: str, where: str, names: dict[str, Any], functions: dict[str, Callable[[Any], Any]]
) -> Any:
    """The value of a parsed formula: its constant parts computed, the rest built from ``names``
    and ``functions`` (UFL, NumPy or symbols)."""

    def build(node: ast.AST) -> Any:
        if isinstance(node, ast.Expression):
            return build(node.body)
        if isinstance(node, ast.Constant) and isinstance(node.value, int | float) and not isinstance(node.value, bool):
            return _finite(float(node.value), where, text)
        if isinstance(node, ast.Name):
            if node.id in names:
                return names[node.id]
            if node.id in _CONSTANTS:
                return _CONSTANTS[node.id]
            known = ", ".join([*names, *_CONSTANTS])
            raise ParameterError(f"{where}: unknown name {node.id!r} in {text!r} (known: {known})")
        if isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
            try:
                return _finite(_BINARY[type(node.op)](build(node.left), build(node.right)), where, text)
            except (OverflowError, ZeroDivisionError) as e:  # of the formula's constant part
                raise ParameterError(f"{where}: {text!r}: {e}") from None
        if isinstance(node, ast.UnaryOp) and type(node.op) in _UNARY:
            return _UNARY[type(node.op)](build(node.operand))
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and node.func.id in _FUNCTIONS
            and len(node.args) == 1
            and not node.keywords
        ):
            argument = build(node.args[0])
            if isinstance(argument, float):
                return _finite(_numeric(node.func.id, argument, where, text), where, text)
            return argument if isinstance(argument, _Symbol) else functions[node.func.id](argument)
        raise ParameterError(
            f"{where}: {text!r} is not a formula of {', '.join(names)} (numbers, + - * / **, "
            f"{', '.join(_FUNCTIONS)}, pi, e)"
        )

    return build(tree)


def _numeric(function: str, value: float, where: str, text: str) -> float:
    """A function of a number, computed now (a formula's constant part)."""
    try:
        special: dict[str, Callable[[float], float]] = {"ln": math.log, "abs": abs}
        return float((special.get(function) or getattr(math, function))(value))
    except (ValueError, OverflowError) as e:
        raise ParameterError(f"{where}: {text!r}: {function}({value:g}) is not defined ({e})") from None
