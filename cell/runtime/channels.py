"""Channels: the latest value, unit, bus time and status of every signal in the cell."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

OK, STALE, INVALID = "ok", "stale", "invalid"


@dataclass
class Channel:
    """One named value in the cell: a DBC signal read from the bus or a block output.

    ``t`` is the bus time of the value. A bus channel turns stale when ``now - t`` exceeds
    ``stale_after``; a block output carries the status its block gave it at its last tick.
    """

    name: str
    unit: str = ""
    source: str = "bus"
    stale_after: float = math.inf
    value: float | None = None
    t: float | None = None
    status: str = STALE
    reason: str | None = "no value yet"

    def update(self, value: float, t: float) -> None:
        self.value = value
        self.t = t
        if math.isfinite(value):
            self.status, self.reason = OK, None
        else:
            self.status, self.reason = INVALID, f"value is {value}"

    def mark(self, status: str, reason: str | None) -> None:
        self.status, self.reason = status, reason

    def status_at(self, now: float | None) -> tuple[str, str | None]:
        """Status as seen at bus time ``now`` (bus channels age; outputs keep their mark)."""
        if self.value is None:
            return STALE, "no value yet"
        if self.source == "bus" and now is not None and self.t is not None:
            age = now - self.t
            if age > self.stale_after:
                return STALE, f"no frame for {age:.2f} s (limit {self.stale_after:.2f} s)"
        return self.status, self.reason

    def snapshot(self, now: float | None) -> dict[str, Any]:
        status, reason = self.status_at(now)
        return {
            "name": self.name,
            "value": self.value,
            "unit": self.unit,
            "time": self.t,
            "status": status,
            "reason": reason,
            "source": self.source,
        }


_CODES = {OK: 0, STALE: 1, INVALID: 2}
_NAMES = np.array([OK, STALE, INVALID], dtype=object)


class History:
    """Every channel's value and status at each MED tick, in fixed-size ring buffers.

    All channels share one time axis, so a tick costs one float and one byte per channel;
    a channel that appears later reads as stale before it appeared.
    """

    def __init__(self, length: int) -> None:
        self.length = max(1, int(length))
        self.t = np.full(self.length, np.nan)
        self.values: dict[str, np.ndarray] = {}
        self.codes: dict[str, np.ndarray] = {}
        self._next = 0
        self._count = 0

    def record(self, t: float, rows: Iterable[tuple[str, float | None, str]]) -> None:
        k = self._next
        self.t[k] = t
        for name, value, status in rows:
            values = self.values.get(name)
            if values is None:
                values = self.values[name] = np.full(self.length, np.nan)
                self.codes[name] = np.full(self.length, _CODES[STALE], dtype=np.uint8)
            values[k] = np.nan if value is None else value
            self.codes[name][k] = _CODES[status]
        self._next = (k + 1) % self.length
        self._count = min(self._count + 1, self.length)

    def drop(self, name: str) -> None:
        self.values.pop(name, None)
        self.codes.pop(name, None)

    def series(self, name: str, seconds: float) -> list[tuple[float, float | None, str]]:
        """``(time, value or None, status)`` over the last ``seconds`` of ticks, oldest first."""
        if self._count == 0 or name not in self.values:
            return []
        order = np.arange(self._next - self._count, self._next) % self.length
        t = self.t[order]
        keep = order[t > t[-1] - seconds + 1e-9]
        values, codes = self.values[name][keep], _NAMES[self.codes[name][keep]]
        return [(float(tt), None if math.isnan(v) else float(v), str(c))
                for tt, v, c in zip(self.t[keep], values, codes)]
