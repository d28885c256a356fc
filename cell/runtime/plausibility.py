"""Plausibility at the door: a bus value outside its signal's range, or changing faster than
its rate limit, is ``invalid`` and reaches no block.

Each decoded bus value is checked before it is stored in its channel
(:meth:`cell.runtime.scheduler.Runtime._flush`):

- **Range.** The signal's DBC minimum and maximum (cantools ``Signal.minimum``/``maximum``).
  A DBC that gives no range (``[0|0]``, as most production DBC files write "none") sets no
  limit; the raw type's own range is no limit either. A value that is the range's edge
  after rounding to the raw step (half a ``scale``) is in range: the simulator clamps a
  value to the range before encoding it.
- **Rate of change**, optional, in the signal's units per second: the DBC signal attribute
  ``RateLimit`` (``BA_DEF_ SG_ "RateLimit" FLOAT 0 1e9;`` then
  ``BA_ "RateLimit" SG_ <frame id> <signal> <rate>;``), or a cell file. A value is too fast
  when it differs from the last value that passed by more than ``rate`` times the bus time
  between them (plus one raw step), so after a genuine step the value is accepted again once
  the allowed change has grown to it.
- **A cell file** (``testcell up --plausibility FILE``, YAML or JSON): a list of
  ``{signal, min, max, rate}`` entries (``min``/``max``/``rate`` optional, ``null`` for none)
  that replace the DBC's range and rate of those signals. :func:`read_file` validates it
  whole and names the entry (and, in YAML, the line) of a bad one.

An implausible value still shows in its channel, with status ``invalid`` and a reason naming
the signal, its value and the range (or the rate); it is counted by signal
(``/health`` ``implausible``). Blocks refuse inputs that are not ``ok``, so it never reaches
one.
"""

from __future__ import annotations

import collections
import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cell.core.errors import ConfigError

#: The DBC signal attribute that declares a rate-of-change limit, units per second.
RATE_ATTRIBUTE = "RateLimit"

_INF = math.inf


@dataclass(frozen=True)
class Limit:
    """The plausible values of one signal: a range (``None``: no bound) and a rate limit
    (units per second; ``None``: none). ``step`` is the signal's raw step (its DBC scale),
    the rounding a value may carry."""

    signal: str
    minimum: float | None = None
    maximum: float | None = None
    rate: float | None = None
    step: float = 0.0
    unit: str = ""

    @property
    def empty(self) -> bool:
        return self.minimum is None and self.maximum is None and self.rate is None

    def range_text(self) -> str:
        lo = "-inf" if self.minimum is None else f"{self.minimum:g}"
        hi = "inf" if self.maximum is None else f"{self.maximum:g}"
        return f"{lo}..{hi}{' ' + self.unit if self.unit else ''}"


def _number(value: Any) -> float | None:
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def signal_limit(signal: Any) -> Limit:
    """The limit a cantools signal declares: its range (none when the DBC gives ``[0|0]`` or
    none at all) and its ``RateLimit`` attribute."""
    lo, hi = _number(signal.minimum), _number(signal.maximum)
    if lo is not None and hi is not None and lo == 0.0 and hi == 0.0:
        lo = hi = None  # [0|0]: "no range", as DBC editors write it
    rate = None
    attrs = getattr(getattr(signal, "dbc", None), "attributes", None) or {}
    if RATE_ATTRIBUTE in attrs:
        rate = _number(attrs[RATE_ATTRIBUTE].value)
        if rate is not None and rate <= 0.0:
            rate = None
    step = 0.0 if signal.is_float else abs(float(signal.scale or 0.0))
    return Limit(signal.name, lo, hi, rate, step, signal.unit or "")


def limits_of(messages: Iterable[Any]) -> dict[str, dict[str, Limit]]:
    """Message name -> signal name -> :class:`Limit`, for the signals that have one."""
    out: dict[str, dict[str, Limit]] = {}
    for m in messages:
        found = {s.name: lim for s in m.signals if not (lim := signal_limit(s)).empty}
        if found:
            out[m.name] = found
    return out


