"""Unit checking of the CyFlex-style labels (seed 004, Figure 3).

A unit is ``None`` (unknown: not checked, e.g. an input channel or anything inside braces),
``()`` (``none``, dimensionless) or a sorted tuple of ``(name, exponent)`` pairs. Unit
names compare case-insensitively. Adding, subtracting or comparing two known, different
units outside braces is a load error; that is what the braces of Figure 3 are for.
Multiplication and division combine exponents, so ``10[rpm] * 2[s]`` is ``rpm*s``.
"""

from __future__ import annotations

from collections.abc import Callable

from cell.scripts.errors import ScriptError
from cell.scripts.expr import Binary, Brace, Call, Name, Node, Num, Unary

Unit = tuple[tuple[str, float], ...] | None
NONE: Unit = ()
SECONDS: Unit = (("s", 1.0),)
HERTZ: Unit = (("s", -1.0),)


def parse_unit(text: str) -> Unit:
    """``none`` (any case) is dimensionless; any other name is a base unit of its own."""
    name = text.strip().lower()
    return NONE if name == "none" else ((name, 1.0),)


def fmt(unit: Unit) -> str:
    if unit is None:
        return "unknown"
    if not unit:
        return "none"
    if unit == HERTZ:
        return "hz"
    return "*".join(n if e == 1 else f"{n}^{e:g}" for n, e in unit)


def mul(a: Unit, b: Unit, sign: float = 1.0) -> Unit:
    if a is None or b is None:
        return None
    powers = dict(a)
    for n, e in b:
        powers[n] = powers.get(n, 0.0) + sign * e
    return tuple(sorted((n, e) for n, e in powers.items() if e != 0.0))


def scale(a: Unit, k: float) -> Unit:
    if a is None:
        return None
    return tuple((n, e * k) for n, e in a if e * k != 0.0)


def _literal(node: Node) -> float | None:
    """Value of a (possibly negated) number literal, else ``None``."""
    sign = 1.0
    while isinstance(node, Unary) and node.op in "+-":
        sign = -sign if node.op == "-" else sign
        node = node.operand
    if isinstance(node, Brace):
        return _literal(node.inner)
    return sign * node.value if isinstance(node, Num) else None


class UnitChecker:
    """Infers the unit of an expression and raises :class:`ScriptError` on a mismatch.

    ``unit_of(name)`` gives the unit of a referenced name (``None`` when unknown);
    ``where(index)`` turns a position in the logical line into ``(line, column)``.
    """

    def __init__(
        self,
        file: str,
        unit_of: Callable[[str], Unit],
        where: Callable[[int], tuple[int, int]],
    ) -> None:
        self.file = file
        self.unit_of = unit_of
        self.where = where

    def _same(self, node: Node, what: str, units: list[Unit]) -> Unit:
        known = [u for u in units if u is not None]
        for u in known[1:]:
            if u != known[0]:
                raise ScriptError(
                    self.file, *self.where(node.pos),
                    f"cannot {what} [{fmt(known[0])}] and [{fmt(u)}] outside braces; "
                    "wrap the expression in {...} to skip unit checking",
                )
        return known[0] if known else None

    def infer(self, node: Node) -> Unit:
        if isinstance(node, Num):
            return None if node.unit is None else parse_unit(node.unit)
        if isinstance(node, Name):
            return self.unit_of(node.name)
        if isinstance(node, Brace):
            return None
        if isinstance(node, Unary):
            u = self.infer(node.operand)
            return NONE if node.op == "not" else u
        if isinstance(node, Binary):
            left, right = self.infer(node.left), self.infer(node.right)
            if node.op in ("+", "-"):
                return self._same(node, "add" if node.op == "+" else "subtract", [left, right])
            # a bare number scales: 2 * x keeps the unit of x
            left = NONE if left is None and _literal(node.left) is not None else left
            right = NONE if right is None and _literal(node.right) is not None else right
            if node.op == "*":
                return mul(left, right)
            if node.op == "/":
                return mul(left, right, -1.0)
            if node.op in ("and", "or"):
                return NONE
            self._same(node, "compare", [left, right])
            return NONE
        if isinstance(node, Call):
            args = [self.infer(a) for a in node.args]
            f = node.func
            if f in ("abs",):
                return args[0]
            if f in ("min", "max", "limit"):
                return self._same(node, f"take @{f} of", args)
            if f == "if":
                return self._same(node, "choose between", args[1:])
            if f == "sqrt":
                return scale(args[0], 0.5)
            if f == "pow":
                if args[0] == NONE:
                    return NONE
                k = _literal(node.args[1])
                return scale(args[0], k) if k is not None else None
            return NONE  # exp, log, log10, sin, cos, tan
        raise TypeError(type(node).__name__)  # pragma: no cover


def stat_unit(suffix: str, unit: Unit) -> Unit:
    """Unit of the running-average statistic ``suffix`` of a signal in ``unit``."""
    if suffix in ("ST", "EN", "TN", "TX"):
        return SECONDS
    if suffix == "RA":
        return HERTZ
    if suffix in ("CV", "NM"):
        return NONE
    if suffix in ("IN", "IT"):
        return mul(unit, SECONDS)
    if suffix in ("CL", "EL"):
        return mul(unit, HERTZ)
    if suffix == "ES":
        return scale(unit, 2.0)
    return unit
