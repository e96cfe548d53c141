"""Load values written as formulas of position and time, e.g. ``"-1e3 * y * sin(pi * t)"``.

A formula is a Python arithmetic expression of the reference coordinates ``x``, ``y``, ``z`` (m)
and the time ``t`` (s), with numbers, ``+ - * / **``, parentheses, the constants ``pi`` and
``e``, and the functions ``sin cos tan exp ln sqrt abs tanh``. It is read with Python's ``ast``
(nothing is executed) and becomes a UFL expression, evaluated exactly at the quadrature points:
the time is a ``fem.Constant`` of the model, so stepping recompiles nothing.
"""

from __future__ import annotations

import ast
import math
import operator
from collections.abc import Callable

import ufl
from ufl.core.expr import Expr

from lungmech.errors import ParameterError

__all__ = ["check", "to_ufl"]

_FUNCTIONS: dict[str, Callable[[Expr], Expr]] = {
    "sin": ufl.sin,
    "cos": ufl.cos,
    "tan": ufl.tan,
    "exp": ufl.exp,
    "ln": ufl.ln,
    "sqrt": ufl.sqrt,
    "abs": abs,
    "tanh": ufl.tanh,
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
_UNARY = {ast.USub: operator.neg, ast.UAdd: operator.pos}


class _Symbol:
    """A variable for :func:`check`: every operation on it gives a symbol (nothing is computed)."""

    def _any(self, *_):
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


def _build(text: str, where: str, names: dict):
    if not isinstance(text, str):
        raise ParameterError(f"{where}: expected a number or a formula (got {text!r})")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as e:
        raise ParameterError(f"{where}: {text!r} is not a formula ({e.msg})") from None

    def build(node: ast.AST):
        if isinstance(node, ast.Expression):
            return build(node.body)
        if isinstance(node, ast.Constant) and isinstance(node.value, int | float) and not isinstance(node.value, bool):
            return float(node.value)
        if isinstance(node, ast.Name):
            if node.id in names:
                return names[node.id]
            if node.id in _CONSTANTS:
                return _CONSTANTS[node.id]
            known = ", ".join([*names, *_CONSTANTS])
            raise ParameterError(f"{where}: unknown name {node.id!r} in {text!r} (known: {known})")
        if isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
            try:
                return _BINARY[type(node.op)](build(node.left), build(node.right))
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
                return _numeric(node.func.id, argument, where, text)
            return argument if isinstance(argument, _Symbol) else _FUNCTIONS[node.func.id](argument)
        raise ParameterError(
            f"{where}: {text!r} is not a formula of {', '.join(names)} (numbers, + - * / **, "
            f"{', '.join(_FUNCTIONS)}, pi, e)"
        )

    return build(tree)


def _numeric(function: str, value: float, where: str, text: str) -> float:
    """A function of a number, computed now (a formula's constant part)."""
    try:
        return float({"ln": math.log, "abs": abs}.get(function, getattr(math, function, None))(value))
    except (ValueError, OverflowError) as e:
        raise ParameterError(f"{where}: {text!r}: {function}({value:g}) is not defined ({e})") from None
