"""What a runtime counts of its own running: frames, bad frames, ticks and their overruns.

:class:`HealthCounters` holds the counts ``/health`` and ``/metrics`` show: frames received
(by arbitration ID and in all), frames that could not be decoded by kind, frame IDs that no
DBC file defines, frames older than the newest one, block steps that failed, outputs
withheld from the bus for not being finite, ticks that had work, the ticks whose work
outlasted their period and the wall time of each block's step. The scheduler
(:class:`cell.runtime.scheduler.Runtime`) counts into it as it applies frames and runs ticks.
"""

from __future__ import annotations

import collections
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
        #: decoded bus values outside their signal's range or rate limit, by signal
        #: (:mod:`cell.runtime.plausibility`)
        self.implausible: collections.Counter[str] = collections.Counter()

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

    def count_overrun(self) -> None:
        """Count a tick whose work took longer than its period."""
        self.tick_overruns += 1

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
               streams: dict[str, dict[str, Any]]) -> dict[str, Any]:
        """The runtime's part of ``/health``, at bus time ``now``, with the sample streams'
        order and loss counts."""
        return {
            "frames": self.frames,
            "frames_per_s": self.frames_per_second(now),
            "decode_errors": dict(self.decode_errors),
            "late_frames": self.late_frames,
            "unknown_ids": self.unknown_id_counts(),
            "block_errors": dict(self.block_errors),
            "streams": streams,
            "withheld": dict(self.withheld),
            "implausible": dict(self.implausible),
            "tick_overruns": self.tick_overruns,
            "last_frame_time": last_frame_time,
            "bus_time": now,
        }


__all__ = ["FRAME_ERROR_KINDS", "MAX_COUNTED_IDS", "MAX_UNKNOWN_IDS", "OTHER_IDS", "HealthCounters"]
