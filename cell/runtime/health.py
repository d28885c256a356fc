"""What a runtime counts of its own running: frames, bad frames, ticks and their overruns.

:class:`HealthCounters` holds the counts ``/health`` and ``/metrics`` show: frames received
(by arbitration ID and in all), frames that could not be decoded by kind, frame IDs that no
DBC file defines, frames older than the newest one, block steps that failed, outputs
withheld from the bus for not being finite, ticks that had work, the ticks whose work
outlasted their period and the wall time of each block's step. The scheduler
(:class:`cell.runtime.scheduler.Runtime`) counts into it as it applies frames and runs ticks.
"""

from __future__ import annotations

import bisect
import collections
import math
from typing import Any

from cell.bus.dbc import DECODE_ERROR_KINDS

#: distinct arbitration IDs counted one by one (``frames_by_id``); frames of further IDs
#: are counted together under :data:`OTHER_IDS`, so a bus of random IDs stays bounded
MAX_COUNTED_IDS = 1024
OTHER_IDS = (-1, False)

#: Kinds of bad frame counted in ``/health``: the decoder's, plus remote and error frames
#: (which carry no signal values).
FRAME_ERROR_KINDS = (*DECODE_ERROR_KINDS, "remote_frame", "error_frame")

#: How many distinct unknown frame IDs are remembered (a fuzzed bus has millions).
MAX_UNKNOWN_IDS = 256

#: Bus times of the most recent frames kept for the frame rate.
FRAME_TIMES = 20_000

#: The window of the "per minute" counts (tick overruns, missed cycles), seconds of bus time.
MINUTE_S = 60.0

#: A message's inter-arrival longer than this (seconds of bus time) is an outage (its sender
#: stopped, the bus fell silent: its channels turn stale and say so), not missed cycles.
OUTAGE_S = 1.0

#: Bus time a message with a gap is watched before its missed cycles are counted.
SETTLE_S = 0.5

#: Events kept for the per-minute counts (beyond this, the oldest are forgotten).
EVENT_TIMES = 10_000

#: Upper bounds (wall seconds) of the tick-duration histogram's buckets; a last bucket holds
#: everything slower.
TICK_BUCKETS = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5)


class CycleGaps:
    """Frames lost on the way, found from each cyclic message's arrivals.

    A frame that comes more than 1.5 DBC cycles after the one before is a sign of loss, but
    not proof: a sender that was late sends what was due at once, and bus time is the send or
    receive time on these buses. So a gap only makes its message *suspect*; once at least
    :data:`SETTLE_S` of bus time has passed since the last look, the frames that came are
    compared with the cycles that passed: ``round(dt / cycle) - frames`` cycles were missed,
    when positive. A late sender that caught up misses nothing, jitter does not add up, a
    sender slower than its DBC cycle (no single gap) misses nothing, and a gap over
    :data:`OUTAGE_S` is an outage instead (its sender stopped, the bus fell silent: the
    channels turn stale and say so).
    """

    def __init__(self) -> None:
        #: frame key -> bus time of its newest frame (the scheduler keeps it, frame by frame)
        self.arrived: dict[tuple[int, bool], float] = {}
        #: missed cycles by message name
        self.missed: collections.Counter[str] = collections.Counter()
        #: outages (gaps over OUTAGE_S) by message name
        self.outages: collections.Counter[str] = collections.Counter()
        #: (bus time, cycles) of each loss, for the last minute's count
        self.times: collections.deque[tuple[float, int]] = collections.deque(maxlen=EVENT_TIMES)
        #: key -> (message name, cycle) of messages with a gap since their window began
        self._suspect: dict[tuple[int, bool], tuple[str, float]] = {}
        #: key -> (bus time, frames counted) where the message's window began
        self._window: dict[tuple[int, bool], tuple[float, int]] = {}

    def gap(self, key: tuple[int, bool], name: str, dt: float, cycle_s: float) -> None:
        """Message ``name`` (cycle ``cycle_s``) came ``dt`` after its frame before."""
        if dt > OUTAGE_S:
            self.outages[name] += 1
            self._window.pop(key, None)  # a new window begins after the outage
            self._suspect.pop(key, None)
            return
        self._suspect[key] = (name, cycle_s)

    def settle(self, key: tuple[int, bool], ts: float, count: int | None) -> None:
        """The message of ``key``'s newest frame is stamped ``ts``; ``count`` of its frames
        have been received so far (called as the runtime decodes it)."""
        if count is None:
            return
        w = self._window.get(key)
        if w is None or ts < w[0]:
            self._window[key] = (ts, count)
            return
        suspect = self._suspect.get(key)
        if suspect is None:
            self._window[key] = (ts, count)
            return
        if ts - w[0] < SETTLE_S:
            return  # let a late sender catch up before counting
        name, cycle = suspect
        missed = round((ts - w[0]) / cycle) - (count - w[1])
        if missed > 0:
            self.missed[name] += missed
            self.times.append((ts, missed))
        del self._suspect[key]
        self._window[key] = (ts, count)

    def last_minute(self, now: float | None) -> int:
        if now is None:
            return 0
        return sum(n for t, n in self.times if t > now - MINUTE_S)



