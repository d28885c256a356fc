"""A user's signals on the channels the cell's blocks read (``--map CELL_CHANNEL=SIGNAL``).

The cell's filters, observers and controllers read the cell's own channel names
(``EXH_BP_R``, ...). A real cell's DAQ names its signals its own way and often in its own
units. A mapping says "my ``DAQ_BP_R`` in kPa is the cell's ``EXH_BP_R``": right after a
frame is decoded, the mapped channel takes the source signal's value, converted, with the
source's bus time and status (an implausible source value makes the mapped channel
``invalid``; a source whose frames stop makes it ``stale`` after the source's own cycle).
While a channel is mapped, frames that carry a signal of that channel's own name are not
read into it: the mapping is its one source.

Entries
-------
``CELL_CHANNEL=SIGNAL`` converts between the two units when both are known and differ
(:data:`UNITS`: pressure, temperature, speed, fraction, mass flow, time); equal units need
nothing. ``CELL_CHANNEL=SIGNAL*SCALE+OFFSET`` (``*SCALE`` and ``+OFFSET``/``-OFFSET`` each
optional) gives the conversion explicitly, and wins over the unit table. An unknown unit
pair without an explicit conversion is refused naming both units. ``SIGNAL`` may be
``MESSAGE.SIGNAL`` to pick a signal of one message.

A mapping file (``--map FILE``, YAML or JSON) holds the same entries, either as an object
``{CELL_CHANNEL: "SIGNAL[*SCALE+OFFSET]"}`` or as a list of ``{channel, signal, scale,
offset}`` objects. Every error names the entry (``--map 'X=Y'`` or the file and line).

At start a mapping onto a channel no block reads, onto a block's output, from a signal no
loaded DBC file has, or a channel mapped twice, is refused (:class:`ConfigError`, exit 2).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cell.core.errors import ConfigError
from cell.runtime.units import key as unit_key

if TYPE_CHECKING:  # pragma: no cover
    from cell.bus.dbc import CellDatabase
    from cell.runtime.scheduler import Runtime

# -- units -----------------------------------------------------------------------------------
#: standard acceleration of gravity, m/s^2 (exact, CGPM 1901)
G_N = 9.80665
#: the international avoirdupois pound, kg, and inch, m (exact, 1959)
LB, INCH = 0.45359237, 0.0254

#: unit key (:func:`cell.runtime.units.key`) -> (quantity, factor, offset): the value in the
#: quantity's base unit is ``value * factor + offset``. The factors are exact by definition
#: (mmH2O and inH2O are the conventional ones, at 1000 kg/m^3 and standard gravity).
UNITS: dict[str, tuple[str, float, float]] = {
    # pressure, base Pa
    "pa": ("pressure", 1.0, 0.0),
    "hpa": ("pressure", 100.0, 0.0),
    "kpa": ("pressure", 1e3, 0.0),
    "mpa": ("pressure", 1e6, 0.0),
    "mbar": ("pressure", 100.0, 0.0),
    "bar": ("pressure", 1e5, 0.0),
    "atm": ("pressure", 101325.0, 0.0),
    "psi": ("pressure", LB * G_N / INCH ** 2, 0.0),
    "mmh2o": ("pressure", G_N, 0.0),
    "mmwc": ("pressure", G_N, 0.0),
    "cmh2o": ("pressure", 10 * G_N, 0.0),
    "inh2o": ("pressure", 25.4 * G_N, 0.0),
    "mmhg": ("pressure", 101325.0 / 760.0, 0.0),
    "torr": ("pressure", 101325.0 / 760.0, 0.0),
    # temperature, base K
    "k": ("temperature", 1.0, 0.0),
    "degc": ("temperature", 1.0, 273.15),
    "°c": ("temperature", 1.0, 273.15),
    "c": ("temperature", 1.0, 273.15),
    "degf": ("temperature", 5.0 / 9.0, 273.15 - 32.0 * 5.0 / 9.0),
    "°f": ("temperature", 5.0 / 9.0, 273.15 - 32.0 * 5.0 / 9.0),
    # rotational speed, base rad/s
    "rad/s": ("speed", 1.0, 0.0),
    "rpm": ("speed", 2.0 * math.pi / 60.0, 0.0),
    "1/min": ("speed", 2.0 * math.pi / 60.0, 0.0),
    "krpm": ("speed", 2.0 * math.pi / 60.0 * 1e3, 0.0),
    # fraction, base 1 (a unit-less channel has no known unit: it is never converted)
    "%": ("fraction", 0.01, 0.0),
    "percent": ("fraction", 0.01, 0.0),
    "pct": ("fraction", 0.01, 0.0),
    "ppm": ("fraction", 1e-6, 0.0),
    "permille": ("fraction", 1e-3, 0.0),
    # mass flow, base kg/s
    "kg/s": ("mass flow", 1.0, 0.0),
    "g/s": ("mass flow", 1e-3, 0.0),
    "kg/h": ("mass flow", 1.0 / 3600.0, 0.0),
    # time, base s
    "s": ("time", 1.0, 0.0),
    "ms": ("time", 1e-3, 0.0),
    "min": ("time", 60.0, 0.0),
    "h": ("time", 3600.0, 0.0),
}


def conversion(source_unit: str, target_unit: str) -> tuple[float, float] | None:
    """``(scale, offset)`` with ``target = source * scale + offset``; ``None`` when the pair
    is unknown (either unit unknown or empty, or two quantities). Equal spellings (ignoring
    case, ``_``, ``-`` and spaces) give ``(1, 0)``."""
    a, b = unit_key(source_unit or ""), unit_key(target_unit or "")
    if a == b and a:
        return 1.0, 0.0
    ua, ub = UNITS.get(a), UNITS.get(b)
    if ua is None or ub is None or ua[0] != ub[0]:
        return None
    # base = v * fa + oa; target = (base - ob) / fb
    scale = ua[1] / ub[1]
    offset = (ua[2] - ub[2]) / ub[1]
    return scale, offset


# -- entries ---------------------------------------------------------------------------------
_NAME = r"[A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)?"
_NUM = r"[0-9]+(?:\.[0-9]*)?(?:[eE][+-]?[0-9]+)?|\.[0-9]+(?:[eE][+-]?[0-9]+)?"
_SOURCE = re.compile(rf"\s*(?P<src>{_NAME})\s*(?:\*\s*(?P<scale>[+-]?(?:{_NUM}))\s*)?"
                     rf"(?:(?P<sign>[+-])\s*(?P<off>{_NUM})\s*)?")


@dataclass(frozen=True)
class MapEntry:
    """One mapping: ``target = source * scale + offset`` (see the module notes)."""

    target: str
    source: str
    scale: float = 1.0
    offset: float = 0.0
    explicit: bool = False
    """The conversion was given (``*scale+offset``), not taken from the units."""
    where: str = ""
    """Where the entry was given: ``--map 'X=Y'`` or ``file line N``."""
    source_unit: str = ""
    target_unit: str = ""
    message: str = ""
    """The DBC message that carries the source signal (set when checked)."""
    signal: str = ""
    """The source's signal name within its message (set when checked)."""

    def convert(self, value: float) -> float:
        return value * self.scale + self.offset

    def describe(self) -> str:
        how = (f"*{self.scale:.10g}{self.offset:+.10g}" if (self.scale, self.offset) != (1.0, 0.0)
               else "")
        units = (f" ({self.source_unit or 'no unit'} -> {self.target_unit or 'no unit'})"
                 if self.source_unit != self.target_unit else "")
        return f"{self.target}={self.source}{how}{units}"


