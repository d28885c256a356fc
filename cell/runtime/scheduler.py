"""The cyclic runtime: bus time, FAS/MED/SLO ticks, channels and blocks.

The runtime is driven by frames, never by the wall clock. Frames are applied in
timestamp order; before a frame stamped ``ts`` is applied, every tick due strictly before
``ts`` runs, so at each tick an input's value is the latest frame value at or before the
tick. The same object runs live (:mod:`cell.app.live`) and offline (:mod:`cell.runtime.replay`), so a
log replayed at any speed gives the numbers the live cell gave.

The runtime is made of three parts: the scheduler here (ticks, blocks, decoding and routing
of frames), its channels (:class:`~cell.runtime.store.ChannelStore`: values, history,
staleness) and its counts (:class:`~cell.runtime.health.HealthCounters`: frames, bad
frames, overruns, the ``/health`` answer).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import can
import numpy as np

from cell.runtime import stream_time, units
from cell.runtime.blocks import RATE_NAMES, Block
from cell.runtime.channels import INVALID, OK, STALE, Channel
from cell.bus.dbc import CellDatabase, FrameDecodeError
from cell.core.errors import ConfigError, UnknownBlockError
from cell.runtime.faults import BlockFaults, describe
from cell.runtime.health import (FRAME_ERROR_KINDS, MAX_COUNTED_IDS, MAX_UNKNOWN_IDS, OTHER_IDS,
                                 HealthCounters)
from cell.runtime.channel_params import check_channel_params
from cell.runtime.mapping import SignalMap
from cell.runtime.plausibility import Plausibility
from cell.runtime.samples import SampleLayout, SampleTracker, find_sample_streams
from cell.runtime.senders import SenderWatch
from cell.runtime.stream_codec import fast_unpacker
from cell.runtime.store import ChannelStore, Reading

_EPS = 1e-9

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Rates:
    """Tick rates in Hz of the three cyclic tasks (seed 004: 50/10/1 Hz)."""

    FAS: float = 50.0
    MED: float = 10.0
    SLO: float = 1.0

    @classmethod
    def parse(cls, spec: str | None) -> Rates:
        """Parse ``--cycle``: a number sets MED in Hz; ``FAS=50,MED=10,SLO=1`` sets any of them."""
        if spec is None or str(spec).strip() == "":
            return cls()
        spec = str(spec).strip()
        values: dict[str, float] = {}
        parts = [p.strip() for p in spec.split(",")]
        for part in parts:
            name, sep, text = part.partition("=")
            if not sep:
                name, text = "MED", part
            name = name.strip().upper()
            if name not in RATE_NAMES:
                raise ConfigError(f"--cycle {spec!r}: unknown task {name!r}; use FAS, MED or SLO")
            try:
                hz = float(text)
            except ValueError:
                raise ConfigError(f"--cycle {spec!r}: {name} rate {text!r} is not a number") from None
            if not math.isfinite(hz) or not 0.01 <= hz <= 1000:
                raise ConfigError(f"--cycle {spec!r}: {name} rate must be 0.01..1000 Hz, got {text}")
            values[name] = hz
        return cls(**values)

    def period(self, name: str) -> float:
        return 1.0 / getattr(self, name)


class _SampleRoute:
    """One sample stream in the runtime: its layout, its order tracker and its consumers."""

    __slots__ = ("layout", "tracker", "blocks", "unpack")

    def __init__(self, layout: SampleLayout, window: int, message: Any = None) -> None:
        self.layout = layout
        self.tracker = SampleTracker(layout, window=window)
        self.blocks: list[Block] = []
        #: the frame's samples from its bytes without cantools, when the layout allows
        self.unpack = fast_unpacker(message, layout) if message is not None else None


def _checked(block: Block, outputs: Any, chans: dict[str, Channel]) -> dict[str, float]:
    """A block's step result as ``{output: float}``; a result that is not a mapping of its own
    outputs to real numbers (a complex number, an undeclared output) raises, which faults the
    block (:mod:`cell.runtime.faults`) before any channel changes."""
    out: dict[str, float] = {}
    for name, value in outputs.items():
        if name not in block.outputs or name not in chans:
            raise KeyError(f"{block.name} returned {name!r}, which is not one of its outputs")
        if isinstance(value, (complex, np.complexfloating)) or (
                isinstance(value, np.ndarray) and value.dtype.kind == "c"):
            raise TypeError(f"{block.name} returned the complex number {value!r} for {name}; "
                            "outputs are real numbers")
        try:
            out[name] = float(value)
        except (TypeError, ValueError) as exc:
            raise TypeError(f"{block.name} returned {type(value).__name__} {value!r} for {name}; "
                            f"outputs are real numbers ({exc})") from None
    return out


def _counted(name: str, doc: str) -> property:
    """A count of the runtime's :class:`~cell.runtime.health.HealthCounters`, read and set
    through the runtime."""
    def get(self: Runtime) -> Any:
        return getattr(self.counters, name)

    def set_(self: Runtime, value: Any) -> None:
        setattr(self.counters, name, value)

    return property(get, set_, doc=doc)


class Runtime:
    """Channels, blocks and the tick scheduler of one cell.

    Blocks that declare sample :attr:`~cell.runtime.blocks.Block.streams` also get every sample of
    those crank-angle streams (:mod:`cell.runtime.samples`), in angle order, as each frame is
    applied (between ticks, on bus time); lost, reordered and late frames are counted per
    stream in :meth:`health` and gaps are reported to the blocks (:meth:`Block.gap`).

    The channels live in :attr:`store` (:class:`~cell.runtime.store.ChannelStore`), the
    counts in :attr:`counters` (:class:`~cell.runtime.health.HealthCounters`); the runtime
    reads and counts into both under its :attr:`lock`.

    Parameters
    ----------
    db:
        The DBC codec; decides units, staleness and which outputs go on the bus.
    blocks:
        Blocks to run, stepped in the order given within each tick.
    rates:
        FAS/MED/SLO rates. History and output rows are taken at MED ticks.
    history_s:
        Length of each channel's history ring buffer, in seconds of bus time.
    stream_window:
        Frames of a sample stream that may arrive ahead of a missing one before it is
        declared lost (a reordering this deep is put right).
    """

    frames = _counted("frames", "frames applied, good or bad")
    late_frames = _counted("late_frames", "frames stamped earlier than the newest one applied")
    decode_errors = _counted("decode_errors", "bad frames by kind (:data:`FRAME_ERROR_KINDS`)")
    unknown_ids = _counted("unknown_ids", "frames whose ID no DBC file defines, by ID")
    block_errors = _counted("block_errors", "failed block steps, by block")
    withheld = _counted("withheld", "outputs withheld from the bus for not being finite, by channel")
    frames_by_id = _counted("frames_by_id", "frames received per (arbitration ID, extended)")
    ticks = _counted("ticks", "ticks that had work")
    tick_overruns = _counted("tick_overruns", "ticks whose work took longer than their period")
    tick_seconds_max = _counted("tick_seconds_max", "wall seconds of the slowest tick so far")
    step_time = _counted("step_time", "per block: [wall seconds spent in step, steps]")

    def __init__(
        self,
        db: CellDatabase,
        blocks: Iterable[Block] = (),
        rates: Rates | None = None,
        history_s: float = 600.0,
        stream_window: int = 2,
    ) -> None:
        self.db = db
        self.rates = rates or Rates()
        self.lock = threading.RLock()
        self.history_len = max(1, int(round(history_s * self.rates.MED)))
        # an input goes stale by the third MED tick after its frames stop
        self.store = ChannelStore(db, self.history_len, stale_floor=1.5 / self.rates.MED)
        self.counters = HealthCounters()
        #: every block's faults and backoff (:mod:`cell.runtime.faults`)
        self.faults = BlockFaults()
        #: range and rate checks of the decoded bus values (:mod:`cell.runtime.plausibility`)
        self.plausibility = Plausibility(db.messages, self.counters.implausible)
        #: second senders of the simulator's messages, judged at MED ticks (cell.runtime.senders)
        self.senders = SenderWatch(db.messages, self.counters)
        #: newest undecoded frame per message: frames are decoded when a tick or a reader
        #: needs their values, so the ten frames of a 100 Hz message between two 10 Hz
        #: ticks cost one decode, not ten
        self._pending: dict[tuple[int, bool], tuple[Any, float, bytes]] = {}
        self.blocks: dict[str, Block] = {}
        self.producer: dict[str, str] = {}
        #: the DBC messages all of whose signals some block produces; found again only when
        #: the blocks change (``None``), not at every tick
        self._out_messages: list | None = None
        self._busy_rates: frozenset[str] | None = None
        #: (task, Hz) of the three tasks, for the tick arithmetic
        self._hz = tuple((r, getattr(self.rates, r)) for r in RATE_NAMES)
        #: frame key -> (DBC message, its length): the decode's lookup, once per frame
        #: and the inter-arrival beyond which cycles were missed (1.5 DBC cycles; inf: no cycle)
        self._known = {key: (m, m.length, 1.5 * m.cycle_time / 1000.0 if m.cycle_time else math.inf)
                       for key, m in self.db.by_id.items()}
        self.outbox: list[can.Message] = []
        self.tick_listeners: list[Callable[[float], None]] = []
        #: small state kept for the service between requests (trip onset, reset counter)
        self.extra_state: dict[str, Any] = {}
        self.last_frame_time: float | None = None
        self.last_tick_time: float | None = None
        self._next_index: dict[str, int] | None = None
        self._next_due: float | None = None
        #: frame key -> the sample stream it carries, for streams some block consumes
        self._streams: dict[tuple[int, bool], _SampleRoute] = {}
        self._stream_window = stream_window
        self._layouts: dict[str, SampleLayout] | None = None
        #: a user's signals on the cell's channels (:mod:`cell.runtime.mapping`)
        self.signal_map = SignalMap()
        #: the blocks' seconds on samples not yet counted (:meth:`_count_stream_time`)
        self._stream_spent: dict[str, float] = {}
        for block in blocks:
            self.add_block(block)

    # -- blocks ---------------------------------------------------------------------
    def add_block(self, block: Block) -> None:
        """Add a block; refuse one whose outputs another producer already owns."""
        with self.lock:
            if block.name in self.blocks:
                raise ConfigError(f"a block named {block.name!r} already exists")
            for out in block.outputs:
                owner = self.producer.get(out)
                if owner is not None:
                    raise ConfigError(
                        f"{block.name} cannot produce {out}: {owner} already produces it"
                    )
                info = self.db.signals.get(out)
                if info is not None and self.db.message(info.message).senders != ["RUNTIME"]:
                    raise ConfigError(
                        f"{block.name} cannot produce {out}: it is a bus input sent by "
                        f"{', '.join(self.db.message(info.message).senders) or 'another node'}"
                    )
            layouts = [self._stream_layout(name, block.name) for name in block.streams]
            self.blocks[block.name] = block
            for layout in layouts:
                self._stream_route(layout).blocks.append(block)
            self._out_messages = self._busy_rates = None
            for out in block.outputs:
                self.producer[out] = block.name
                # DBC, declared, else its one input's
                unit = units.resolve(self.db, block, out, self.store.unit_of)
                ch = self.store.add(out, source=block.name)
                ch.unit = ch.unit or unit

    def remove_block(self, name: str) -> Block:
        """Remove a block, its output channels and its error counts (they ended with it)."""
        with self.lock:
            block = self.block(name)
            del self.blocks[name]
            self.counters.forget_block(name)
            self.faults.forget(name)
            for key, route in list(self._streams.items()):
                route.blocks = [b for b in route.blocks if b is not block]
                if not route.blocks:
                    del self._streams[key]
            self._out_messages = self._busy_rates = None
            for out in block.outputs:
                self.producer.pop(out, None)
                self.store.drop(out)
                self.counters.forget_output(out)
            return block

    def _stream_layout(self, stream: str, block: str) -> SampleLayout:
        """The layout of a sample stream the DBC defines; refuse one it does not."""
        if self._layouts is None:
            self._layouts = find_sample_streams(self.db.messages)
        layout = self._layouts.get(stream)
        if layout is None:
            raise ConfigError(f"{block} consumes sample stream {stream!r}, which no DBC message "
                              f"carries; streams: {', '.join(sorted(self._layouts)) or 'none'}")
        return layout

    def _stream_route(self, layout: SampleLayout) -> _SampleRoute:
        m = self.db.message(layout.message)
        key = (m.frame_id, bool(m.is_extended_frame))
        route = self._streams.get(key)
        if route is None:
            route = self._streams[key] = _SampleRoute(layout, self._stream_window, m)
        return route

    def _decode_streams(self, msgs: list | tuple) -> dict[int, tuple[int, np.ndarray]]:
        """The samples of every stream frame among ``msgs`` that takes the fast path, decoded
        together per stream (:meth:`StreamUnpacker.many`), by ``id`` of the frame."""
        streams = self._streams
        found: dict[tuple[int, bool], list] = {}
        for msg in msgs:
            key = (msg.arbitration_id, msg.is_extended_id)
            if key in streams and len(msg.data) == 8:
                found.setdefault(key, []).append(msg)
        out: dict[int, tuple[int, np.ndarray]] = {}
        for key, frames in found.items():
            unpack = streams[key].unpack
            if unpack is None:
                continue
            if len(frames) == 1:
                out[id(frames[0])] = unpack(bytes(frames[0].data))
                continue
            indexes, samples = unpack.many([m.data for m in frames])
            for msg, index, row in zip(frames, indexes, samples):
                out[id(msg)] = (index, row)
        return out

    def _ingest_stream(self, route: _SampleRoute, message: Any, data: bytes, ts: float,
                       decoded: tuple[int, np.ndarray] | None = None) -> None:
        """Hand a stream frame's samples, in angle order, to the blocks that consume it
        (``decoded``: its samples, when decoded with the rest of its batch).

        The blocks' time on the samples counts in their ``step_time`` and in the work of
        the next tick (:func:`cell.runtime.stream_time.count`, in one sum per ingest)."""
        if decoded is not None:
            index, samples = decoded
        elif route.unpack is not None and len(data) == 8:
            index, samples = route.unpack(bytes(data))
        else:
            try:
                values = self.db.decode_payload(message, bytes(data))
            except FrameDecodeError as exc:
                self.counters.count_decode_error(exc.kind)
                return
            index, samples = route.layout.unpack(values)
        name = route.layout.name
        faults = self.faults
        spent = self._stream_spent
        events: Iterable[tuple] = ((("samples", index, samples, ts),)
                                   if route.tracker.take(index, len(samples))
                                   else route.tracker.push(index, samples, ts))
        clock = time.perf_counter
        for event in events:
            for block in route.blocks:
                if faults.by_block and faults.waiting(block.name, ts) is not None:
                    continue  # backing off after a fault: its samples wait for the retry
                started = clock()
                try:
                    if event[0] == "samples":
                        block.samples(name, event[1], event[2], event[3])
                    else:
                        block.gap(name, event[1], event[2], event[3])
                except ArithmeticError as exc:
                    self.counters.block_errors[block.name] += 1
                    faults.count(block.name, "refused", describe(exc), ts)
                except Exception as exc:  # any defect of one block faults that block alone
                    self.counters.block_errors[block.name] += 1
                    faults.exception(block, exc, ts)
                spent[block.name] = spent.get(block.name, 0.0) + (clock() - started)

    def _count_stream_time(self) -> None:
        """Count the blocks' time on samples since the last call (:mod:`stream_time`)."""
        spent = self._stream_spent
        for name, seconds in spent.items():
            if name in self.blocks:
                stream_time.count(self, name, seconds)
        spent.clear()

    def block(self, name: str, family: str | None = None) -> Block:
        block = self.blocks.get(name)
        if block is None or (family is not None and block.family != family):
            known = [b.name for b in self.blocks.values() if family is None or b.family == family]
            raise UnknownBlockError(family or "block", name, known)
        return block

    def set_params(self, name: str, changes: dict[str, Any], family: str | None = None) -> dict:
        """Validate and apply a parameter change; it takes effect at the next tick."""
        with self.lock:
            block = self.block(name, family)
            check_channel_params(self, block, changes)  # a channel there is, of the right unit
            return block.set_params(changes)

    def set_map(self, smap: SignalMap) -> None:
        """Install checked mappings (:func:`cell.runtime.mapping.install`): each mapped
        channel takes its unit from the mapping and goes stale on its source's cycle."""
        with self.lock:
            self._flush()
            self.signal_map = smap
            for e in smap.entries:
                ch = self.store.add(e.target)
                ch.unit = e.target_unit or ch.unit
                cycle = self.db.message(e.message).cycle_time
                ch.stale_after = max(2.5 * cycle / 1000.0 if cycle else 0.0,
                                     self.store.stale_floor)
                ch.value, ch.t, ch.status, ch.reason = None, None, STALE, "no value yet"

    # -- bus time -------------------------------------------------------------------
    @property
    def now(self) -> float | None:
        """The runtime's bus time: the later of the last frame and the last tick."""
        times = [t for t in (self.last_frame_time, self.last_tick_time) if t is not None]
        return max(times) if times else None

    def frames_per_second(self, window_s: float = 1.0) -> float:
        """Frame rate over the last ``window_s`` seconds of bus time."""
        with self.lock:
            return self.counters.frames_per_second(self.now, window_s)

    # -- frames and ticks -----------------------------------------------------------
    def ingest(self, msg: can.Message) -> None:
        """Apply one received frame at its bus time, after the ticks due before it."""
        self.ingest_many((msg,))

    def ingest_many(self, msgs: Iterable[can.Message]) -> int:
        """Apply frames in order (the offline replay's fast path); returns how many."""
        n = 0
        known = self._known
        pending = self._pending
        streams = self._streams
        counters = self.counters
        frame_times = counters.frame_times
        by_id_count = counters.frames_by_id
        max_ids = counters.max_counted_ids
        gaps = counters.gaps
        arrived = gaps.arrived
        with self.lock:
            nxt = self._next_due
            last = self.last_frame_time
            # a batch's stream frames are decoded together; a log read as it goes, frame by frame
            decoded = (self._decode_streams(msgs) if streams and isinstance(msgs, (list, tuple))
                       else None)
            try:
                for msg in msgs:
                    n += 1
                    ts = msg.timestamp
                    if nxt is None or ts > nxt + _EPS:
                        self.last_frame_time = last  # what a tick listener sees as now
                        self._run_ticks(ts, inclusive=False)
                        nxt = self._next_due
                    frame_times.append(ts)
                    key = (msg.arbitration_id, msg.is_extended_id)  # True == 1: one key either way
                    seen = by_id_count.get(key)
                    if seen is None and len(by_id_count) >= max_ids:
                        by_id_count[OTHER_IDS] = by_id_count.get(OTHER_IDS, 0) + 1  # a bus of random IDs
                    else:
                        by_id_count[key] = (seen or 0) + 1
                    if last is None or ts >= last:
                        last = ts
                    else:
                        counters.late_frames += 1
                    if msg.is_error_frame or msg.is_remote_frame:
                        counters.count_decode_error("error_frame" if msg.is_error_frame
                                                    else "remote_frame")
                        continue
                    entry = known.get(key)
                    if entry is None or len(msg.data) != entry[1]:
                        try:
                            self.db.check(msg)  # the one place that words the error
                        except FrameDecodeError as exc:
                            counters.count_decode_error(exc.kind, key)
                        continue
                    message = entry[0]
                    prev_ts = arrived.get(key)
                    if prev_ts is None or ts > prev_ts:
                        arrived[key] = ts
                        if prev_ts is not None and ts - prev_ts > entry[2]:
                            gaps.gap(key, message.name, ts - prev_ts, entry[2] / 1.5)
                    if streams:
                        route = streams.get(key)
                        if route is not None:
                            self._ingest_stream(route, message, msg.data, ts,
                                                decoded.get(id(msg)) if decoded else None)
                    prev = pending.get(key)
                    if prev is None or ts >= prev[1]:
                        pending[key] = (message, ts, msg.data)
            finally:  # frames applied before a bad log line still count
                counters.frames += n
                self.last_frame_time = last
                if self._stream_spent:
                    self._count_stream_time()
        return n

    def _flush(self) -> None:
        """Decode the newest pending frame of each message into its channels."""
        if not self._pending:
            return
        pending = list(self._pending.items())
        self._pending.clear()  # in place: ingest_many holds a reference to this dict
        chans = self.store.by_name
        settle, counts = self.counters.gaps.settle, self.counters.frames_by_id
        smap = self.signal_map
        mapped, by_source = smap.targets, smap.by_source
        for key, (message, ts, data) in pending:
            settle(key, ts, counts.get(key))
            try:
                values = self.db.decode_payload(message, bytes(data))
            except FrameDecodeError as exc:
                self.counters.count_decode_error(exc.kind)
                continue
            bad = self.plausibility.check(message.name, values, ts)  # {signal: reason} or None
            for name, value in values.items():
                if self.producer.get(name):
                    continue  # our own output seen on the bus (e.g. a second runtime's)
                if mapped:
                    fed = by_source.get((message.name, name))
                    if fed is not None:
                        self._map_value(fed, name, value, ts, bad)
                    if name in mapped:
                        continue  # a mapped channel reads its mapping only
                ch = chans.get(name)
                if ch is None:
                    ch = self.store.add(name)
                if ch.t is None or ts >= ch.t:
                    ch.update(value, ts)
                    if bad is not None and name in bad:
                        ch.mark(INVALID, bad[name])  # implausible: no block reads it

    def _map_value(self, entries: list, name: str, value: float, ts: float,
                   bad: dict[str, str] | None) -> None:
        """A mapped source's value onto its channels, with its bus time and status."""
        chans = self.store.by_name
        for e in entries:
            ch = chans[e.target]
            if ch.t is None or ts >= ch.t:
                ch.update(e.convert(value), ts)
                if bad is not None and name in bad:
                    ch.mark(INVALID, f"mapped from {e.source}: {bad[name]}")

    def advance(self, t: float) -> None:
        """Run every tick due at or before bus time ``t`` (end of a log, or a silent bus)."""
        with self.lock:
            self._run_ticks(t, inclusive=True)

    def _run_ticks(self, until: float, inclusive: bool) -> None:
        nxt = self._next_due
        if nxt is not None and (nxt > until + _EPS or (not inclusive and nxt >= until - _EPS)):
            return  # the common case: a frame between two ticks
        if self._stream_spent:  # the samples' work so far goes to the tick about to run
            self._count_stream_time()
        if self._next_index is None:
            # first time seen: the first tick of each task is the first grid point at or after it
            self._next_index = {
                r: math.ceil(until * getattr(self.rates, r) - _EPS) for r in RATE_NAMES
            }
        index, hz = self._next_index, self._hz
        while True:
            due = []
            for r, f in hz:
                t = index[r] / f
                if t < until - _EPS or (inclusive and t <= until + _EPS):
                    due.append((t, r))
            if not due:
                break
            t = min(d[0] for d in due)
            ticking = frozenset(r for (tt, r) in due if abs(tt - t) <= _EPS)
            for r in ticking:
                index[r] += 1
            busy = self._busy_rates
            if busy is None:  # the tasks some block ticks at; found again when the blocks change
                busy = self._busy_rates = frozenset(r for b in self.blocks.values() for r in b.rates)
            work = "MED" in ticking or not ticking.isdisjoint(busy)
            if work:
                started = time.perf_counter()
                self._flush()  # a FAS tick with no FAS block reads nothing: skip the decode
                self._tick(ticking, t)
            self.last_tick_time = t
            if "MED" in ticking:
                self._after_med_tick(t)
            if work:
                self._count_tick(time.perf_counter() - started + stream_time.take(self), ticking)
        self._next_due = min(index[r] / f for r, f in hz)

    def _count_tick(self, seconds: float, ticking: frozenset[str]) -> None:
        """Count a tick that had work, and an overrun when the work took longer than the
        period of the fastest task with work in it (a FAS tick with no FAS block has none)."""
        self.counters.count_tick(seconds)
        rates = self.rates
        if seconds * max(rates.FAS, rates.MED, rates.SLO) <= 1.0:
            return  # shorter than every period (the common case): no overrun, nothing to scan
        working = [r for r in ticking if r == "MED" or any(r in b.rates for b in self.blocks.values())]
        if working and seconds > min(rates.period(r) for r in working):
            self.counters.count_overrun(self.last_tick_time)

    def _tick(self, ticking: frozenset[str], t: float) -> None:
        updated: set[str] = set()
        chans = self.store.by_name
        counters = self.counters
        block_errors, withheld = counters.block_errors, counters.withheld
        faults = self.faults
        for block in list(self.blocks.values()):
            if ticking.isdisjoint(block.rates):
                continue
            if faults.by_block:
                waiting = faults.waiting(block.name, t)
                if waiting is not None:  # backing off after a fault: not stepped
                    for out in block.outputs:
                        chans[out].mark(INVALID, waiting)
                    continue
            values: dict[str, float] = {}
            bad: tuple[str, str] | None = None
            for name in block.inputs:
                ch = chans.get(name)
                if ch is None:
                    bad = (STALE, f"input {name} has no value yet")
                    break
                status, reason = ch.status_at(t)
                if status != OK:
                    bad = (status, f"input {name} is {status}: {reason}")
                    break
                values[name] = ch.value  # type: ignore[assignment]
            if bad is not None:
                held = block.fallback(t, bad[1])  # a controller's held or safe output, or None
                for out in block.outputs:
                    if held is not None and out in held:
                        chans[out].update(float(held[out]), t)
                        updated.add(out)
                    else:
                        chans[out].mark(*bad)
                continue
            started = time.perf_counter()
            try:
                outputs = _checked(block, block.step(t, values, ticking), chans)
            except ArithmeticError as exc:  # the block's own "cannot compute this tick"
                block_errors[block.name] += 1
                reason = describe(exc)
                faults.count(block.name, "refused", reason, t)
                for out in block.outputs:
                    chans[out].mark(INVALID, reason)
                continue
            except Exception as exc:  # any other defect faults this block alone
                block_errors[block.name] += 1
                reason = faults.exception(block, exc, t)
                for out in block.outputs:
                    chans[out].mark(INVALID, reason)
                continue
            finally:
                counters.count_step(block.name, time.perf_counter() - started)
            if faults.by_block:
                faults.stepped(block.name)
            reasons = block.errors
            for out, value in outputs.items():
                ch = chans[out]
                ch.update(value, t)
                if ch.status != OK:
                    block_errors[block.name] += 1
                    if not math.isfinite(ch.value):
                        withheld[out] += 1  # _emit keeps it off the bus
                        faults.count(block.name, "nonfinite", f"{out} is {ch.value}", t)
                    if out in reasons:
                        ch.mark(INVALID, reasons[out])
                updated.add(out)
        if updated:
            self._emit(updated, t)

    def _emit(self, updated: set[str], t: float) -> None:
        """Queue a DBC frame for each output message that carries an updated signal."""
        chans = self.store.by_name
        if self._out_messages is None:
            self._out_messages = self.db.messages_carrying(set(self.producer))
        for message in self._out_messages:
            names = self.db.payload_signals(message)  # the E2E counter and CRC: encode's
            if not updated.intersection(names):
                continue
            if not any(self.blocks[self.producer[n]].on_bus for n in names):
                continue  # e.g. both banks' controllers disabled: their demand stays off
            # a frame another block keeps on the bus (the other bank's enabled controller)
            # carries a block's output that is off the bus by itself, e.g. a disabled
            # controller's manual or safe output: one bank off never stops the other's demand
            picked = [chans[n] for n in names]
            if any(c.status != OK or c.value is None for c in picked):
                continue  # a stale or invalid output is not put on the bus
            try:
                frame = self.db.encode(message.name, {c.name: c.value for c in picked}, t)
            except Exception as exc:  # kept off the bus and counted; the tick goes on
                self.counters.encode_errors[message.name] += 1
                if self.counters.encode_errors[message.name] in (1, 10, 100):
                    log.warning("cannot encode %s at bus time %.3f: %s", message.name, t, describe(exc))
                continue
            self.outbox.append(frame)

    def _after_med_tick(self, t: float) -> None:
        self.store.record(t)
        self.senders.at(t)
        for listener in self.tick_listeners:
            try:
                listener(t)
            except Exception as exc:  # a listener's defect never ends the loop
                name = getattr(listener, "__qualname__", type(listener).__name__)
                self.counters.listener_errors[name] += 1
                if self.counters.listener_errors[name] in (1, 10, 100):
                    log.warning("tick listener %s failed at bus time %.3f: %s", name, t, describe(exc))

    def send(self, frames: Iterable[can.Message]) -> None:
        """Queue frames for the bus; the live loop sends them with the next outputs."""
        with self.lock:
            self.outbox.extend(frames)

    def take_outbox(self) -> list[can.Message]:
        with self.lock:
            out, self.outbox = self.outbox, []
            return out

    # -- views ----------------------------------------------------------------------
    @property
    def channels(self) -> dict[str, Channel]:
        """Every channel by name, with the frames received so far applied."""
        self._flush()
        return self.store.by_name

    def snapshot(self) -> list[dict[str, Any]]:
        """Every channel as seen now, by name."""
        with self.lock:
            self._flush()
            return self.store.snapshot(self.now)

    def channel(self, name: str) -> Channel:
        with self.lock:
            self._flush()
            return self.store.channel(name)

    def history(self, name: str, seconds: float) -> list[tuple[float, float | None, str]]:
        with self.lock:
            self._flush()  # 404 for a channel no frame has brought yet
            return self.store.history(name, seconds)

    def readings(self, names: Iterable[str] | None = None,
                 at: float | None = None) -> dict[str, Reading]:
        """Value, status and bus time of every channel (or of those of ``names`` that exist)
        as seen at bus time ``at`` (default: now)."""
        with self.lock:
            self._flush()
            return self.store.readings(self.now if at is None else at, names)

    def unknown_id_counts(self, top: int = 32) -> dict[str, int]:
        """The most frequent frame IDs that no DBC defines, as ``"0x123"`` (``x`` suffix:
        extended) -> frames."""
        with self.lock:
            return self.counters.unknown_id_counts(top)

    def health(self) -> dict[str, Any]:
        with self.lock:
            streams = {r.layout.name: r.tracker.counts.as_dict() for r in self._streams.values()}
            return self.counters.report(self.now, self.last_frame_time, streams,
                                        self.faults.report())


__all__ = ["FRAME_ERROR_KINDS", "MAX_COUNTED_IDS", "MAX_UNKNOWN_IDS", "OTHER_IDS", "Rates", "Runtime"]