class HealthCounters:
    """The frame, error and tick counts of one runtime, and the ``/health`` answer drawn from them.

    The bounds on distinct IDs (:data:`MAX_COUNTED_IDS`, :data:`MAX_UNKNOWN_IDS`) are read
    when the counters are made.
    """

    def __init__(self) -> None:
        #: frames applied, good or bad
        self.frames = 0
        #: frames stamped earlier than the newest frame already applied
        self.late_frames = 0
        self.decode_errors: collections.Counter[str] = collections.Counter(
            {k: 0 for k in FRAME_ERROR_KINDS}
        )
        #: frames whose ID no DBC file defines, by ID (at most ``max_unknown_ids`` distinct IDs)
        self.unknown_ids: collections.Counter[tuple[int, bool]] = collections.Counter()
        self.max_unknown_ids = MAX_UNKNOWN_IDS
        #: block steps (and sample hand-overs) that failed, by block
        self.block_errors: collections.Counter[str] = collections.Counter()
        #: outputs withheld from the bus because a block produced NaN or inf, by channel
        self.withheld: collections.Counter[str] = collections.Counter()
        #: bus times of the latest frames, for the frame rate
        self.frame_times: collections.deque[float] = collections.deque(maxlen=FRAME_TIMES)
        #: frames received per (arbitration ID, extended), known or not
        self.frames_by_id: dict[tuple[int, bool], int] = {}
        self.max_counted_ids = MAX_COUNTED_IDS
        #: ticks that had work (every MED tick; FAS and SLO ticks when a block runs at them)
        self.ticks = 0
        #: ticks whose work (block steps and MED listeners) took longer than their period
        self.tick_overruns = 0
        #: wall seconds of the slowest tick so far
        self.tick_seconds_max = 0.0
        #: per block: [wall seconds spent in step, steps]
        self.step_time: dict[str, list[float]] = {}
        #: ticks by duration: ``tick_buckets[i]`` ticks took at most TICK_BUCKETS[i] (and more
        #: than the bound before); the last holds the slower ones
        self.tick_buckets = [0] * (len(TICK_BUCKETS) + 1)
        #: wall seconds of all ticks together
        self.tick_seconds_sum = 0.0
        #: bus times of the latest overruns, for the overruns per minute
        self.overrun_times: collections.deque[float] = collections.deque(maxlen=EVENT_TIMES)
        #: cycles missed by cyclic messages (:class:`CycleGaps`)
        self.gaps = CycleGaps()
        #: MED-tick listeners that raised, by listener (the tick goes on)
        self.listener_errors: collections.Counter[str] = collections.Counter()
        #: output frames that could not be encoded, by message (they stay off the bus)
        self.encode_errors: collections.Counter[str] = collections.Counter()
        #: decoded bus values outside their signal's range or rate limit, by signal
        #: (:mod:`cell.runtime.plausibility`)
        self.implausible: collections.Counter[str] = collections.Counter()
        #: frames of a simulator message beyond its cycle rate (a second sender), by message
        #: (counted by :class:`cell.runtime.senders.SenderWatch`)
        self.conflicts: collections.Counter[str] = collections.Counter()

    # -- counting -------------------------------------------------------------------
    def count_decode_error(self, kind: str, key: tuple[int, bool] | None = None) -> None:
        """Count a frame that could not be decoded; an unknown ID is also counted by ID,
        for as many distinct IDs as are remembered."""
        self.decode_errors[kind] += 1
        if kind == "unknown_id" and key is not None and (
                key in self.unknown_ids or len(self.unknown_ids) < self.max_unknown_ids):
            self.unknown_ids[key] += 1

    def count_tick(self, seconds: float) -> None:
        """Count a tick that had work and took ``seconds`` of wall time."""
        self.ticks += 1
        if seconds > self.tick_seconds_max:
            self.tick_seconds_max = seconds
        self.tick_seconds_sum += seconds
        self.tick_buckets[bisect.bisect_left(TICK_BUCKETS, seconds)] += 1

    def tick_histogram(self) -> tuple[list[tuple[float, int]], float]:
        """Cumulative ``(upper bound, ticks)`` of the tick durations (the last bound is
        infinite) and their sum, as a Prometheus histogram counts them."""
        out, total = [], 0
        for bound, n in zip((*TICK_BUCKETS, math.inf), self.tick_buckets):
            total += n
            out.append((bound, total))
        return out, self.tick_seconds_sum

    def count_overrun(self, t: float | None = None) -> None:
        """Count a tick (at bus time ``t``) whose work took longer than its period."""
        self.tick_overruns += 1
        if t is not None:
            self.overrun_times.append(t)

    def overruns_per_minute(self, now: float | None) -> int:
        """Tick overruns over the last minute of bus time before ``now``."""
        if now is None:
            return 0
        return sum(1 for t in self.overrun_times if t > now - MINUTE_S)

    def count_step(self, block: str, seconds: float) -> None:
        """Add one step of ``block`` that took ``seconds`` of wall time."""
        spent = self.step_time.get(block)
        if spent is None:
            spent = self.step_time[block] = [0.0, 0]
        spent[0] += seconds
        spent[1] += 1

    def forget_block(self, block: str) -> None:
        """Drop the error count of a removed block (it ended with it)."""
        self.block_errors.pop(block, None)

    def forget_output(self, channel: str) -> None:
        """Drop the withheld count of a removed block's output."""
        self.withheld.pop(channel, None)

    # -- reading --------------------------------------------------------------------
    def frames_per_second(self, now: float | None, window_s: float = 1.0) -> float:
        """Frame rate over the ``window_s`` seconds of bus time before ``now``."""
        if not self.frame_times:
            return 0.0
        count = sum(1 for t in reversed(self.frame_times) if t > now - window_s)
        return count / window_s

    def unknown_id_counts(self, top: int = 32) -> dict[str, int]:
        """The most frequent frame IDs that no DBC defines, as ``"0x123"`` (``x`` suffix:
        extended) -> frames."""
        return {f"0x{i:X}{'x' if ext else ''}": n
                for (i, ext), n in self.unknown_ids.most_common(top)}

    def report(self, now: float | None, last_frame_time: float | None,
               streams: dict[str, dict[str, Any]],
               block_faults: dict[str, dict[str, Any]] | None = None) -> dict[str, Any]:
        """The runtime's part of ``/health``, at bus time ``now``, with the sample streams'
        order and loss counts."""
        return {
            "frames": self.frames,
            "frames_per_s": self.frames_per_second(now),
            "decode_errors": dict(self.decode_errors),
            "late_frames": self.late_frames,
            "unknown_ids": self.unknown_id_counts(),
            "block_errors": dict(self.block_errors),
            "block_faults": block_faults or {},
            "streams": streams,
            "withheld": dict(self.withheld),
            "implausible": dict(self.implausible),
            "tick_overruns": self.tick_overruns,
            "tick_overruns_per_min": self.overruns_per_minute(now),
            "frames_lost": {"missed_cycles": sum(self.gaps.missed.values()),
                            "missed_cycles_last_min": self.gaps.last_minute(now),
                            "by_message": dict(self.gaps.missed),
                            "outages": dict(self.gaps.outages)},
            "listener_errors": dict(self.listener_errors),
            "encode_errors": dict(self.encode_errors),
            "conflicts": dict(self.conflicts),
            "last_frame_time": last_frame_time,
            "bus_time": now,
        }


__all__ = ["FRAME_ERROR_KINDS", "MAX_COUNTED_IDS", "MAX_UNKNOWN_IDS", "MINUTE_S", "OTHER_IDS", "OUTAGE_S",
           "TICK_BUCKETS", "CycleGaps", "HealthCounters"]
