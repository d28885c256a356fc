"""Fan-out of the runtime's MED ticks to live subscribers (``WS /stream``, ``GET /stream/sse``).

The runtime thread calls :meth:`StreamHub.on_tick` once per MED tick (a tick listener). It
records one :class:`Record` — every channel's value, status and bus time at that tick — into
a ring shared by every client, then wakes the event loops that serve clients: one call per
loop, whatever the number of clients, so clients cost the runtime nothing per tick.

Each client is a cursor into the ring (a sequence number), served by its own task. A client
that reads slower than ticks arrive falls behind; when it is more than ``backlog`` records
behind, the oldest records it has not seen are skipped and counted (``dropped``), and it goes
on with the newest. The server holds, per client, a cursor and at most the socket's own
write buffer, so a client that stops reading cannot grow the server's memory; the ring is
fixed in size.
"""

from __future__ import annotations

import asyncio
import collections
import fnmatch
import json
import math
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from cell.app.cell import Cell

#: records kept for all clients (10 s at 10 Hz)
RING = 100
#: records a client may lag behind before the oldest are skipped and counted
BACKLOG = 50
#: most patterns one subscription may hold
MAX_PATTERNS = 200
#: most subscribers at once (WebSocket and SSE together); more are refused
MAX_CLIENTS = 256


class SubscriptionError(ValueError):
    """A subscription request that names nothing usable; the message says why."""


class TooManyClients(RuntimeError):
    """The hub already serves :data:`MAX_CLIENTS` subscribers."""


def parse_patterns(spec: Any, where: str) -> tuple[str, ...]:
    """Channel names or glob patterns (``*``, ``?``, ``[..]``), as a list or comma-separated text."""
    if isinstance(spec, str):
        items = [p.strip() for p in spec.split(",")]
    elif isinstance(spec, list) and all(isinstance(p, str) for p in spec):
        items = [p.strip() for p in spec]
    else:
        raise SubscriptionError(f"{where}: give channel names or glob patterns as a list of strings "
                                f"or comma-separated text, got {type(spec).__name__}")
    items = [p for p in items if p]
    if not items:
        raise SubscriptionError(f"{where}: names no channel; e.g. EXH_BP_R or EXH_BP_*")
    if len(items) > MAX_PATTERNS:
        raise SubscriptionError(f"{where}: at most {MAX_PATTERNS} names or patterns, got {len(items)}")
    for p in items:
        if len(p) > 200 or any(c.isspace() or not c.isprintable() for c in p):
            raise SubscriptionError(f"{where}: {p[:40]!r} is not a channel name or glob pattern")
    return tuple(dict.fromkeys(items))


def _clean(v: float | None) -> float | None:
    return v if v is None or math.isfinite(v) else None


@dataclass
class Record:
    """Every channel at one MED tick: name -> (value or None, status, bus time of the value)."""

    seq: int
    time: float
    values: dict[str, tuple[float | None, str, float | None]]
    #: encoded messages by subscription, shared by clients that subscribe alike
    encoded: dict[tuple[str, ...], str] = field(default_factory=dict)
    #: bus time of the newest value in each subscription's message (frame-to-API latency)
    newest: dict[tuple[str, ...], float | None] = field(default_factory=dict)


class Client:
    """One subscriber: its patterns, its cursor into the ring and what it has missed."""

    def __init__(self, hub: StreamHub, patterns: tuple[str, ...], backlog: int, kind: str = "ws") -> None:
        self.hub = hub
        self.kind = kind
        self.patterns = patterns
        self.backlog = backlog
        self.next_seq = hub.seq + 1  # from the next tick on
        self.dropped = 0
        self.sent = 0
        self.event = asyncio.Event()
        self.loop = asyncio.get_running_loop()
        self._names: tuple[tuple[frozenset[str], tuple[str, ...]], tuple[str, ...]] | None = None

    def names(self, available: Iterable[str]) -> tuple[str, ...]:
        """The channels the patterns match among ``available``, sorted (cached per channel set)."""
        avail = frozenset(available)
        if self._names is None or self._names[0] != (avail, self.patterns):
            self._names = ((avail, self.patterns), match(self.patterns, avail))
        return self._names[1]

    def take(self) -> list[Record]:
        """The records due to this client, oldest first, after skipping what it cannot catch up."""
        records = self.hub.since(self.next_seq)
        if not records:
            return []
        first = records[0].seq
        if first > self.next_seq:  # fell off the ring
            self.dropped += first - self.next_seq
        if len(records) > self.backlog:
            self.dropped += len(records) - self.backlog
            records = records[-self.backlog:]
        self.next_seq = records[-1].seq + 1
        return records

    def message(self, rec: Record) -> str:
        """The JSON message of ``rec`` for this client (encoded once per subscription)."""
        names = self.names(rec.values)
        key = self.patterns
        text = rec.encoded.get(key)
        if text is None:
            vals = rec.values
            body = json.dumps({n: [vals[n][0], vals[n][1], vals[n][2]] for n in names},
                              separators=(",", ":"))
            text = rec.encoded[key] = f'{{"type":"data","seq":{rec.seq},"time":{rec.time!r},"values":{body}'
            rec.newest[key] = max((vals[n][2] for n in names if vals[n][2] is not None), default=None)
        return f'{text},"dropped":{self.dropped}}}'


