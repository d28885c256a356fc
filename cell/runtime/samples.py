"""Crank-angle sample streams: many consecutive samples per frame, consumed in angle order.

A cyclic channel holds the latest value at each tick, which suits a 10 Hz filter. A signal
sampled every 6 deg of crank angle (seed 001) is different: 6 000 samples/s at 6 000 rpm,
and an observer of it must see every sample, in order. Such a signal travels as a *sample
stream*: each frame carries several consecutive samples and the crank angle of the first.

The DBC says which messages are streams, by a naming rule (no attribute needed, so a user's
logger decodes the frames with plain cantools):

- one signal ``<STREAM>_ANGLE`` (unit ``deg``): the crank angle of the frame's first sample.
  Its scale is the sample step (6 deg) and its DBC maximum plus one step is the angle
  period over which it wraps (720 deg, one engine cycle);
- signals ``<STREAM>_0`` ... ``<STREAM>_{n-1}``: the ``n`` consecutive samples, sample ``k``
  at ``ANGLE + k * step``.

:class:`SampleLayout` reads that layout from a message and packs or unpacks frame values;
the simulator packs through it, the runtime unpacks through it (encoding and decoding stay
in :mod:`cell.bus.dbc`). :class:`SampleTracker` puts a stream's frames back in angle order: a
frame that arrives early waits (up to ``window`` frames) for the ones before it; a gap that
does not fill is reported as lost samples; a frame that arrives after its place has passed
is dropped. Everything is counted, for ``/health``.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from cantools.database.can import Message

#: suffix of the signal that carries the frame's first sample's crank angle
ANGLE_SUFFIX = "_ANGLE"


@dataclass(frozen=True)
class SampleLayout:
    """The layout of one sample-stream message (see the module docstring).

    Attributes
    ----------
    name:
        The stream's name (the signals' common prefix), e.g. ``AFR_UEGO``.
    message:
        The DBC message's name.
    angle_signal, sample_signals:
        Signal names: the start angle and the ``n`` samples in angle order.
    step_deg, period_deg:
        Sample step and wrap period of the angle, deg CA.
    """

    name: str
    message: str
    angle_signal: str
    sample_signals: tuple[str, ...]
    step_deg: float
    period_deg: float
    unit: str = ""

    @property
    def n(self) -> int:
        """Samples per frame."""
        return len(self.sample_signals)

    @property
    def period(self) -> int:
        """Samples per angle period (120 for 6 deg over 720 deg)."""
        return int(round(self.period_deg / self.step_deg))

    @classmethod
    def from_message(cls, message: Message) -> SampleLayout | None:
        """The stream layout of ``message``, or ``None`` when it is not a sample stream."""
        angle = [s for s in message.signals if s.name.endswith(ANGLE_SUFFIX)]
        if len(angle) != 1 or (angle[0].unit or "").lower() != "deg":
            return None
        a = angle[0]
        name = a.name[: -len(ANGLE_SUFFIX)]
        others = {s.name: s for s in message.signals if s is not a}
        samples = tuple(f"{name}_{k}" for k in range(len(others)))
        if not others or set(samples) != set(others) or a.maximum is None or not a.scale > 0:
            return None
        step = float(a.scale)
        period = float(a.maximum) + step
        if abs(period / step - round(period / step)) > 1e-9:
            return None
        return cls(name, message.name, a.name, samples, step, period, others[samples[0]].unit or "")

    def frame_values(self, index: int, samples: np.ndarray) -> dict[str, float]:
        """Signal values of a frame whose first sample has angle index ``index``."""
        values = {self.angle_signal: (index % self.period) * self.step_deg}
        values.update(zip(self.sample_signals, (float(v) for v in samples)))
        return values

    def unpack(self, values: Mapping[str, float]) -> tuple[int, np.ndarray]:
        """``(angle index of the first sample, samples)`` of a decoded frame."""
        index = int(round(values[self.angle_signal] / self.step_deg)) % self.period
        return index, np.fromiter((values[s] for s in self.sample_signals), float, self.n)


def find_sample_streams(messages: list[Message]) -> dict[str, SampleLayout]:
    """Every sample-stream layout among ``messages``, by stream name."""
    out = {}
    for m in messages:
        layout = SampleLayout.from_message(m)
        if layout is not None:
            out[layout.name] = layout
    return out


@dataclass
class SampleCounts:
    """What a :class:`SampleTracker` saw, as shown in ``/health``."""

    frames: int = 0
    samples: int = 0
    #: frames that arrived after a later one and were put back in order
    reordered: int = 0
    #: frames that arrived after their place had passed (dropped)
    late: int = 0
    #: frames never received: the gaps skipped over, in frames of ``n`` samples
    lost_frames: int = 0
    #: gaps skipped over (each reported to the consuming blocks)
    gaps: int = 0
    last_gap: dict[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass
class SampleTracker:
    """Puts one stream's frames in angle order and finds the missing ones.

    Parameters
    ----------
    layout:
        The stream's layout.
    window:
        Frames that may arrive ahead of a missing one before the gap is declared lost
        (a reordering up to this depth is repaired; a deeper one counts as loss + late).

    :meth:`push` takes a frame and yields events in angle order: ``("samples", index,
    values, t)`` for consecutive samples and ``("gap", lost, index, t)`` before samples
    that follow ``lost`` missing ones. A frame more than half a period behind the expected
    angle is taken as late; when more than ``window`` such frames arrive in sequence, the
    stream has in fact jumped ahead (a long gap): the tracker follows them and reports the
    gap. A gap of a whole multiple of the period (a bus silent for an entire engine cycle)
    cannot be seen from the angle alone.
    """

    layout: SampleLayout
    window: int = 2
    counts: SampleCounts = field(default_factory=SampleCounts)
    _next: int | None = None
    _held: dict[int, tuple[np.ndarray, float]] = field(default_factory=dict)
    _run: list[tuple[int, np.ndarray, float]] = field(default_factory=list)
    _period: int = field(default=0, init=False, repr=False)

    def __post_init__(self) -> None:
        self._period = self.layout.period

    def take(self, index: int, n: int) -> bool:
        """The common case of :meth:`push` without its generator: a frame of ``n`` samples
        at ``index`` that is the one expected, with nothing held back. Counts it and returns
        True (the caller passes its samples on, as the one ``("samples", ...)`` event
        :meth:`push` would yield); returns False, changing nothing, for any other frame."""
        nxt = self._next
        if self._held or (nxt is not None and nxt != index):
            return False
        c = self.counts
        c.frames += 1
        c.samples += n
        if self._run:
            self._run.clear()
        self._next = (index + n) % self._period
        return True

    def push(self, index: int, values: np.ndarray, t: float) -> Iterator[tuple]:
        c, period = self.counts, self.layout.period
        c.frames += 1
        if self._next is None:
            self._next = index
        d = (index - self._next) % period
        if d >= period // 2 or (d == 0 and index in self._held):
            c.late += 1  # its place has passed (or it is a duplicate)...
            run = self._run
            if run and index != (run[-1][0] + len(run[-1][1])) % period:
                run.clear()
            run.append((index, values, t))
            if len(run) <= self.window:
                return
            # ...unless the stream goes on from there: it jumped ahead over a long gap
            c.late -= len(run)
            first = run[0][0]
            lost = (first - self._next) % period
            c.lost_frames += -(-lost // self.layout.n)
            c.gaps += 1
            c.last_gap = {"at_index": first, "lost_samples": lost, "t": run[0][2]}
            yield ("gap", lost, first, run[0][2])
            self._held.clear()
            for i, vals, ts in run:
                c.samples += len(vals)
                yield ("samples", i, vals, ts)
            self._next = (run[-1][0] + len(run[-1][1])) % period
            run.clear()
            return
        self._run.clear()
        if d > 0:
            if index in self._held:
                c.late += 1
                return
            self._held[index] = (values, t)
            if len(self._held) <= self.window:
                return
            # give up on the missing frames: skip to the nearest held one
            nearest = min(self._held, key=lambda i: (i - self._next) % period)
            lost = (nearest - self._next) % period
            c.lost_frames += -(-lost // self.layout.n)
            c.gaps += 1
            c.last_gap = {"at_index": nearest, "lost_samples": lost, "t": t}
            yield ("gap", lost, nearest, t)
            self._next = nearest
        else:
            if self._held:
                c.reordered += 1  # the missing one came: what waited goes out in order
            self._held[index] = (values, t)
        while self._next in self._held:
            vals, ts = self._held.pop(self._next)
            c.samples += len(vals)
            yield ("samples", self._next, vals, ts)
            self._next = (self._next + len(vals)) % period


__all__ = ["SampleCounts", "SampleLayout", "SampleTracker", "find_sample_streams"]
