"""One spelling per unit for every channel.

A channel's unit is, in this order:

1. the DBC's, for a channel that is a DBC signal (the DBC is the one source of truth);
2. the unit its block declares (a CyFlex label's ``units`` column, an observer's model
   units), spelled as the DBC spells the same unit: ``MM_H2O`` and ``mmh2o`` are ``mmH2O``;
   ``none`` (dimensionless) is the empty string;
3. for an output that depends on exactly one input channel — a filter of one input, an
   ``.fdv`` output computed from one channel, a running-average statistic of one channel —
   the unit of that input (for a statistic, as the statistic transforms it: an integral of
   ``mmH2O`` is ``mmH2O*s``).

Two spellings are the same unit when they match ignoring case, ``_``, ``-`` and spaces.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover
    from .blocks import Block
    from .runtime import Runtime

#: spellings of units no DBC file may use, by their key (see :func:`key`)
ALIASES = {
    "none": "", "": "", "-": "", "1": "",
    "hz": "Hz", "s": "s", "sec": "s", "ms": "ms",
    "percent": "%", "pct": "%",
    "degc": "°C", "°c": "°C", "celsius": "°C",
    "mmh2o": "mmH2O", "mmwc": "mmH2O",
    "nm": "Nm", "kw": "kW", "kpa": "kPa", "pa": "Pa", "kg/s": "kg/s", "l/h": "L/h",
}
_FACTOR = re.compile(r"([^*^]+)(\^-?[0-9.]+)?")


def key(text: str) -> str:
    """What two spellings of one unit share: lower case, without ``_``, ``-`` and spaces."""
    k = re.sub(r"[\s_]", "", text.strip().lower())
    return k if k == "-" else k.replace("-", "")


def spellings(units: Iterable[str]) -> dict[str, str]:
    """Key -> spelling, from the units the DBC files use (they win over :data:`ALIASES`)."""
    out = dict(ALIASES)
    for u in units:
        if u:
            out[key(u)] = u
    return out


def spell(text: str, known: dict[str, str]) -> str:
    """``text`` in the cell's spelling; each factor of a product (``mmh2o*s``) on its own."""
    text = (text or "").strip()
    if key(text) in known:
        return known[key(text)]
    parts = []
    for factor in text.split("*"):
        m = _FACTOR.fullmatch(factor.strip())
        if m is None:
            return text
        base, power = m.group(1), m.group(2) or ""
        parts.append(known.get(key(base), base) + power)
    if len(parts) == 1:
        return parts[0]
    return "*".join(p for p in parts if p).replace("*s^-1", "/s")


def script_sources(block: Block, out: str) -> set[str] | None:
    """The input channels a script output depends on (through its locals and labels), or
    ``None`` when the block is not a script this knows how to read."""
    graph: dict[str, set[str]] = {}
    stmts = getattr(block, "_stmts", None)
    if stmts is not None:  # .fdv: NAME = expression
        from .formula.expr import names_in

        for st in stmts:
            graph.setdefault(st.target, set()).update(n.name for n in names_in(st.expr))
    elif hasattr(block, "labels") and hasattr(block, "ravgs"):  # CyFlex labels and .ravg
        from .formula.expr import names_in

        for lb in block.labels:
            graph.setdefault(lb.name, set()).update(n.name for n in names_in(lb.expr))
        for ra in block.ravgs:
            for n in ra.names:
                graph.setdefault(n, set()).add(ra.in_variable)
    else:
        return None
    inputs, seen, todo, found = set(block.inputs), set(), [out], set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        if name in inputs:
            found.add(name)
        todo.extend(graph.get(name, ()))
    return found


def _stat_of_input(block: Block, out: str) -> tuple[str, str] | None:
    """``(input channel, statistic suffix)`` when ``out`` is a running-average statistic
    of an input channel (CyFlex ``.ravg``)."""
    from .formula.expr import SUFFIXES

    inputs = set(block.inputs)
    for ra in getattr(block, "ravgs", ()):
        if ra.in_variable in inputs and out in ra.names:
            return ra.in_variable, SUFFIXES[ra.names.index(out)]
    return None


def resolve(rt: Runtime, block: Block, out: str) -> str:
    """The unit of output ``out`` of ``block`` in runtime ``rt`` (see the module's rules)."""
    db = rt.db
    info = db.signals.get(out)
    if info is not None and info.unit:
        return info.unit
    known = spellings(s.unit for s in db.signals.values())

    def unit_of(channel: str) -> str:
        src = db.signals.get(channel) or rt._channels.get(channel)
        return spell(src.unit, known) if src is not None else ""

    stat = _stat_of_input(block, out)
    if stat is not None:
        from .formula.units import fmt, parse_unit, stat_unit

        channel, suffix = stat
        base = unit_of(channel)
        u = stat_unit(suffix, parse_unit(base) if base else None)
        if u is not None:
            text = fmt(u)
            return "" if text == "none" else spell(text, known)
    declared = block.units.get(out, "")
    if declared and key(declared) != "":
        return spell(declared, known)
    if declared:  # declared dimensionless
        return ""
    if block.keeps_input_unit and len(block.inputs) == 1:
        return unit_of(block.inputs[0])
    sources = script_sources(block, out)
    if sources is not None and len(sources) == 1:
        return unit_of(next(iter(sources)))
    return ""


__all__ = ["ALIASES", "key", "resolve", "script_sources", "spell", "spellings"]
