"""Syntax tree to Python source, compiled once at load.

Generated code contains only identifiers this module invents (``v0``, ``i3``, ``_pow``),
``repr`` of finite floats, Python operators and ``repr`` of names that already matched the
identifier grammar. No user text is ever evaluated. The code runs with an empty
``__builtins__`` and sees only :data:`FUNCTION_TABLE` plus the helpers a dialect passes in,
so a script cannot reach any Python object.

Semantics, chosen to be what Python computes on floats:

* ``+ - * /`` are float operations; ``/`` by zero raises, and is caught by the statement.
* ``pow`` is :func:`math.pow` (domain and overflow errors raise), ``abs`` is
  :func:`math.fabs`, and the other functions are those of :mod:`math`.
* comparisons, ``and``, ``or`` and ``not`` give 1.0 or 0.0; ``and``/``or`` short-circuit;
  a condition is true when it is non-zero.
* ``if(c, a, b)`` evaluates only the branch it returns; ``limit(x, lo, hi)`` is
  ``min(max(x, lo), hi)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from cell.scripts.expr import Binary, Brace, Call, Name, Node, Num, Unary


class NonFiniteResult(ArithmeticError):
    """A statement produced NaN or an infinity."""


def _nonfinite(value: float) -> float:
    raise NonFiniteResult(f"result is {value}")


#: The only callables a compiled script can reach.
FUNCTION_TABLE: dict[str, Any] = {
    "_pow": math.pow,
    "_abs": math.fabs,
    "_sqrt": math.sqrt,
    "_exp": math.exp,
    "_log": math.log,
    "_log10": math.log10,
    "_sin": math.sin,
    "_cos": math.cos,
    "_tan": math.tan,
    "_min": min,
    "_max": max,
    "_nonfinite": _nonfinite,
    #: exceptions a statement contains: division by zero, domain, overflow, NaN/inf
    "_ERRS": (ArithmeticError, ValueError),
}

_PY_OP = {"<>": "!=", "and": "and", "or": "or"}


def emit(node: Node, ref: Callable[[Name], str], cond: bool = False) -> str:
    """Python expression text for ``node``; ``ref`` maps a name to a Python identifier.

    ``cond`` asks for a value used only for its truth (a condition), which avoids
    converting comparisons to 1.0/0.0 and back.
    """
    if isinstance(node, Num):
        return repr(float(node.value))
    if isinstance(node, Name):
        return ref(node)
    if isinstance(node, Brace):
        return emit(node.inner, ref, cond)
    if isinstance(node, Unary):
        if node.op == "not":
            inner = emit(node.operand, ref, True)
            return f"(not {inner})" if cond else f"(0.0 if {inner} else 1.0)"
        inner = emit(node.operand, ref)
        return f"(-{inner})" if node.op == "-" else inner
    if isinstance(node, Binary):
        op = _PY_OP.get(node.op, node.op)
        if op in ("and", "or"):
            text = f"{emit(node.left, ref, True)} {op} {emit(node.right, ref, True)}"
            return f"({text})" if cond else f"(1.0 if {text} else 0.0)"
        left, right = emit(node.left, ref), emit(node.right, ref)
        if op in ("+", "-", "*", "/"):
            return f"({left} {op} {right})"
        text = f"{left} {op} {right}"
        return f"({text})" if cond else f"(1.0 if {text} else 0.0)"
    if isinstance(node, Call):
        if node.func == "if":
            c, a, b = node.args
            return f"({emit(a, ref)} if {emit(c, ref, True)} else {emit(b, ref)})"
        args = [emit(a, ref) for a in node.args]
        if node.func == "limit":
            return f"_min(_max({args[0]}, {args[1]}), {args[2]})"
        return f"_{node.func}({', '.join(args)})"
    raise TypeError(f"cannot emit {type(node).__name__}")  # pragma: no cover


def compile_functions(source: str, filename: str, extra: dict[str, Any]) -> dict[str, Any]:
    """Compile generated ``source`` and return its namespace.

    The namespace has an empty ``__builtins__`` and holds only :data:`FUNCTION_TABLE`
    and ``extra`` (helpers of the dialect, never user objects).
    """
    namespace: dict[str, Any] = {"__builtins__": {}}
    namespace.update(FUNCTION_TABLE)
    namespace.update(extra)
    code = compile(source, filename, "exec", dont_inherit=True)
    exec(code, namespace)  # noqa: S102 - generated from our own syntax tree, see module doc
    return namespace


def reason(exc: BaseException) -> str:
    """Short human text for an exception raised by a statement."""
    if isinstance(exc, ZeroDivisionError):
        return "division by zero"
    if isinstance(exc, OverflowError):
        return "overflow (result too large)"
    if isinstance(exc, NonFiniteResult):
        return str(exc)
    if isinstance(exc, ValueError):
        return f"domain error ({exc})"
    return f"{type(exc).__name__}: {exc}"
