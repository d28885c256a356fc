"""The PUMA-style ``.fdv`` dialect: a cyclic Formula Device script (seed 004, Figures 5-6).

A script has two sections, each introduced by its own line::

    [init]        // runs once at load (Figure 5)
    dim Q_EXH_BP_R
    Q_EXH_BP_R = 4*pow(10,-6)
    [formulas]    // runs every cycle, top to bottom (Figure 6)
    public EXH_BP_R_Kalman
    EXH_BP_R_Kalman = ...

Statements are ``dim NAME`` (a local, starting at 0), ``public NAME`` (an output channel,
also a variable), and ``NAME = expression``. ``//`` starts a comment and a trailing ``\\``
continues a line. A name that is neither declared nor a function is an input channel.
A ``// rate: FAS`` comment (or the ``rate`` argument) picks the task; the default is MED.

Locals assigned in ``[init]`` and never in ``[formulas]`` are the script's constants
(Figure 5's ``Q_EXH_BP_R`` and ``R_EXH_BP_R``); :meth:`FdvBlock.set_constants` changes them.

This dialect is this project's own, modelled on the published listings; it claims no
compatibility with AVL PUMA.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from cell.runtime.blocks import RATE_NAMES
from cell.scripts.block import ScriptBlock
from cell.scripts.codegen import compile_functions, emit
from cell.scripts.errors import ErrorList, ScriptError
from cell.scripts.expr import FUNCTIONS, KEYWORDS, Name, Node, Parser, Tokenizer, names_in, render
from cell.scripts.source import LogicalLine, logical_lines

#: Most statements a script may hold.
MAX_STATEMENTS = 5_000

SECTIONS = ("init", "formulas")
_SECTION = re.compile(r"\s*\[\s*([^\]]*?)\s*\]\s*$")
_RATE = re.compile(r"//\s*rate\s*:\s*(\S*)", re.IGNORECASE)
_IDENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_RESERVED = KEYWORDS | set(FUNCTIONS) | {"dim", "public"}


@dataclass
class Statement:
    section: str
    target: str
    expr: Node
    line: LogicalLine
    target_pos: int  # index of the target in the line
    expr_start: int

    @property
    def where(self) -> tuple[int, int]:
        return self.line.at(self.target_pos)


class FdvBlock(ScriptBlock):
    """A compiled ``.fdv`` script (seed 004, Figures 5-6).

    Parameters
    ----------
    name:
        Script name, e.g. ``kalman.fdv``; used in error messages and as the block name.
    text:
        The script.
    rate:
        ``FAS``, ``MED`` or ``SLO``; overrides a ``// rate:`` comment. Default MED.
    rates:
        Accepted for a uniform loader signature; ``.fdv`` scripts do not use rates in Hz.

    Raises
    ------
    ScriptError
        With every load error found, each as ``file:line:column: message``.
    """

    kind = "fdv"
    dialect = "fdv"

    def __init__(self, name: str, text: str, rate: str | None = None, rates: Any = None) -> None:
        errors = ErrorList()
        self.file = name
        lines = logical_lines(name, text, "//", errors)
        directive_rate = self._rate_directive(name, text, errors)
        stmts, declared, publics = self._parse(name, lines, errors)
        errors.raise_if_any()
        chosen = rate or directive_rate or "MED"
        if chosen not in RATE_NAMES:
            raise ScriptError(name, 1, 1, f"bad rate {chosen!r}; expected FAS, MED or SLO")
        inputs = self._resolve(name, stmts, declared, publics, errors)
        errors.raise_if_any()
        super().__init__(name, inputs, publics, chosen)
        self.source = text
        self._outputs_set = frozenset(publics)
        self._stmts = stmts
        self._compile(stmts, declared, inputs)

    # -- parsing ---------------------------------------------------------------------
    @staticmethod
    def _rate_directive(file: str, text: str, errors: ErrorList) -> str | None:
        found = None
        for number, raw in enumerate(text.splitlines(), start=1):
            m = _RATE.search(raw)
            if m is None:
                continue
            value = m.group(1).upper()
            if value not in RATE_NAMES:
                errors.add(ScriptError(file, number, m.start(1) + 1,
                                       f"bad rate {m.group(1)!r}; expected FAS, MED or SLO",
                                       expected="FAS, MED or SLO"))
            elif found is None:
                found = value
        return found

    def _parse(
        self, file: str, lines: list[LogicalLine], errors: ErrorList
    ) -> tuple[list[Statement], dict[str, tuple[str, tuple[int, int]]], list[str]]:
        self._decl_seen: dict[str, dict[str, tuple[int, int]]] = {}
        section: str | None = None
        seen_sections: dict[str, int] = {}
        stmts: list[Statement] = []
        declared: dict[str, tuple[str, tuple[int, int]]] = {}  # name -> (kind, where)
        publics: list[str] = []
        for line in lines:
            text = line.text
            m = _SECTION.match(text)
            if m:
                name = m.group(1).lower()
                col = text.index("[") + 1
                if name not in SECTIONS:
                    errors.add(ScriptError(file, line.line, line.at(col)[1],
                                           f"unknown section [{m.group(1)}]; expected [init] or "
                                           "[formulas]", expected="[init] or [formulas]"))
                    section = "bad"
                    continue
                if name in seen_sections:
                    errors.add(ScriptError(file, line.line, line.at(col - 1)[1],
                                           f"section [{name}] appears twice (first at line "
                                           f"{seen_sections[name]})"))
                seen_sections[name] = line.line
                section = name
                continue
            if section is None:
                ln, col = line.at(len(text) - len(text.lstrip()))
                errors.add(ScriptError(file, ln, col, "a statement before any section; start "
                                       "the script with [init] or [formulas]",
                                       expected="[init] or [formulas]"))
                section = "bad"
                continue
            if section == "bad":
                continue
            try:
                stmt = self._statement(file, line, section, declared, publics)
            except ScriptError as exc:
                errors.add(exc)
                continue
            if stmt is not None:
                stmts.append(stmt)
                if len(stmts) > MAX_STATEMENTS:
                    errors.add(ScriptError(file, *stmt.where, f"more than {MAX_STATEMENTS} "
                                           "statements"))
                    break
        if "formulas" not in seen_sections and not errors:
            errors.add(ScriptError(file, lines[-1].line if lines else 1, 1,
                                   "the script has no [formulas] section",
                                   expected="a [formulas] section"))
        return stmts, declared, publics

    def _statement(
        self,
        file: str,
        line: LogicalLine,
        section: str,
        declared: dict[str, tuple[str, tuple[int, int]]],
        publics: list[str],
    ) -> Statement | None:
        tz = Tokenizer(file, line, cyflex=False)
        toks = tz.tokens()
        first = toks[0]
        if first.kind == "NAME" and first.text in ("dim", "public") and toks[1].kind == "NAME":
            target = toks[1]
            if toks[2].kind != "END":
                raise tz.error(toks[2].start, f"expected end of line after {first.text} "
                               f"{target.text}, got {toks[2].text!r}", expected="end of line")
            self._check_name(tz, target.start, target.text)
            kind = first.text
            where = line.at(target.start)
            seen = self._decl_seen.setdefault(kind, {})
            if target.text in seen:
                raise tz.error(target.start, f"{target.text} is already declared with {kind} "
                               f"at line {seen[target.text][0]}")
            seen[target.text] = where
            if kind == "public":
                publics.append(target.text)
                declared[target.text] = ("public", where)
            elif target.text not in declared:
                declared[target.text] = ("dim", where)
            return None
        if first.kind == "NAME" and first.text in ("dim", "public"):
            raise tz.error(toks[1].start, f"expected a name after {first.text}, got "
                           f"{'end of line' if toks[1].kind == 'END' else repr(toks[1].text)}",
                           expected="a name")
        if first.kind == "NAME" and toks[1].kind == "OP" and toks[1].text == "=":
            self._check_name(tz, first.start, first.text)
            if toks[2].kind == "END":
                raise tz.error(toks[2].start, "expected an expression after '='",
                               expected="an expression")
            expr = Parser(file, line, toks[2:], cyflex=False).parse()
            return Statement(section, first.text, expr, line, first.start, toks[2].start)
        raise tz.error(first.start, "expected a statement: 'dim NAME', 'public NAME' or "
                       "'NAME = expression'", expected="a statement")

    @staticmethod
    def _check_name(tz: Tokenizer, pos: int, name: str) -> None:
        if name in _RESERVED:
            raise tz.error(pos, f"{name!r} is a reserved word and cannot be a variable")

    def _resolve(
        self,
        file: str,
        stmts: list[Statement],
        declared: dict[str, tuple[str, tuple[int, int]]],
        publics: list[str],
        errors: ErrorList,
    ) -> list[str]:
        inputs: list[str] = []
        for st in stmts:
            if st.target not in declared:
                errors.add(ScriptError(file, *st.where, f"{st.target} is not declared; add "
                                       f"'dim {st.target}' for a local or 'public {st.target}' "
                                       "for an output", expected="a declared name"))
            for ref in names_in(st.expr):
                if ref.name in declared:
                    continue
                if st.section == "init":
                    errors.add(ScriptError(file, *st.line.at(ref.pos),
                                           f"[init] runs once at load and cannot read input "
                                           f"channel {ref.name}; declare it with dim if it is "
                                           "a local"))
                elif ref.name not in inputs:
                    inputs.append(ref.name)
        return inputs

    # -- code generation -------------------------------------------------------------
    def _compile(self, stmts: list[Statement], declared: dict, inputs: list[str]) -> None:
        names = list(declared)
        self._slot = {n: k for k, n in enumerate(names)}
        self._S = [0.0] * len(names)
        init = [s for s in stmts if s.section == "init"]
        formulas = [s for s in stmts if s.section == "formulas"]
        in_formulas = {s.target for s in formulas}
        in_init = {s.target for s in init}
        self._const_slot = {
            n: self._slot[n] for n in names
            if declared[n][0] == "dim" and n in in_init and n not in in_formulas
        }
        self.locals = [n for n in names if declared[n][0] == "dim"]
        for n in names:
            self._keys[n] = (
                declared[n][0],
                tuple(render(s.expr) for s in init if s.target == n),
                tuple(render(s.expr) for s in formulas if s.target == n),
            )
        input_id = {n: f"i{k}" for k, n in enumerate(inputs)}
        var_id = {n: f"v{k}" for k, n in enumerate(names)}

        def ref(node: Name) -> str:
            return var_id.get(node.name) or input_id[node.name]

        src: list[str] = []
        table: list[tuple[str, int, int]] = []
        # [init]: runs once; an error there is a load error
        used = _used(init, declared)
        src.append("def _init(S):")
        src += [f"    {var_id[n]} = S[{self._slot[n]}]" for n in used] or ["    pass"]
        for st in init:
            k = len(table)
            table.append((st.target, *st.where))
            src += [
                "    try:",
                f"        _r = {emit(st.expr, ref)}",
                "        if _r - _r:",
                "            _r = _nonfinite(_r)",
                f"        {var_id[st.target]} = _r",
                "    except _ERRS as _e:",
                f"        return ({k}, _e)",
            ]
        src += [f"    S[{self._slot[n]}] = {var_id[n]}" for n in sorted(in_init, key=names.index)]
        src.append("    return None")
        # [formulas]: runs every step
        used = _used(formulas, declared)
        counts: dict[str, int] = {}
        for st in formulas:
            counts[st.target] = counts.get(st.target, 0) + 1
        src.append("def _formulas(S, I, bad):")
        src += [f"    {var_id[n]} = S[{self._slot[n]}]" for n in used]
        src += [f"    {input_id[n]} = I[{n!r}]" for n in inputs]
        assigned_before: set[str] = set()
        for st in formulas:
            k = len(table)
            table.append((st.target, *st.where))
            ln, col = st.where
            target = var_id[st.target]
            risky = [r for r in dict.fromkeys(x.name for x in names_in(st.expr))
                     if r in assigned_before]
            src.append(f"    # line {ln}: {st.target}")
            ind = "    "
            if risky:
                cond = " or ".join(f"{r!r} in bad" for r in risky)
                src += [f"    if bad and ({cond}):",
                        f"        bad[{st.target!r}] = _dep(bad, {tuple(risky)!r})",
                        "    else:"]
                ind = "        "
            if isinstance(st.expr, Name) and st.expr.name in declared:
                src.append(f"{ind}{target} = {ref(st.expr)}")
                if counts[st.target] > 1:
                    src.append(f"{ind}if bad: bad.pop({st.target!r}, None)")
            else:
                src += [
                    f"{ind}try:",
                    f"{ind}    _r = {emit(st.expr, ref)}",
                    f"{ind}    if _r - _r:",
                    f"{ind}        _r = _nonfinite(_r)",
                    f"{ind}    {target} = _r",
                ]
                if counts[st.target] > 1:
                    src.append(f"{ind}    if bad: bad.pop({st.target!r}, None)")
                src += [f"{ind}except _ERRS as _e:",
                        f"{ind}    bad[{st.target!r}] = _why({k}, _e)"]
            assigned_before.add(st.target)
        src += [f"    S[{self._slot[n]}] = {var_id[n]}" for n in names if n in in_formulas]
        outs = ", ".join(f"{n!r}: {var_id[n]}" for n in self.outputs)
        src.append(f"    return {{{outs}}}")
        for n in list(declared) + inputs:
            assert _IDENT.fullmatch(n), n  # only identifiers reach the generated code
        self.generated = "\n".join(src) + "\n"

        ns = compile_functions(self.generated, f"<fdv {self.name}>", self._error_helpers(table))
        self._run = ns["_formulas"]
        failed = ns["_init"](self._S)
        if failed is not None:
            k, exc = failed
            target, line, col = table[k]
            raise ScriptError(self.name, line, col,
                              f"[init] failed: {self.why(target, line, col, exc)}")

    # -- stepping --------------------------------------------------------------------
    def step(
        self, t: float, inputs: dict[str, float], ticking: frozenset[str] | None = None
    ) -> dict[str, float]:
        """Run ``[formulas]`` once with the inputs' latest values; return every output."""
        bad: dict[str, str] = {}
        try:
            out = self._run(self._S, inputs, bad)
        except KeyError as exc:
            raise KeyError(f"script {self.name} needs input {exc.args[0]!r}") from None
        return self._finish(out, bad)

    def _step(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        return self.step(t, inputs)

    def dependencies(self) -> dict[str, set[str]]:
        graph: dict[str, set[str]] = {}
        for st in self._stmts:  # NAME = expression
            graph.setdefault(st.target, set()).update(n.name for n in names_in(st.expr))
        return graph

    def describe(self) -> dict[str, Any]:
        out = super().describe()
        out["locals"] = list(self.locals)
        return out


def _used(stmts: list[Statement], declared: dict) -> list[str]:
    """Declared names read or assigned by ``stmts``, in declaration order."""
    seen = {s.target for s in stmts}
    for s in stmts:
        seen.update(r.name for r in names_in(s.expr) if r.name in declared)
    return [n for n in declared if n in seen]
