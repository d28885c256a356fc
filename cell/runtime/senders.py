"""A second sender on the bus: frames the simulator sends, arriving faster than it sends them.

CAN has no sender address: a forger that puts ``ENGINE_STATUS`` on the bus is read like the
simulator. What gives it away is the rate. Every message whose DBC transmitter is ``SIM`` and
that declares a cycle time (``GenMsgCycleTime``) should arrive once per cycle; a second
sender of the same message makes it arrive more often.

:class:`SenderWatch` counts, over windows of :data:`WINDOW_S` seconds of bus time (taken at
the runtime's MED ticks, from the frame counts it keeps anyway, so nothing is added per
frame), how many cycles' worth of frames each such message brought: ``frames * cycle``. For
the simulator's own messages that is the same number for all of them, the *pace* of the
bus: the window's length at speed 1, twenty times it when the simulator runs at ``--speed
20`` and frames are stamped on receipt. The pace is taken as the median over the messages
seen (at least :data:`MIN_PEERS` of them; with fewer, speed 1 is assumed). A message that
brought more than :data:`CONFLICT_RATIO` times the pace (1.5 frames per cycle, where one
sender brings one) is in *conflict*: its frames beyond the pace are counted as that
message's conflicts, and ``/health`` names it (degraded) for :data:`HOLD_WINDOWS` windows
after the last window that showed it.

A forger that copies most of the simulator's messages moves the median too; this watch
sees a second sender of a few messages, which is what a forged command or status is.
"""

from __future__ import annotations

import statistics
from collections.abc import Mapping
from typing import Any

#: The node whose messages are watched (the DBC's transmitter of the simulator's frames).
SIM_NODE = "SIM"
#: Seconds of bus time per window.
WINDOW_S = 1.0
#: Frames per cycle over a window above which a message has a second sender.
CONFLICT_RATIO = 1.5
#: Fewest frames of a message in a window before its rate is judged (a 100 ms message
#: brings 10 a window at speed 1).
MIN_FRAMES = 4
#: Fewest messages seen in a window for their median to set the pace.
MIN_PEERS = 3
#: Windows after the last conflict during which ``/health`` still names the message.
HOLD_WINDOWS = 3


class SenderWatch:
    """Counts the second senders of the simulator's messages (see the module notes).

    Parameters
    ----------
    messages:
        The DBC messages (cantools ``Message`` objects) of the cell.
    counters:
        The runtime's :class:`~cell.runtime.health.HealthCounters`: its ``frames_by_id`` (frames
        per ``(arbitration ID, extended)``) is read at each window's end, and the conflicts
        are counted into its ``conflicts``.
    """

    def __init__(self, messages: Any, counters: Any) -> None:
        #: frame key -> (message name, cycle time in s) of every watched message
        self.watched: dict[tuple[int, bool], tuple[str, float]] = {
            (m.frame_id, bool(m.is_extended_frame)): (m.name, m.cycle_time / 1000.0)
            for m in messages if SIM_NODE in (m.senders or []) and m.cycle_time}
        self._counters = counters
        self._seen: dict[tuple[int, bool], int] = {}
        self._start: float | None = None
        #: per message in conflict: its frames per cycle in the last window that showed it
        #: and that window's end (bus time)
        self.last: dict[str, tuple[float, float]] = {}
        self.windows = 0
        self.pace: float | None = None

    def at(self, t: float) -> None:
        """Called at every MED tick with its bus time: closes a window when one is full."""
        if self._start is None:
            self._start, self._seen = t, self._snapshot()
            return
        span = t - self._start
        if span < WINDOW_S:
            return
        now = self._snapshot()
        counts = {key: n - self._seen.get(key, 0) for key, n in now.items()}
        self._start, self._seen = t, now
        self.windows += 1
        self._judge(counts, span, t)

    def _snapshot(self) -> dict[tuple[int, bool], int]:
        counts: Mapping[tuple[int, bool], int] = self._counters.frames_by_id
        return {key: counts.get(key, 0) for key in self.watched}

    def _judge(self, counts: dict[tuple[int, bool], int], span: float, t: float) -> None:
        cycles = {key: n * self.watched[key][1] for key, n in counts.items() if n > 0}
        if len(cycles) >= MIN_PEERS:
            pace = statistics.median(cycles.values())
        else:
            pace = span  # too few messages to tell the speed: one frame per cycle of bus time
        self.pace = pace / span if span > 0 else None
        if pace <= 0:
            return
        for key, c in cycles.items():
            name, cycle = self.watched[key]
            n = counts[key]
            if n >= MIN_FRAMES and c > CONFLICT_RATIO * pace:
                extra = n - round(pace / cycle)
                self._counters.conflicts[name] += max(1, extra)
                self.last[name] = (c / pace, t)

    def active(self, now: float | None) -> dict[str, float]:
        """The messages in conflict now (shown in a window at most :data:`HOLD_WINDOWS`
        windows ago), with their frames per cycle."""
        if now is None:
            return {}
        hold = HOLD_WINDOWS * WINDOW_S + WINDOW_S
        return {name: ratio for name, (ratio, at) in self.last.items() if now - at <= hold}

    def reasons(self, now: float | None) -> list[str]:
        """One ``/health`` reason per message in conflict now."""
        return [f"second sender of {name} on the bus: {ratio:.1f} frames per cycle where "
                f"the simulator sends 1 ({self.conflicts[name]} extra frames so far)"
                for name, ratio in sorted(self.active(now).items())]

    @property
    def conflicts(self) -> dict[str, int]:
        """Frames beyond one sender's pace, by message, since the start (``/health``'s
        ``conflicts``)."""
        return self._counters.conflicts


__all__ = ["CONFLICT_RATIO", "HOLD_WINDOWS", "MIN_FRAMES", "MIN_PEERS", "SIM_NODE", "WINDOW_S",
           "SenderWatch"]
