"""A runtime over frames that already exist (a log): frames, then the ticks due, on bus time.

:func:`feed` runs a runtime over frames, calling ``on_tick`` at every MED tick and finishing
the ticks due at the last frame's time. The closed loop with a simulator is
:class:`cell.sim.lockstep.Lockstep`, which shares :class:`Listening`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import can

from cell.core.errors import LogFormatError
from cell.runtime.scheduler import Runtime

TickListener = Callable[[float], None]


class Listening:
    """Context: ``on_tick`` listens to the runtime's MED ticks while inside."""

    def __init__(self, runtime: Runtime, on_tick: TickListener | None) -> None:
        self.runtime, self.on_tick = runtime, on_tick

    def __enter__(self) -> None:
        if self.on_tick is not None:
            self.runtime.tick_listeners.append(self.on_tick)

    def __exit__(self, *exc: object) -> None:
        if self.on_tick is not None:
            self.runtime.tick_listeners.remove(self.on_tick)


@dataclass
class Fed:
    """What :func:`feed` did: frames applied, the last frame's time, where a log broke."""

    frames: int = 0
    last_time: float | None = None
    error: LogFormatError | None = None


def feed(runtime: Runtime, frames: Iterable[can.Message], on_tick: TickListener | None = None
         ) -> Fed:
    """Run ``runtime`` over ``frames`` (a log), then the ticks due at the last frame's time.

    A malformed log line (:class:`LogFormatError` from the frame iterator) stops the frames;
    the ticks up to the last good frame still run, and the error is returned in the result.
    """
    fed = Fed()
    before = runtime.counters.frames
    with Listening(runtime, on_tick):
        try:
            runtime.ingest_many(frames)
        except LogFormatError as exc:
            fed.error = exc
        fed.frames = runtime.counters.frames - before  # counted as applied, a bad line or not
        if fed.frames:
            fed.last_time = runtime.last_frame_time
            runtime.advance(fed.last_time)
    return fed
