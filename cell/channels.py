"""Channels: the latest value, unit, bus time and status of every signal in the cell."""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field
from typing import Any

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
    history: collections.deque = field(default_factory=lambda: collections.deque(maxlen=6000))

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
