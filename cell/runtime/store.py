"""The channels of one runtime: their latest values, their history at MED ticks, their staleness.

A :class:`ChannelStore` holds every channel of a runtime by name (bus signals and block
outputs, :class:`~cell.runtime.channels.Channel`) and a ring buffer of every channel's value
and status at each MED tick (:class:`~cell.runtime.channels.History`). A bus channel turns
stale when its frames stop: after two and a half of its DBC cycle times, and never sooner
than the floor the runtime gives (the third MED tick after its last frame).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

from cell.bus.dbc import CellDatabase
from cell.core.errors import UnknownBlockError
from cell.runtime.channels import OK, Channel, History

#: ``(value, status, bus time of the value)`` of a channel as seen at some bus time
Reading = tuple[float | None, str, float | None]


class ChannelStore:
    """Every channel of a runtime by name, with the history of each at MED ticks.

    Parameters
    ----------
    db:
        The DBC codec: the unit and cycle time of each bus signal.
    history_len:
        MED ticks kept in each channel's history.
    stale_floor:
        Seconds of bus time without a frame before which no bus channel turns stale.
    """

    def __init__(self, db: CellDatabase, history_len: int, stale_floor: float) -> None:
        self.db = db
        self.history_len = history_len
        self.stale_floor = stale_floor
        #: every channel by name
        self.by_name: dict[str, Channel] = {}
        self._history = History(history_len)

    def add(self, name: str, source: str = "bus") -> Channel:
        """The channel ``name``, made on first use: a bus signal (``source="bus"``, unit
        and staleness from the DBC) or the output of the block named ``source``."""
        ch = self.by_name.get(name)
        if ch is None:
            info = self.db.signals.get(name)
            stale_after = math.inf
            if source == "bus":
                cycle = info.cycle_time_s if info and info.cycle_time_s else 0.0
                stale_after = max(2.5 * cycle, self.stale_floor)
            ch = Channel(
                name=name,
                unit=info.unit if info else "",
                source=source,
                stale_after=stale_after,
            )
            self.by_name[name] = ch
        return ch

    def drop(self, name: str) -> None:
        """Forget a channel and its history (the output of a removed block)."""
        self.by_name.pop(name, None)
        self._history.drop(name)

    def unit_of(self, name: str) -> str | None:
        """The channel's unit, ``None`` when there is no such channel."""
        ch = self.by_name.get(name)
        return ch.unit if ch is not None else None

    def channel(self, name: str) -> Channel:
        """The channel ``name``; :class:`UnknownBlockError` naming the channels there are."""
        ch = self.by_name.get(name)
        if ch is None:
            raise UnknownBlockError("channel", name, sorted(self.by_name))
        return ch

    def record(self, t: float) -> None:
        """Take every channel's value and status at the MED tick ``t`` into the history."""
        rows = []
        for ch in self.by_name.values():
            status = ch.status_at(t)[0]
            rows.append((ch.name, ch.value if status == OK else None, status))
        self._history.record(t, rows)

    def history(self, name: str, seconds: float) -> list[tuple[float, float | None, str]]:
        """``(time, value or None, status)`` of the channel at each MED tick of the last
        ``seconds``; :class:`UnknownBlockError` for an unknown channel."""
        self.channel(name)
        return self._history.series(name, seconds)

    def snapshot(self, now: float | None) -> list[dict[str, Any]]:
        """Every channel as seen at bus time ``now``, by name."""
        return [ch.snapshot(now) for ch in sorted(self.by_name.values(), key=lambda c: c.name)]

    def readings(self, at: float | None, names: Iterable[str] | None = None) -> dict[str, Reading]:
        """Value, status and bus time of every channel (or of those of ``names`` that exist)
        as seen at bus time ``at``."""
        chans = self.by_name
        if names is None:
            picked: Iterable[Channel] = chans.values()
        else:
            picked = (chans[n] for n in names if n in chans)
        out = {}
        for ch in picked:
            status, _ = ch.status_at(at)
            out[ch.name] = (ch.value, status, ch.t)
        return out


__all__ = ["ChannelStore", "Reading"]
