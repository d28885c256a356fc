"""Tokenizer, syntax tree and Pratt parser shared by both script dialects.

The expression language is the one of seed 004's listings: numbers, ``+ - * /``, unary
minus, parentheses, function calls (``pow(a,b)`` in Figure 6, ``@pow(a,b)`` in Figure 3),
comparisons, ``and``/``or``/``not`` and ``if(cond, a, b)``. The CyFlex dialect adds unit
annotations on numbers (``4[none]``), braces ``{...}`` that switch unit checking off, and
running-average statistic names such as ``a_X_hat_EXH_BP_R_lm.FV`` (Figure 2).

The parser is hand written and bounded: nesting deeper than :data:`MAX_DEPTH` is a load
error, so hostile input costs linear work and never reaches Python's recursion limit.
There is no attribute access, indexing, string, lambda or loop in the grammar.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

from cell.scripts.errors import ScriptError
from cell.scripts.source import LogicalLine

#: Deepest nesting of an expression tree (parentheses, calls, operator chains).
MAX_DEPTH = 100

#: Running-average statistic suffixes in the order of seed 004, Figure 2.
SUFFIXES = (
    "AV", "MN", "MX", "RN", "SD", "CV", "ST", "EN", "TN", "TX", "IV",
    "FV", "DL", "IN", "IT", "ES", "EO", "EL", "CL", "CO", "RA", "NM",
)

#: Function name -> (minimum, maximum) number of arguments (``None``: no maximum).
FUNCTIONS: dict[str, tuple[int, int | None]] = {
    "pow": (2, 2),
    "abs": (1, 1),
    "sqrt": (1, 1),
    "exp": (1, 1),
    "log": (1, 1),
    "log10": (1, 1),
    "sin": (1, 1),
    "cos": (1, 1),
    "tan": (1, 1),
    "min": (2, None),
    "max": (2, None),
    "limit": (3, 3),
    "if": (3, 3),
}

KEYWORDS = frozenset({"and", "or", "not"})
COMPARISONS = ("<", "<=", ">", ">=", "==", "<>", "!=")
_BINARY_PREC = {"or": 1, "and": 2, "+": 5, "-": 5, "*": 6, "/": 6}
_BINARY_PREC.update({op: 4 for op in COMPARISONS})
_PREFIX_NOT_PREC = 3
_UNARY_PREC = 7

_NUMBER = re.compile(r"(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_UNIT = re.compile(r"\[([^\[\]\s{}()]*)\]")
_UNIT_TEXT = re.compile(r"[A-Za-z0-9_%/*^.+-]+")
_SUFFIX = re.compile(r"\.([A-Za-z]+)")


# -- syntax tree -------------------------------------------------------------------------
@dataclass(eq=False)
class Node:
    """Base of the syntax tree; ``pos`` indexes the logical line the node starts at."""

    pos: int
    height: int = field(default=1, init=False)


@dataclass(eq=False)
class Num(Node):
    value: float = 0.0
    unit: str | None = None


@dataclass(eq=False)
class Name(Node):
    name: str = ""


@dataclass(eq=False)
class Unary(Node):
    op: str = "-"  # "-", "+" or "not"
    operand: Node | None = None


@dataclass(eq=False)
class Binary(Node):
    op: str = "+"  # arithmetic, comparison, "and", "or"
    left: Node | None = None
    right: Node | None = None


@dataclass(eq=False)
class Call(Node):
    func: str = ""
    args: list[Node] = field(default_factory=list)


@dataclass(eq=False)
class Brace(Node):
    """``{...}``: the contents evaluate normally, without unit checking (Figure 3)."""

    inner: Node | None = None


def children(node: Node) -> list[Node]:
    if isinstance(node, Unary):
        return [node.operand]
    if isinstance(node, Binary):
        return [node.left, node.right]
    if isinstance(node, Call):
        return list(node.args)
    if isinstance(node, Brace):
        return [node.inner]
    return []


def names_in(node: Node) -> list[Name]:
    """Every :class:`Name` in ``node``, left to right (iterative; trees are bounded anyway)."""
    out: list[Name] = []
    stack = [node]
    while stack:
        n = stack.pop()
        if isinstance(n, Name):
            out.append(n)
        stack.extend(reversed(children(n)))
    return out


# -- tokens ------------------------------------------------------------------------------
@dataclass
class Token:
    kind: str  # NUM NAME STAT FUNC UNIT OP END
    text: str
    start: int
    value: float = 0.0
    unit: str | None = None


class Tokenizer:
    """Turns a slice of a logical line into tokens; raises :class:`ScriptError` on bad input."""

    def __init__(self, file: str, line: LogicalLine, cyflex: bool) -> None:
        self.file = file
        self.line = line
        self.cyflex = cyflex

    def error(self, index: int, message: str, expected: str | None = None) -> ScriptError:
        ln, col = self.line.at(index)
        return ScriptError(self.file, ln, col, message, expected)

    def tokens(self, start: int = 0, end: int | None = None) -> list[Token]:
        text = self.line.text
        end = len(text) if end is None else end
        out: list[Token] = []
        i = start
        while i < end:
            ch = text[i]
            if ch.isspace():
                i += 1
                continue
            if ch.isdigit() or (ch == "." and i + 1 < end and text[i + 1].isdigit()):
                i = self._number(text, i, end, out)
                continue
            if ch.isalpha() or ch == "_":
                i = self._name(text, i, end, out)
                continue
            if ch == "@":
                m = _NAME.match(text, i + 1, end)
                if not self.cyflex:
                    raise self.error(i, "unexpected character '@'; functions are called "
                                     "without '@' in .fdv scripts, e.g. pow(a, b)")
                if not m:
                    raise self.error(i, "'@' must be followed by a function name, e.g. @pow",
                                     expected="a function name")
                out.append(Token("FUNC", m.group(0), i))
                i = m.end()
                continue
            if ch == "[":
                m = _UNIT.match(text, i, end)
                if self.cyflex and m:
                    out.append(Token("UNIT", m.group(0), i, unit=m.group(1)))
                    i = m.end()
                    continue
                if self.cyflex:
                    raise self.error(i, "unclosed or malformed unit annotation; write e.g. 4[none]",
                                     expected="']'")
                raise self.error(i, "indexing with '[...]' is not part of the language")
            two = text[i:i + 2]
            if two in ("<=", ">=", "==", "<>", "!="):
                out.append(Token("OP", two, i))
                i += 2
                continue
            if two == "**":
                raise self.error(i, "'**' is not an operator; use " + self._fn("pow") + "(a, b)")
            if ch in "+-*/(),<>=" or (self.cyflex and ch in "{}"):
                out.append(Token("OP", ch, i))
                i += 1
                continue
            if ch == "^":
                raise self.error(i, "'^' is not an operator; use " + self._fn("pow") + "(a, b)")
            if ch == ".":
                raise self.error(i, "attribute access with '.' is not part of the language")
            if ch in "{}":
                raise self.error(i, f"unexpected character {ch!r}; braces belong to the "
                                 "CyFlex-style .labels dialect")
            raise self.error(i, f"unexpected character {ch!r}")
        out.append(Token("END", "", end))
        return out

    def _fn(self, name: str) -> str:
        return "@" + name if self.cyflex else name

    def _number(self, text: str, i: int, end: int, out: list[Token]) -> int:
        m = _NUMBER.match(text, i, end)
        j = m.end()
        if j < end and (text[j].isalnum() or text[j] in "_."):
            k = j
            while k < end and (text[k].isalnum() or text[k] in "_."):
                k += 1
            raise self.error(i, f"bad number {text[i:k]!r}",
                             expected="a number such as 1, 0.1 or 4e-6")
        value = float(m.group(0))
        if not math.isfinite(value):
            raise self.error(i, f"number {m.group(0)!r} is too large")
        unit = None
        if j < end and text[j] == "[":
            if not self.cyflex:
                raise self.error(j, "unit annotations like 4[none] belong to the CyFlex-style "
                                 ".labels dialect")
            um = _UNIT.match(text, j, end)
            if not um:
                raise self.error(j, "unclosed or malformed unit annotation; write e.g. 4[none]",
                                 expected="']'")
            unit = um.group(1)
            if not _UNIT_TEXT.fullmatch(unit):
                raise self.error(j + 1, f"bad unit {unit!r}",
                                 expected="a unit name such as none or rpm")
            j = um.end()
        out.append(Token("NUM", text[i:j], i, value=value, unit=unit))
        return j

    def _name(self, text: str, i: int, end: int, out: list[Token]) -> int:
        m = _NAME.match(text, i, end)
        j = m.end()
        name = m.group(0)
        if j < end and text[j] == ".":
            sm = _SUFFIX.match(text, j, end) if self.cyflex else None
            if sm is None:
                raise self.error(j, f"attribute access '{name}.' is not part of the language")
            suffix = sm.group(1)
            if suffix not in SUFFIXES:
                raise self.error(
                    j + 1, f"unknown running-average statistic .{suffix} (attribute access "
                    "is not part of the language); known: " + ", ".join(SUFFIXES),
                    expected="a statistic suffix",
                )
            j = sm.end()
            if j < end and text[j] == ".":
                raise self.error(j, "attribute access with '.' is not part of the language")
            out.append(Token("STAT", text[i:j], i))
            return j
        out.append(Token("NAME", name, i))
        return j


# -- parser -------------------------------------------------------------------------------
class Parser:
    """Pratt parser over one expression. Raises :class:`ScriptError` at the first error."""

    def __init__(self, file: str, line: LogicalLine, tokens: list[Token], cyflex: bool) -> None:
        self.file = file
        self.line = line
        self.toks = tokens
        self.i = 0
        self.cyflex = cyflex
        self.depth = 0

    # helpers
    def error(self, index: int, message: str, expected: str | None = None) -> ScriptError:
        ln, col = self.line.at(index)
        return ScriptError(self.file, ln, col, message, expected)

    @property
    def tok(self) -> Token:
        return self.toks[self.i]

    def describe(self, tok: Token) -> str:
        return "end of line" if tok.kind == "END" else repr(tok.text)

    def expect(self, text: str, what: str, opened: Token | None = None) -> Token:
        tok = self.tok
        if tok.kind == "OP" and tok.text == text:
            self.i += 1
            return tok
        where = ""
        if opened is not None:
            ln, col = self.line.at(opened.start)
            where = f" to close {opened.text!r} opened at {ln}:{col}"
        raise self.error(tok.start, f"expected {what}{where}, got {self.describe(tok)}",
                         expected=what)

    def _node(self, node: Node, *kids: Node) -> Node:
        node.height = 1 + max((k.height for k in kids), default=0)
        if node.height > MAX_DEPTH:
            raise self.error(node.pos, f"expression is nested more than {MAX_DEPTH} levels deep; "
                             "split it into several statements")
        return node

    # grammar
    def parse(self) -> Node:
        node = self.expr(0)
        tok = self.tok
        if tok.kind != "END":
            if tok.kind == "OP" and tok.text == "=":
                raise self.error(tok.start, "unexpected '='; '=' assigns, use '==' to compare",
                                 expected="an operator or end of line")
            if tok.kind == "OP" and tok.text in ")}":
                raise self.error(tok.start, f"unmatched {tok.text!r}")
            raise self.error(tok.start, f"expected an operator or end of line, got "
                             f"{self.describe(tok)}", expected="an operator or end of line")
        return node

    def expr(self, min_prec: int) -> Node:
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise self.error(self.tok.start, f"expression is nested more than {MAX_DEPTH} levels "
                             "deep; split it into several statements")
        try:
            left = self.prefix(min_prec)
            last_cmp = False
            while True:
                tok = self.tok
                op = tok.text if tok.kind in ("OP", "NAME") else None
                prec = _BINARY_PREC.get(op) if op is not None else None
                if prec is None or prec < min_prec:
                    return left
                if tok.kind == "NAME" and op not in ("and", "or"):
                    return left
                if op in COMPARISONS and last_cmp:
                    raise self.error(tok.start, "comparisons do not chain; write "
                                     "(a < b) and (b < c)")
                self.i += 1
                right = self.expr(prec + 1)
                left = self._node(Binary(tok.start, op=op, left=left, right=right), left, right)
                last_cmp = op in COMPARISONS
        finally:
            self.depth -= 1

    def prefix(self, min_prec: int) -> Node:
        tok = self.tok
        if tok.kind == "OP" and tok.text in "-+":
            self.i += 1
            operand = self.expr(_UNARY_PREC)
            return self._node(Unary(tok.start, op=tok.text, operand=operand), operand)
        if tok.kind == "NAME" and tok.text == "not":
            if min_prec > _PREFIX_NOT_PREC:
                raise self.error(tok.start, "put 'not ...' in parentheses here")
            self.i += 1
            operand = self.expr(_PREFIX_NOT_PREC)
            return self._node(Unary(tok.start, op="not", operand=operand), operand)
        return self.primary()

    def primary(self) -> Node:
        tok = self.tok
        if tok.kind == "NUM":
            self.i += 1
            return Num(tok.start, value=tok.value, unit=tok.unit)
        if tok.kind == "UNIT":
            raise self.error(tok.start, f"a unit annotation {tok.text} must follow a number "
                             f"(did you mean 1{tok.text}?)", expected="a number before the unit")
        if tok.kind == "STAT":
            self.i += 1
            if self.tok.kind == "UNIT":
                raise self.error(self.tok.start, "only numbers take unit annotations")
            return Name(tok.start, name=tok.text)
        if tok.kind == "FUNC":
            return self.call(tok, tok.text)
        if tok.kind == "NAME":
            nxt = self.toks[self.i + 1]
            is_call = nxt.kind == "OP" and nxt.text == "("
            if tok.text in KEYWORDS:
                raise self.error(tok.start, f"expected a value, got {tok.text!r}",
                                 expected="a value")
            if is_call:
                if self.cyflex:
                    hint = (f"; did you mean @{tok.text}?" if tok.text in FUNCTIONS
                            else "; functions are spelled @name, e.g. @pow")
                    raise self.error(tok.start, f"unknown function {tok.text!r}{hint}")
                return self.call(tok, tok.text)
            if not self.cyflex and tok.text in FUNCTIONS:
                raise self.error(tok.start, f"{tok.text!r} is a function; call it as "
                                 f"{tok.text}(...)", expected="'('")
            self.i += 1
            if self.tok.kind == "UNIT":
                raise self.error(self.tok.start, "only numbers take unit annotations")
            return Name(tok.start, name=tok.text)
        if tok.kind == "OP" and tok.text == "(":
            self.i += 1
            inner = self.expr(0)
            self.expect(")", "')'", opened=tok)
            return inner
        if tok.kind == "OP" and tok.text == "{":
            self.i += 1
            inner = self.expr(0)
            self.expect("}", "'}'", opened=tok)
            return self._node(Brace(tok.start, inner=inner), inner)
        what = "a number, a name, a function call or '('"
        raise self.error(tok.start, f"expected a value ({what}), got {self.describe(tok)}",
                         expected=what)

    def call(self, tok: Token, fname: str) -> Node:
        spelled = ("@" if self.cyflex else "") + fname
        if fname not in FUNCTIONS:
            known = ", ".join(("@" if self.cyflex else "") + f for f in FUNCTIONS)
            raise self.error(tok.start, f"unknown function {spelled!r}; known: {known}",
                             expected="a known function")
        self.i += 1
        opened = self.expect("(", "'('")
        args: list[Node] = []
        if not (self.tok.kind == "OP" and self.tok.text == ")"):
            while True:
                args.append(self.expr(0))
                if self.tok.kind == "OP" and self.tok.text == ",":
                    self.i += 1
                    continue
                break
        self.expect(")", "')' or ','", opened=opened)
        lo, hi = FUNCTIONS[fname]
        if len(args) < lo or (hi is not None and len(args) > hi):
            want = str(lo) if lo == hi else (f"at least {lo}" if hi is None else f"{lo} to {hi}")
            raise self.error(tok.start, f"{spelled} takes {want} argument"
                             f"{'s' if want != '1' else ''}, got {len(args)}")
        return self._node(Call(tok.start, func=fname, args=args), *args)


def parse_expression(file: str, line: LogicalLine, start: int, cyflex: bool) -> Node:
    """Parse ``line.text[start:]`` as one expression."""
    toks = Tokenizer(file, line, cyflex).tokens(start)
    if toks[0].kind == "END":
        raise ScriptError(file, *line.at(start), "expected an expression, got end of line",
                          expected="an expression")
    return Parser(file, line, toks, cyflex).parse()


def render(node: Node) -> str:
    """Canonical text of an expression (fully parenthesised); used to compare formulas."""
    parts: list[str] = []

    def go(n: Node) -> None:
        if isinstance(n, Num):
            parts.append(repr(n.value) + (f"[{n.unit}]" if n.unit is not None else ""))
        elif isinstance(n, Name):
            parts.append(n.name)
        elif isinstance(n, Unary):
            parts.append(f"({n.op} ")
            go(n.operand)
            parts.append(")")
        elif isinstance(n, Binary):
            parts.append("(")
            go(n.left)
            parts.append(f" {n.op} ")
            go(n.right)
            parts.append(")")
        elif isinstance(n, Call):
            parts.append(n.func + "(")
            for k, a in enumerate(n.args):
                if k:
                    parts.append(", ")
                go(a)
            parts.append(")")
        elif isinstance(n, Brace):
            parts.append("{")
            go(n.inner)
            parts.append("}")

    go(node)
    return "".join(parts)