def match(patterns: Iterable[str], names: Iterable[str]) -> tuple[str, ...]:
    """Names matched by any pattern (exact names and globs), sorted."""
    names = list(names)
    out: set[str] = set()
    for p in patterns:
        if any(c in p for c in "*?["):
            out.update(fnmatch.filter(names, p))
        elif p in names:
            out.add(p)
    return tuple(sorted(out))


class StreamHub:
    """The shared ring of MED-tick records and the clients reading it.

    Parameters
    ----------
    cell:
        The cell whose ticks are streamed; the hub listens to its MED ticks.
    ring:
        Records kept for all clients.
    backlog:
        Default number of records a client may lag before older ones are dropped.
    """

    def __init__(self, cell: Cell, ring: int = RING, backlog: int = BACKLOG) -> None:
        self.cell = cell
        self.backlog = max(1, min(backlog, ring))
        self.records: collections.deque[Record] = collections.deque(maxlen=max(1, ring))
        self.seq = 0
        self.clients: set[Client] = set()
        self.connections_total = 0
        self.dropped_total = 0  # over clients that have left; live ones add their own
        #: set by :meth:`close`: every stream ends (the server is shutting down)
        self.closed = False
        self._lock = threading.Lock()
        cell.on_tick(self.on_tick)
        cell.on_stall(self.on_tick)  # a stopped or stalled loop: every channel stale, at once

    # -- the runtime's side -----------------------------------------------------------
    def on_tick(self, t: float) -> None:
        """Record the tick (runtime thread, runtime lock held) and wake the serving loops."""
        if not self.clients:
            return  # nobody listens: a tick costs nothing
        _, readings = self.cell.readings(at=t)
        rows = {name: (_clean(value), status, at) for name, (value, status, at) in readings.items()}
        with self._lock:
            self.seq += 1
            self.records.append(Record(self.seq, t, rows))
            loops = {c.loop for c in self.clients}
        for loop in loops:
            try:
                loop.call_soon_threadsafe(self._wake, loop)
            except RuntimeError:  # a loop that closed under us
                pass

    def close(self) -> None:
        """End every stream (at server shutdown: an event stream never ends by itself)."""
        with self._lock:
            self.closed = True
            loops = {c.loop for c in self.clients}
        for loop in loops:
            try:
                loop.call_soon_threadsafe(self._wake, loop)
            except RuntimeError:
                pass

    def _wake(self, loop: asyncio.AbstractEventLoop) -> None:
        for c in list(self.clients):
            if c.loop is loop:
                c.event.set()

    # -- the clients' side ------------------------------------------------------------
    def since(self, seq: int) -> list[Record]:
        with self._lock:
            if not self.records or self.records[-1].seq < seq:
                return []
            start = max(0, seq - self.records[0].seq)
            return list(self.records)[start:]

    def join(self, patterns: tuple[str, ...], backlog: int | None = None, kind: str = "ws") -> Client:
        """A new client (call from its event loop); it gets ticks from the next one on."""
        with self._lock:
            if len(self.clients) >= MAX_CLIENTS:
                raise TooManyClients(f"the cell already streams to {len(self.clients)} subscribers "
                                     f"(at most {MAX_CLIENTS}); try again later")
            c = Client(self, patterns, backlog or self.backlog, kind)
            self.clients.add(c)
            self.connections_total += 1
        return c

    def leave(self, client: Client) -> None:
        with self._lock:
            if client in self.clients:
                self.clients.discard(client)
                self.dropped_total += client.dropped

    def describe(self, names: Iterable[str]) -> list[dict[str, Any]]:
        """Name, unit and source of channels, for the ``subscribed`` answer."""
        return self.cell.describe_channels(names)

    def current(self, names: Iterable[str]) -> tuple[float | None, dict[str, list]]:
        """The bus time now and every named channel's latest value, status and time then
        (the ``snapshot`` message)."""
        now, readings = self.cell.readings(names)
        return now, {n: [_clean(value), status, at] for n, (value, status, at) in readings.items()}

    @property
    def dropped(self) -> int:
        with self._lock:
            return self.dropped_total + sum(c.dropped for c in self.clients)


__all__ = ["Client", "Record", "StreamHub", "SubscriptionError", "TooManyClients", "match",
           "parse_patterns"]
