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
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover
    from cell.bus.dbc import CellDatabase
    from cell.runtime.blocks import Block

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


def resolve(db: CellDatabase, block: Block, out: str,
            channel_unit: Callable[[str], str | None]) -> str:
    """The unit of output ``out`` of ``block`` (see the module's rules).

    ``db`` is the DBC catalogue; ``channel_unit(name)`` is the unit of a channel the runtime
    already has (an output of another block), or ``None``.
    """
    info = db.signals.get(out)
    if info is not None and info.unit:
        return info.unit
    known = spellings(s.unit for s in db.signals.values())

    def unit_of(channel: str) -> str:
        sig = db.signals.get(channel)
        unit = sig.unit if sig is not None else channel_unit(channel)
        return spell(unit, known) if unit is not None else ""

    stat = block.statistic_unit(out, unit_of)
    if stat is not None:
        return stat if stat == "" else spell(stat, known)
    declared = block.units.get(out, "")
    if declared and key(declared) != "":
        return spell(declared, known)
    if declared:  # declared dimensionless
        return ""
    if block.keeps_input_unit and len(block.inputs) == 1:
        return unit_of(block.inputs[0])
    sources = block.sources_of(out)
    if sources is not None and len(sources) == 1:
        return unit_of(next(iter(sources)))
    return ""


__all__ = ["ALIASES", "key", "resolve", "spell", "spellings"]