def _number(v: Any, what: str, at: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise ConfigError(f"{at}: {what} must be a finite number, got {v!r}")
    return float(v)


def parse_source(target: str, text: Any, where: str) -> MapEntry:
    """An entry from its target and ``SIGNAL[*SCALE][+OFFSET]`` text."""
    if not isinstance(target, str) or not re.fullmatch(_NAME, target.strip()) or "." in target:
        raise ConfigError(f"{where}: {target!r} is not a channel name")
    if not isinstance(text, str):
        raise ConfigError(f"{where}: the signal of {target} must be a name "
                          f"(SIGNAL or SIGNAL*SCALE+OFFSET), got {text!r}")
    m = _SOURCE.fullmatch(text)
    if m is None:
        raise ConfigError(f"{where}: {text!r} is not SIGNAL, SIGNAL*SCALE+OFFSET or "
                          f"MESSAGE.SIGNAL (e.g. EXH_BP_R=DAQ_BP_R*101.97+0)")
    scale = float(m["scale"]) if m["scale"] is not None else None
    offset = float(m["sign"] + m["off"]) if m["off"] is not None else None
    if scale is not None and (scale == 0.0 or not math.isfinite(scale)):
        raise ConfigError(f"{where}: the scale must be a finite number other than 0, got "
                          f"{m['scale']}")
    explicit = scale is not None or offset is not None
    return MapEntry(target.strip(), m["src"], 1.0 if scale is None else scale,
                    0.0 if offset is None else offset, explicit, where)


def parse_spec(spec: str) -> MapEntry:
    """One ``--map CELL_CHANNEL=SIGNAL[*SCALE+OFFSET]`` argument."""
    where = f"--map {spec!r}"
    target, sep, source = spec.partition("=")
    if not sep:
        raise ConfigError(f"{where}: give CELL_CHANNEL=SIGNAL or a mapping file")
    return parse_source(target.strip(), source, where)


def _file_entries(data: Any, marks: list[str], source: str) -> list[MapEntry]:
    out: list[MapEntry] = []
    if isinstance(data, dict):
        for i, (target, text) in enumerate(data.items()):
            at = f"{source}" + (f" {marks[i]}" if i < len(marks) else "") + f", entry {target}"
            out.append(parse_source(str(target), text, at))
        return out
    if not isinstance(data, list):
        raise ConfigError(f"{source}: must be an object {{CELL_CHANNEL: SIGNAL}} or a list of "
                          f"{{channel, signal, scale, offset}}, got {type(data).__name__}")
    for i, entry in enumerate(data):
        at = f"{source}" + (f" {marks[i]}" if i < len(marks) else f" entry {i + 1}")
        if not isinstance(entry, dict):
            raise ConfigError(f"{at}: must be an object with channel, signal, scale, offset; "
                              f"got {entry!r}")
        extra = [k for k in entry if k not in ("channel", "signal", "scale", "offset")]
        if extra:
            raise ConfigError(f"{at}: unknown key {extra[0]!r}; an entry takes channel, "
                              f"signal, scale, offset")
        target, signal = entry.get("channel"), entry.get("signal")
        if not isinstance(target, str) or not target.strip():
            raise ConfigError(f"{at}: 'channel' must name a channel of the cell, got {target!r}")
        at = f"{at}, entry {target.strip()}"
        if not isinstance(signal, str) or not signal.strip():
            raise ConfigError(f"{at}: 'signal' must name a signal, got {signal!r}")
        if re.search(r"[*+]", signal):
            raise ConfigError(f"{at}: give the conversion as 'scale' and 'offset', not in "
                              f"'signal' ({signal!r})")
        e = parse_source(target, signal, at)
        if "scale" in entry or "offset" in entry:
            scale = _number(entry.get("scale", 1.0), "'scale'", at)
            if scale == 0.0:
                raise ConfigError(f"{at}: 'scale' must not be 0")
            e = MapEntry(e.target, e.source, scale, _number(entry.get("offset", 0.0),
                                                            "'offset'", at), True, at)
        out.append(e)
    return out


def read_file(path: str | Path) -> list[MapEntry]:
    """The entries of a mapping file (``.json``; otherwise YAML, of which JSON is a subset)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"--map {path}: cannot read: {exc.strerror or exc}") from None
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise ConfigError(f"--map {path}: not valid JSON: {exc}") from None
        return _file_entries(data, [], str(path))
    import yaml

    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"--map {path}: not valid YAML: {' '.join(str(exc).split())}") from None
    marks: list[str] = []
    if isinstance(node, yaml.MappingNode):
        marks = [f"line {k.start_mark.line + 1}" for k, _ in node.value]
    elif isinstance(node, yaml.SequenceNode):
        marks = [f"line {n.start_mark.line + 1}" for n in node.value]
    return _file_entries(data, marks, str(path))


def parse_maps(items: Iterable[str]) -> list[MapEntry]:
    """Every ``--map`` argument: ``X=Y`` entries, and mapping files (an argument without ``=``)."""
    out: list[MapEntry] = []
    for item in items:
        item = str(item)
        if "=" in item:
            out.append(parse_spec(item))
        else:
            out.extend(read_file(item))
    return out


# -- checking against a cell ---------------------------------------------------------------
def _cell_unit(name: str) -> str | None:
    """The unit the cell's own DBC files give a channel of the cell (any engine's), or
    ``None`` when none of them defines it."""
    try:
        own = _cell_catalogue()
    except ConfigError:  # pragma: no cover - the cell's own files always load
        return None
    info = own.signals.get(name)
    return info.unit if info is not None else None


_OWN: list[Any] = []


def _cell_catalogue() -> CellDatabase:
    from cell.bus.dbc import CellDatabase

    if not _OWN:
        _OWN.append(CellDatabase())
    return _OWN[0]


def _find_signal(db: CellDatabase, name: str) -> tuple[str, str, str] | None:
    """``(message, signal, unit)`` of a source name: a signal, or ``MESSAGE.SIGNAL``."""
    info = db.signals.get(name)
    if info is not None:
        return info.message, info.name, info.unit
    msg_name, dot, sig_name = name.partition(".")
    if dot:
        for m in db.messages:
            if m.name == msg_name:
                for s in m.signals:
                    if s.name == sig_name:
                        return m.name, s.name, s.unit or ""
    return None


class SignalMap:
    """Checked mappings of one runtime, keyed by the (message, signal) they read."""

    def __init__(self, entries: Sequence[MapEntry] = ()) -> None:
        self.entries: list[MapEntry] = list(entries)
        #: (message, signal) -> the entries fed by it
        self.by_source: dict[tuple[str, str], list[MapEntry]] = {}
        for e in self.entries:
            self.by_source.setdefault((e.message, e.signal), []).append(e)
        #: the mapped channels: no frame's own signal of these names is read into them
        self.targets: frozenset[str] = frozenset(e.target for e in self.entries)

    def __bool__(self) -> bool:
        return bool(self.entries)

    def describe(self) -> list[str]:
        return [e.describe() for e in self.entries]


def check(entries: Sequence[MapEntry], db: CellDatabase, reads: Iterable[str],
          outputs: Iterable[str] = ()) -> SignalMap:
    """Check entries against a cell: its DBC catalogue ``db``, the channels its blocks read
    (``reads``) and its blocks' outputs; :class:`ConfigError` names the first bad entry."""
    reads = set(reads)
    outputs = set(outputs)
    seen: dict[str, str] = {}
    out: list[MapEntry] = []
    for e in entries:
        at = e.where or f"--map {e.target}={e.source}"
        if e.target in seen:
            raise ConfigError(f"{at}: {e.target} is already mapped by {seen[e.target]}")
        seen[e.target] = at
        if e.target in outputs:
            raise ConfigError(f"{at}: {e.target} is an output of a block of this cell, not "
                              f"a channel its blocks read")
        if e.target not in reads:
            listing = ", ".join(sorted(reads)) or "none"
            raise ConfigError(f"{at}: no block of this cell reads {e.target}; the channels "
                              f"its blocks read: {listing}")
        found = _find_signal(db, e.source)
        if found is None:
            files = ", ".join(p.name for p in db.files)
            raise ConfigError(f"{at}: no loaded DBC file has a signal {e.source} (loaded: "
                              f"{files}; add yours with --dbc)")
        message, signal, source_unit = found
        if signal == e.target and message == _message_of(db, e.target):
            raise ConfigError(f"{at}: {e.target} cannot be mapped onto itself")
        info = db.signals.get(e.target)
        target_unit = info.unit if info is not None else _cell_unit(e.target)
        target_unit = target_unit or ""
        scale, offset = e.scale, e.offset
        if not e.explicit:
            conv = (1.0, 0.0) if not source_unit and not target_unit else \
                conversion(source_unit, target_unit)
            if conv is None:
                raise ConfigError(
                    f"{at}: cannot convert {e.source} in {source_unit or 'no unit'!s} to "
                    f"{e.target} in {target_unit or 'no unit'!s}: the units "
                    f"{source_unit!r} and {target_unit!r} are not a known pair; give the "
                    f"conversion, e.g. {e.target}={e.source}*SCALE+OFFSET")
            scale, offset = conv
        out.append(MapEntry(e.target, e.source, scale, offset, e.explicit, at, source_unit,
                            target_unit, message, signal))
    return SignalMap(out)


def _message_of(db: CellDatabase, signal: str) -> str | None:
    info = db.signals.get(signal)
    return info.message if info is not None else None


def install(rt: Runtime, items: Iterable[str]) -> SignalMap:
    """Parse and check ``--map`` arguments against ``rt`` and install them; returns the map
    (empty for no arguments)."""
    entries = parse_maps(items)
    if not entries:
        return SignalMap()
    reads = {name for b in rt.blocks.values() for name in b.inputs}
    smap = check(entries, rt.db, reads, rt.producer)
    rt.set_map(smap)
    return smap


__all__ = ["MapEntry", "SignalMap", "UNITS", "check", "conversion", "install", "parse_maps",
           "parse_source", "parse_spec", "read_file"]