class Plausibility:
    """The range and rate checks of one runtime's bus values (see the module notes).

    Parameters
    ----------
    messages:
        The DBC messages (cantools) whose signals are checked.
    counts:
        Where implausible values are counted, by signal (the runtime's health counters).
    """

    def __init__(self, messages: Iterable[Any],
                 counts: collections.Counter[str] | None = None) -> None:
        self.counts: collections.Counter[str] = counts if counts is not None else collections.Counter()
        self._messages = list(messages)
        self._limits = limits_of(self._messages)
        #: signal -> (value, bus time) last accepted, for the rate limits
        self._last: dict[str, tuple[float, float]] = {}
        self._compile()

    def _compile(self) -> None:
        #: message name -> ((signal, low, high, rate, step, limit), ...): the check's table
        self._rules: dict[str, tuple[tuple[str, float, float, float | None, float, Limit], ...]] = {}
        for message, limits in self._limits.items():
            rules = []
            for name, lim in limits.items():
                tol = 0.5 * lim.step
                lo = -_INF if lim.minimum is None else lim.minimum - tol
                hi = _INF if lim.maximum is None else lim.maximum + tol
                rules.append((name, lo, hi, lim.rate, lim.step, lim))
            self._rules[message] = tuple(rules)

    def limit(self, signal: str) -> Limit | None:
        """The limit checked on ``signal`` (the first message's, if several carry it)."""
        for limits in self._limits.values():
            if signal in limits:
                return limits[signal]
        return None

    def limits(self) -> dict[str, Limit]:
        """Every checked signal's limit, by signal."""
        return {n: lim for limits in self._limits.values() for n, lim in limits.items()}

    def override(self, entries: Iterable[Limit]) -> None:
        """Replace the limits of the signals ``entries`` name (a cell file's); refuse, naming
        it, a signal no DBC message carries, and change nothing then."""
        entries = list(entries)
        carriers: dict[str, list[Any]] = collections.defaultdict(list)
        for m in self._messages:
            for s in m.signals:
                carriers[s.name].append((m, s))
        unknown = [e.signal for e in entries if e.signal not in carriers]
        if unknown:
            raise ConfigError(f"plausibility: signal {unknown[0]} is in no DBC file loaded")
        for e in entries:
            for m, s in carriers[e.signal]:
                step = 0.0 if s.is_float else abs(float(s.scale or 0.0))
                lim = Limit(e.signal, e.minimum, e.maximum, e.rate, step, s.unit or "")
                table = self._limits.setdefault(m.name, {})
                if lim.empty:
                    table.pop(e.signal, None)
                else:
                    table[e.signal] = lim
            self._last.pop(e.signal, None)
        self._compile()

    def check(self, message: str, values: Mapping[str, float], t: float) -> dict[str, str] | None:
        """The implausible values of one decoded frame of ``message`` at bus time ``t``:
        ``{signal: reason}``, counted; ``None`` when every value is plausible."""
        rules = self._rules.get(message)
        if rules is None:
            return None
        bad = None
        for name, lo, hi, rate, step, lim in rules:
            v = values.get(name)
            if v is None:
                continue
            if v < lo or v > hi:
                reason = (f"implausible: {name} = {v:g} is outside its range "
                          f"{lim.range_text()}")
            elif rate is not None:
                last = self._last.get(name)
                if last is not None and t > last[1] and abs(v - last[0]) > rate * (t - last[1]) + step:
                    reason = (f"implausible: {name} changed from {last[0]:g} to {v:g} in "
                              f"{t - last[1]:.3g} s, faster than its limit {rate:g}"
                              f"{' ' + lim.unit if lim.unit else ''}/s")
                else:
                    if last is None or t >= last[1]:
                        self._last[name] = (v, t)
                    continue
            else:
                continue
            self.counts[name] += 1
            if bad is None:
                bad = {}
            bad[name] = reason
        return bad


# -- the cell file -------------------------------------------------------------------------
_KEYS = ("signal", "min", "max", "rate")


def _yaml_entries(text: str, path: Path) -> list[tuple[Any, str]]:
    """The YAML file's entries, each with where it is (``line N``)."""
    import yaml

    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {' '.join(str(exc).split())}") from None
    if not isinstance(data, list):
        raise ConfigError(f"{path}: must be a list of {{signal, min, max, rate}} entries, got "
                          f"{type(data).__name__}")
    marks = [f"line {n.start_mark.line + 1}" for n in node.value] if node is not None else []
    return list(zip(data, marks, strict=True))


def parse_entries(data: Any, where: list[str] | None = None, source: str = "plausibility") -> list[Limit]:
    """Check a list of ``{signal, min, max, rate}`` entries into :class:`Limit`s; a
    :class:`ConfigError` names the first bad entry (its index and ``where`` it is)."""
    if not isinstance(data, list):
        raise ConfigError(f"{source}: must be a list of {{signal, min, max, rate}} entries, got "
                          f"{type(data).__name__}")
    out: list[Limit] = []
    seen: dict[str, int] = {}
    for i, entry in enumerate(data):
        at = f"{source}: entry {i + 1}" + (f" ({where[i]})" if where else "")
        if not isinstance(entry, dict):
            raise ConfigError(f"{at}: must be an object with signal, min, max, rate; got "
                              f"{type(entry).__name__} {entry!r}")
        extra = [k for k in entry if k not in _KEYS]
        if extra:
            raise ConfigError(f"{at}: unknown key {extra[0]!r}; an entry takes "
                              f"{', '.join(_KEYS)}")
        signal = entry.get("signal")
        if not isinstance(signal, str) or not signal.strip():
            raise ConfigError(f"{at}: 'signal' must name a signal, got {signal!r}")
        signal = signal.strip()
        at = f"{at}, signal {signal}"
        if signal in seen:
            raise ConfigError(f"{at}: the signal is already given in entry {seen[signal]}")
        seen[signal] = i + 1
        nums: dict[str, float | None] = {}
        for key in ("min", "max", "rate"):
            v = entry.get(key)
            if v is None:
                nums[key] = None
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(f"{at}: {key!r} must be a finite number or null, got {v!r}")
            nums[key] = float(v)
        lo, hi, rate = nums["min"], nums["max"], nums["rate"]
        if lo is not None and hi is not None and lo > hi:
            raise ConfigError(f"{at}: min {lo:g} is above max {hi:g}")
        if rate is not None and rate <= 0.0:
            raise ConfigError(f"{at}: 'rate' must be > 0 units per second, got {rate:g}")
        out.append(Limit(signal, lo, hi, rate))
    return out


def read_file(path: str | Path) -> list[Limit]:
    """The entries of a plausibility file (``.json``; otherwise YAML, of which JSON is a
    subset); :class:`ConfigError` names the file and the entry or line of a problem."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"--plausibility {path}: cannot read: {exc.strerror or exc}") from None
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise ConfigError(f"{path}: not valid JSON: {exc}") from None
        return parse_entries(data, source=str(path))
    pairs = _yaml_entries(text, path)
    return parse_entries([d for d, _ in pairs], [w for _, w in pairs], source=str(path))


__all__ = ["RATE_ATTRIBUTE", "Limit", "Plausibility", "limits_of", "parse_entries", "read_file",
           "signal_limit"]
