"""The CyFlex-style General Labels (``.labels``) and Running Averages (``.ravg``) dialect.

Modelled on seed 004, Figures 2 and 3; this project's own dialect, claiming no
compatibility with Cummins CyFlex.

``.labels``: each label is a header line followed by its expression line(s)::

    # Label units format initial_value interval hst_flag tolerance
    K_EXH_BP_R none 3 0.1 MED OFF 1.0
    P_EXH_BP_R * @pow((P_EXH_BP_R + R_Gain_EXH_BP_R),-1[none])

The interval is ``FAS``, ``MED`` or ``SLO``; ``#`` starts a comment; a trailing ``\\``
continues a line. Functions are spelled ``@pow``, ``@abs``, ``@sqrt``, ``@exp``, ``@log``,
``@log10``, ``@sin``, ``@cos``, ``@tan``, ``@min``, ``@max``, ``@limit``, ``@if``. Numbers may
carry a unit, ``4[none]``; ``{...}`` evaluates without unit checking. Each label starts at
its initial value; at each tick of its interval, labels are evaluated in file order, so a
reference to the label itself or to a later label reads its previous value.

``.ravg``: each line is ``in_variable samples rate statistical_variable`` (the paper's
trailing dot after the statistical variable is accepted). At each tick of its rate, after
that tick's labels, the running average adds one sample of ``in_variable`` and publishes
``statistical_variable.SUFFIX`` for the 22 suffixes of :mod:`cell.scripts.stats`.

Before a running average has its first sample its statistics are unavailable: a label
reading one keeps its value (its initial value) until the sample arrives. This is what
makes Figure 3's ``P_prev_EXH_BP_R`` start at its declared initial value 1, as Figure 5's
``P_Prev_EXH_BP_R`` does.

A label whose expression references nothing (e.g. ``Q_Gain_EXH_BP_R``) is a constant:
its value is computed at load and can be changed with :meth:`CyflexBlock.set_constants`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from collections.abc import Callable
from typing import Any

from cell.runtime.blocks import RATE_NAMES
from cell.scripts.block import ScriptBlock, rates_hz
from cell.scripts.codegen import compile_functions, emit
from cell.scripts.errors import ErrorList, ScriptError
from cell.scripts.expr import (
    _UNIT_TEXT,
    KEYWORDS,
    SUFFIXES,
    Name,
    Node,
    names_in,
    parse_expression,
    render,
)
from cell.scripts.source import LogicalLine, logical_lines
from cell.scripts.stats import MAX_SAMPLES, RunningStats
from cell.scripts.label_units import Unit, UnitChecker, fmt, parse_unit, stat_unit

#: Most labels plus running averages in one set.
MAX_ITEMS = 5_000

HEADER = "Label units format initial_value interval hst_flag tolerance"
RAVG_LINE = "in_variable samples rate statistical_variable"
_IDENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_CHANNEL = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(?:\.[A-Z]{2})?")
_FIELD = re.compile(r"\S+")
_STAT_NAME = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)\.([A-Z]{2})")
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")


@dataclass
class Label:
    name: str
    units: str
    decimals: int
    initial: float
    interval: str
    history: bool
    tolerance: float
    line: LogicalLine  # header line
    expr: Node | None = None
    expr_line: LogicalLine | None = None
    constant: bool = False


@dataclass
class RunningAverage:
    in_variable: str
    samples: int
    rate: str
    statvar: str
    line: LogicalLine
    names: list[str] = field(default_factory=list)


def _fields(line: LogicalLine) -> list[tuple[str, int]]:
    return [(m.group(0), m.start()) for m in _FIELD.finditer(line.text)]


def _looks_like_header(line: LogicalLine) -> bool:
    f = _fields(line)
    return len(f) == 7 and f[4][0].upper() in RATE_NAMES and _IDENT.fullmatch(f[0][0]) is not None


class CyflexBlock(ScriptBlock):
    """A compiled CyFlex-style set: a ``.labels`` file and optionally its ``.ravg`` file.

    Parameters
    ----------
    name:
        Script name, e.g. ``kalman.labels``; the block name and the file in errors.
    text:
        The General Labels text (may be empty when only running averages are wanted).
    ravg_text:
        The Running Averages text with the same stem, or ``None``.
    rates:
        FAS/MED/SLO in Hz (mapping or :class:`cell.runtime.scheduler.Rates`); default 50/10/1 Hz.
        Gives running averages their ``RA`` and ``IN`` rectangle width.
    ravg_name:
        File name used in errors of ``ravg_text``; default ``<stem>.ravg``.

    Notes
    -----
    The block is stepped at every tick of any interval it uses; ``ticking`` decides which
    labels and running averages run. Outputs are every label and every statistic channel;
    a step returns those that ran at that tick.

    Raises
    ------
    ScriptError
        With every load error found, each as ``file:line:column: message``.
    """

    kind = "cyflex"
    dialect = "cyflex"

    def __init__(
        self,
        name: str,
        text: str,
        ravg_text: str | None = None,
        rates: Any = None,
        ravg_name: str | None = None,
    ) -> None:
        errors = ErrorList()
        stem = name.rsplit(".", 1)[0] if "." in name else name
        self.ravg_file = ravg_name or f"{stem}.ravg"
        self.rates_hz = rates_hz(rates)
        labels = self._parse_labels(name, text or "", errors)
        ravgs = self._parse_ravgs(self.ravg_file, ravg_text, {lb.name for lb in labels}, errors)
        errors.raise_if_any()
        if not labels and not ravgs:
            raise ScriptError(name, 1, 1, "the set defines no label and no running average",
                              expected=f"a label header '{HEADER}'")
        if len(labels) + len(ravgs) > MAX_ITEMS:
            raise ScriptError(name, 1, 1, f"more than {MAX_ITEMS} labels and running averages")
        self.labels = labels
        self.ravgs = ravgs
        self._label = {lb.name: lb for lb in labels}
        self._stat_of: dict[str, tuple[int, str]] = {}  # "statvar.SUF" -> (ravg index, suffix)
        for j, ra in enumerate(ravgs):
            ra.names = [f"{ra.statvar}.{s}" for s in SUFFIXES]
            for s in SUFFIXES:
                self._stat_of[f"{ra.statvar}.{s}"] = (j, s)
        inputs = self._resolve(name, errors)
        errors.raise_if_any()
        used = {lb.interval for lb in labels} | {ra.rate for ra in ravgs}
        rates = tuple(r for r in RATE_NAMES if r in used)
        outputs = [lb.name for lb in labels] + [n for ra in ravgs for n in ra.names]
        super().__init__(name, inputs, outputs, rates)
        self.source = text or ""
        self.ravg_source = ravg_text
        self._outputs_set = frozenset(outputs)
        self._units_and_constants(name, errors)
        errors.raise_if_any()
        self._compile()

    # -- parsing ---------------------------------------------------------------------

    def dependencies(self) -> dict[str, set[str]]:
        graph: dict[str, set[str]] = {}
        for lb in self.labels:
            graph.setdefault(lb.name, set()).update(n.name for n in names_in(lb.expr))
        for ra in self.ravgs:
            for n in ra.names:
                graph.setdefault(n, set()).add(ra.in_variable)
        return graph

    def statistic_unit(self, out: str, unit_of: Callable[[str], str]) -> str | None:
        """The unit of a running-average statistic of an input channel (``.ravg``)."""
        inputs = set(self.inputs)
        for ra in self.ravgs:
            if ra.in_variable in inputs and out in ra.names:
                suffix = SUFFIXES[ra.names.index(out)]
                base = unit_of(ra.in_variable)
                u = stat_unit(suffix, parse_unit(base) if base else None)
                if u is None:
                    return None
                text = fmt(u)
                return "" if text == "none" else text
        return None
    def _parse_labels(self, file: str, text: str, errors: ErrorList) -> list[Label]:
        labels: list[Label] = []
        seen: dict[str, int] = {}
        pending: Label | None = None
        skip_next = False
        for line in logical_lines(file, text, "#", errors):
            if skip_next:
                skip_next = False
                if not _looks_like_header(line):
                    continue  # the expression of a label whose header was refused
            if pending is not None:
                if _looks_like_header(line):
                    errors.add(ScriptError(file, pending.line.line, 1,
                                           f"label {pending.name} has no expression line "
                                           "before the next label header",
                                           expected="an expression line"))
                    pending = None
                else:
                    try:
                        pending.expr = parse_expression(file, line, 0, cyflex=True)
                        pending.expr_line = line
                        labels.append(pending)
                    except ScriptError as exc:
                        errors.add(exc)
                    pending = None
                    continue
            try:
                pending = self._header(file, line)
            except ScriptError as exc:
                errors.add(exc)
                skip_next = True
                continue
            if pending.name in seen:
                errors.add(ScriptError(file, line.line, line.at(0)[1],
                                       f"label {pending.name} is already defined at line "
                                       f"{seen[pending.name]}"))
            seen.setdefault(pending.name, line.line)
        if pending is not None:
            errors.add(ScriptError(file, pending.line.line, 1, f"label {pending.name} has no "
                                   "expression line (end of file)", expected="an expression line"))
        return labels

    @staticmethod
    def _header(file: str, line: LogicalLine) -> Label:
        f = _fields(line)

        def err(k: int, message: str, expected: str) -> ScriptError:
            return ScriptError(file, *line.at(f[k][1]), message, expected=expected)

        if len(f) != 7:
            ln, col = line.at(f[0][1])
            raise ScriptError(file, ln, col, f"bad label header: expected 7 fields '{HEADER}', "
                              f"got {len(f)}", expected=HEADER)
        name, units, decimals, initial, interval, hst, tol = (x for x, _ in f)
        if not _IDENT.fullmatch(name) or name in KEYWORDS:
            raise err(0, f"bad label name {name!r}", "a name of letters, digits and _")
        if not _UNIT_TEXT.fullmatch(units):
            raise err(1, f"bad units {units!r}", "a unit name such as none or rpm")
        if not decimals.isdigit():
            raise err(2, f"bad format {decimals!r}", "a whole number of decimal places")
        if not _NUMBER.fullmatch(initial) or not math.isfinite(float(initial)):
            raise err(3, f"bad initial_value {initial!r}", "a number")
        if interval.upper() not in RATE_NAMES:
            raise err(4, f"bad interval {interval!r}; expected FAS, MED or SLO", "FAS, MED or SLO")
        if hst.upper() not in ("ON", "OFF"):
            raise err(5, f"bad hst_flag {hst!r}; expected ON or OFF", "ON or OFF")
        if not _NUMBER.fullmatch(tol) or not math.isfinite(float(tol)):
            raise err(6, f"bad tolerance {tol!r}", "a number")
        return Label(name, units, int(decimals), float(initial), interval.upper(),
                     hst.upper() == "ON", float(tol), line)

    def _parse_ravgs(
        self, file: str, text: str | None, labels: set[str], errors: ErrorList
    ) -> list[RunningAverage]:
        if text is None:
            return []
        out: list[RunningAverage] = []
        seen: dict[str, int] = {}
        for line in logical_lines(file, text, "#", errors):
            f = _fields(line)

            def err(k: int, message: str, expected: str, f=f, line=line) -> ScriptError:
                return ScriptError(file, *line.at(f[k][1]), message, expected=expected)

            if len(f) != 4:
                errors.add(ScriptError(file, *line.at(f[0][1]), f"bad running-average line: "
                                       f"expected 4 fields '{RAVG_LINE}', got {len(f)}",
                                       expected=RAVG_LINE))
                continue
            invar, samples, rate, statvar = (x for x, _ in f)
            statvar = statvar.removesuffix(".")
            if not _CHANNEL.fullmatch(invar):
                errors.add(err(0, f"bad in_variable {invar!r}", "a label or channel name"))
                continue
            if not samples.isdigit() or not 1 <= int(samples) <= MAX_SAMPLES:
                errors.add(err(1, f"bad samples {samples!r}", f"a whole number 1..{MAX_SAMPLES}"))
                continue
            if rate.upper() not in RATE_NAMES:
                errors.add(err(2, f"bad rate {rate!r}; expected FAS, MED or SLO",
                               "FAS, MED or SLO"))
                continue
            if not _IDENT.fullmatch(statvar):
                errors.add(err(3, f"bad statistical_variable {f[3][0]!r}",
                               "a name of letters, digits and _ (optionally ending in '.')"))
                continue
            if statvar in seen:
                errors.add(err(3, f"statistical variable {statvar} is already defined at line "
                               f"{seen[statvar]}", "a new name"))
                continue
            seen[statvar] = line.line
            out.append(RunningAverage(invar, int(samples), rate.upper(), statvar, line))
        return out

    def _resolve(self, file: str, errors: ErrorList) -> list[str]:
        inputs: list[str] = []

        def use(name: str) -> None:
            if name not in self._label and name not in self._stat_of and name not in inputs:
                inputs.append(name)

        for lb in self.labels:
            for ref in names_in(lb.expr):
                use(ref.name)
            lb.constant = not names_in(lb.expr)
        for ra in self.ravgs:
            use(ra.in_variable)
        return inputs

    def _units_and_constants(self, file: str, errors: ErrorList) -> None:
        unit_of_label = {lb.name: parse_unit(lb.units) for lb in self.labels}
        ravg_unit: list[Unit] = []
        for ra in self.ravgs:
            src = ra.in_variable
            if src in unit_of_label:
                u = unit_of_label[src]
            elif src in self._stat_of:
                j, s = self._stat_of[src]
                u = stat_unit(s, ravg_unit[j]) if j < len(ravg_unit) else None
            else:
                u = None
            ravg_unit.append(u)

        def unit_of(name: str) -> Unit:
            if name in unit_of_label:
                return unit_of_label[name]
            if name in self._stat_of:
                j, s = self._stat_of[name]
                return stat_unit(s, ravg_unit[j])
            return None

        for lb in self.labels:
            self.units[lb.name] = lb.units
            line = lb.expr_line
            checker = UnitChecker(file, unit_of, line.at)
            try:
                got = checker.infer(lb.expr)
            except ScriptError as exc:
                errors.add(exc)
                continue
            want = unit_of_label[lb.name]
            if got is not None and got != want:
                errors.add(ScriptError(
                    file, *line.at(len(line.text) - len(line.text.lstrip())),
                    f"label {lb.name} is declared in [{fmt(want)}] but its expression is in "
                    f"[{fmt(got)}]; wrap the expression in {{...}} to skip unit checking"))
        for j, ra in enumerate(self.ravgs):
            for s, n in zip(SUFFIXES, ra.names):
                u = stat_unit(s, ravg_unit[j])
                self.units[n] = "" if u is None else fmt(u)

    # -- code generation -------------------------------------------------------------
    def _compile(self) -> None:
        labels, ravgs = self.labels, self.ravgs
        S: list[float] = []
        for lb in labels:
            self._slot[lb.name] = len(S)
            S.append(lb.initial)
            self._keys[lb.name] = (lb.interval, render(lb.expr))
        self._ravg_base: list[int] = []
        for ra in ravgs:
            self._ravg_base.append(len(S))
            for n in ra.names:
                self._slot[n] = len(S)
                S.append(math.nan)
            S[self._slot[f"{ra.statvar}.NM"]] = 0.0
            S[self._slot[f"{ra.statvar}.RA"]] = self.rates_hz[ra.rate]
        self._S = S
        self._stats = [RunningStats(ra.samples, self.rates_hz[ra.rate]) for ra in ravgs]
        # constants: evaluated once at load
        const_src = ["def _const():", "    _k = -1"]
        for lb in labels:
            if lb.constant:
                self._const_slot[lb.name] = len(S)
                S.append(math.nan)
                const_src += ["    try:", f"        _k = {self._const_slot[lb.name]}",
                              f"        S[_k] = {emit(lb.expr, lambda n: 'nan')}",
                              "    except _ERRS as _e:", "        return (_k, _e)"]
        const_src.append("    return None")
        ns = compile_functions("\n".join(const_src) + "\n", f"<labels {self.name}>", {"S": S})
        failed = ns["_const"]()
        bad_const = next((n for n, k in self._const_slot.items() if not math.isfinite(S[k])), None)
        if failed is not None or bad_const is not None:
            k = failed[0] if failed is not None else self._const_slot[bad_const]
            lb = next(lb for lb in labels if self._const_slot.get(lb.name) == k)
            why = failed[1] if failed is not None else ArithmeticError(f"result is {S[k]}")
            ln, col = lb.expr_line.at(lb.expr.pos)
            raise ScriptError(self.name, ln, col, f"constant label {lb.name} cannot be "
                              f"computed: {self.why(lb.name, ln, col, why)}")
        for n in self.inputs + list(self._label):
            assert _CHANNEL.fullmatch(n), n  # only channel names reach the generated code
        self._fns: dict[frozenset[str], Any] = {}
        self._by_key: dict[frozenset[str], Any] = {}
        self.generated: dict[str, str] = {}
        rates = self.rates
        for mask in range(1, 1 << len(rates)):
            key = frozenset(r for b, r in enumerate(rates) if mask >> b & 1)
            self._by_key[key] = self._compile_tick(key)

    def _compile_tick(self, ticking: frozenset[str]) -> Any:
        labels = [lb for lb in self.labels if lb.interval in ticking]
        ravgs = [(j, ra) for j, ra in enumerate(self.ravgs) if ra.rate in ticking]
        slot = self._slot
        label_id = {lb.name: f"v{slot[lb.name]}" for lb in self.labels}
        input_id = {n: f"i{k}" for k, n in enumerate(self.inputs)}
        read_labels: set[str] = set()
        read_stats: set[str] = set()
        read_inputs: set[str] = set()
        for lb in labels:
            read_labels.add(lb.name)
            for r in names_in(lb.expr):
                if r.name in self._label:
                    read_labels.add(r.name)
                elif r.name in self._stat_of:
                    read_stats.add(r.name)
                else:
                    read_inputs.add(r.name)
        for _, ra in ravgs:
            src = ra.in_variable
            if src in self._label:
                read_labels.add(src)
            elif src not in self._stat_of:
                read_inputs.add(src)

        def ref(node: Name) -> str:
            n = node.name
            if n in label_id:
                return label_id[n]
            if n in self._stat_of:
                return f"s{slot[n]}"
            return input_id[n]

        table: list[tuple[str, int, int]] = []
        src = ["def _tick(S, I, bad, t, _ravg):"]
        src += [f"    {label_id[n]} = S[{slot[n]}]" for n in self._label if n in read_labels]
        src += [f"    s{slot[n]} = S[{slot[n]}]" for n in sorted(read_stats, key=slot.get)]
        src += [f"    {input_id[n]} = I[{n!r}]" for n in self.inputs if n in read_inputs]
        done: set[str] = set()
        for lb in labels:
            target = label_id[lb.name]
            ln, col = lb.expr_line.at(lb.expr.pos)
            src.append(f"    # line {ln}: {lb.name}")
            if lb.constant:
                src.append(f"    {target} = S[{self._const_slot[lb.name]}]")
                continue  # a constant cannot fail, so it never taints a later label
            refs = list(dict.fromkeys(r.name for r in names_in(lb.expr)))
            ind = "    "
            need = sorted({self._stat_of[r][0] for r in refs if r in self._stat_of})
            if need:
                nm = " and ".join(f"S[{slot[self.ravgs[j].statvar + '.NM']}] > 0.0" for j in need)
                src.append(f"{ind}if {nm}:")
                ind += "    "
            risky = [r for r in refs if r in done]
            if risky:
                cond = " or ".join(f"{r!r} in bad" for r in risky)
                src += [f"{ind}if bad and ({cond}):",
                        f"{ind}    bad[{lb.name!r}] = _dep(bad, {tuple(risky)!r})",
                        f"{ind}else:"]
                ind += "    "
            k = len(table)
            table.append((lb.name, ln, col))
            src += [
                f"{ind}try:",
                f"{ind}    _r = {emit(lb.expr, ref)}",
                f"{ind}    if _r - _r:",
                f"{ind}        _r = _nonfinite(_r)",
                f"{ind}    {target} = _r",
                f"{ind}except _ERRS as _e:",
                f"{ind}    bad[{lb.name!r}] = _why({k}, _e)",
            ]
            done.add(lb.name)
        src += [f"    S[{slot[lb.name]}] = {label_id[lb.name]}" for lb in labels]
        outs = ", ".join(f"{lb.name!r}: {label_id[lb.name]}" for lb in labels)
        src.append(f"    out = {{{outs}}}")
        for j, ra in ravgs:
            x = ra.in_variable
            if x in self._label:
                value = label_id[x]
            elif x in self._stat_of:
                value = f"S[{slot[x]}]"
            else:
                value = input_id[x]
            src.append(f"    # running average {ra.statvar} (line {ra.line.line})")
            if x in done:
                src += [f"    if bad and {x!r} in bad:",
                        f"        _ravg({j}, t, None, out, bad, bad[{x!r}])",
                        "    else:",
                        f"        _ravg({j}, t, {value}, out, bad, None)"]
            elif x in self._stat_of:
                j2 = self._stat_of[x][0]
                src += [f"    if S[{slot[self.ravgs[j2].statvar + '.NM']}] > 0.0:",
                        f"        _ravg({j}, t, {value}, out, bad, None)",
                        "    else:",
                        f"        _ravg({j}, t, None, out, bad, '')"]
            else:
                src.append(f"    _ravg({j}, t, {value}, out, bad, None)")
        src.append("    return out")
        text = "\n".join(src) + "\n"
        self.generated["+".join(r for r in RATE_NAMES if r in ticking)] = text

        ns = compile_functions(text, f"<labels {self.name}>", self._error_helpers(table))
        return ns["_tick"]

    def _ravg(self, j: int, t: float, value: float | None, out: dict[str, float],
              bad: dict[str, str], why: str | None) -> None:
        """Run running average ``j``: add a sample, store and publish its statistics."""
        ra = self.ravgs[j]
        base = self._ravg_base[j]
        S = self._S
        names = ra.names
        if why is None and value is not None and value - value:
            why = f"{ra.in_variable} is {value}"
        if why is not None or value is None:
            # no valid sample: the window and its statistics hold
            if why:
                for n in names:
                    bad[n] = f"{ra.statvar}: no sample, {why}"
                out.update(zip(names, S[base:base + len(names)]))
            return
        stats = self._stats[j]
        stats.add(t, value)
        vals = stats.values()
        S[base:base + len(vals)] = vals
        out.update(zip(names, vals))
        for k, v in enumerate(vals):
            if v - v:
                suffix = SUFFIXES[k]
                note = {"CV": "mean is 0", "EL": "all sample times are equal"}.get(suffix, "")
                bad[names[k]] = f"{names[k]}: undefined ({note or f'result is {v}'})"

    # -- stepping --------------------------------------------------------------------
    def step(
        self, t: float, inputs: dict[str, float], ticking: frozenset[str] | None = None
    ) -> dict[str, float]:
        """Run the labels and running averages whose interval ticks at ``t``.

        Returns the values of the labels and statistics that ran at this tick.
        """
        fn = self._fns.get(ticking)
        if fn is None:
            key = frozenset(self.rates) if ticking is None else frozenset(ticking) & frozenset(
                self.rates)
            if not key:
                return {}
            fn = self._fns[ticking] = self._by_key[key]
        bad: dict[str, str] = {}
        try:
            out = fn(self._S, inputs, bad, t, self._ravg)
        except KeyError as exc:
            raise KeyError(f"script {self.name} needs input {exc.args[0]!r}") from None
        return self._finish(out, bad)

    def _step(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        return self.step(t, inputs, getattr(self, "ticking", None))

    # -- views and hot swap ----------------------------------------------------------
    def _constants_changed(self, checked: dict[str, float]) -> None:
        pass  # constant labels read their slot at their next tick

    def _adopt_more(self, old: ScriptBlock) -> list[str]:
        if not isinstance(old, CyflexBlock):
            return []
        adopted = []
        old_by_var = {ra.statvar: (j, ra) for j, ra in enumerate(old.ravgs)}
        for j, ra in enumerate(self.ravgs):
            hit = old_by_var.get(ra.statvar)
            if hit is None:
                continue
            oj, ora = hit
            if (ora.in_variable, ora.samples, ora.rate) != (ra.in_variable, ra.samples, ra.rate):
                continue
            self._stats[j].load(old._stats[oj].window())
            base, obase = self._ravg_base[j], old._ravg_base[oj]
            n = len(SUFFIXES)
            self._S[base:base + n] = old._S[obase:obase + n]
            self._S[self._slot[f"{ra.statvar}.RA"]] = self.rates_hz[ra.rate]
            adopted.append(ra.statvar)
        return adopted

    def state(self) -> dict[str, Any]:
        S = self._S
        return {
            "steps": self.steps,
            "labels": {lb.name: S[self._slot[lb.name]] for lb in self.labels},
            "running_averages": {ra.statvar: self._stats[j].state()
                                 for j, ra in enumerate(self.ravgs)},
        }

    def describe(self) -> dict[str, Any]:
        out = super().describe()
        out["labels"] = [
            {"name": lb.name, "units": lb.units, "format": lb.decimals, "initial_value": lb.initial,
             "interval": lb.interval, "hst_flag": "ON" if lb.history else "OFF",
             "tolerance": lb.tolerance, "constant": lb.constant}
            for lb in self.labels
        ]
        out["running_averages"] = [
            {"in_variable": ra.in_variable, "samples": ra.samples, "rate": ra.rate,
             "statistical_variable": ra.statvar, "channels": list(ra.names)}
            for ra in self.ravgs
        ]
        out["ravg_source"] = self.ravg_source
        return out
