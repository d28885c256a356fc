"""A composition of plants on the DBC: which frames go out when, and where received ones go.

The DBC says everything: the simulator (node ``SIM``) sends every message whose sender is
``SIM`` and whose signals its plants produce, at the message's ``GenMsgCycleTime``; it
receives every message with a signal addressed to ``SIM`` (demands, scenario commands) and
hands each such signal to the plant that consumes it.
"""

from __future__ import annotations

import logging
import math

import can
import numpy as np
from cantools.database.can import Message

from cell.bus.dbc import CellDatabase, FrameDecodeError
from cell.core.errors import ConfigError
from cell.plant.composition import Composition
from cell.runtime.samples import SampleLayout, find_sample_streams
from cell.sim.stream_encode import stream_encoder

log = logging.getLogger(__name__)

#: The simulator's node name in the DBC files.
NODE = "SIM"


class Simulator:
    """A :class:`~cell.plant.composition.Composition` speaking the DBC's frames.

    Parameters
    ----------
    plant:
        The engine's composition.
    db:
        The DBC database.
    t0:
        Bus time of simulation time 0, s (frames are stamped ``t0 + t``).

    Raises
    ------
    ConfigError
        A ``SIM`` message without a cycle time, or one only some of whose signals the
        plants produce (the message names the missing signals).
    """

    def __init__(self, plant: Composition, db: CellDatabase, t0: float = 0.0) -> None:
        self.plant = plant
        self.db = db
        self.t0 = float(t0)
        self.schedule: list[tuple[Message, int, tuple[str, ...]]] = []
        skipped = []
        for m in db.messages:
            if NODE not in (m.senders or []):
                continue
            names = tuple(s.name for s in m.signals)
            missing = plant.missing(names)
            if len(missing) == len(names):
                skipped.append(m.name)  # another engine's frame
                continue
            if missing:
                raise ConfigError(f"{db.file_of(m.name).name}: SIM message {m.name} carries "
                                  f"{', '.join(missing)}, which no plant of engine "
                                  f"{plant.name} produces")
            if not m.cycle_time:
                raise ConfigError(f"{db.file_of(m.name).name}: SIM message {m.name} has no "
                                  "cycle time (GenMsgCycleTime)")
            period = max(1, round(m.cycle_time / 1000.0 / plant.dt))
            self.schedule.append((m, period, names))
        #: sample streams the plants produce: (plant, layout, samples not yet in a frame)
        self.streams: list[tuple[object, SampleLayout, list]] = []
        #: each stream's bulk encoder (:mod:`cell.sim.stream_encode`), None: frame by frame
        self._bulk: dict[str, object] = {}
        layouts = find_sample_streams([m for m in db.messages if NODE in (m.senders or [])])
        for p in plant.plants:
            for name in p.streams:
                layout = layouts.get(name)
                if layout is None:
                    raise ConfigError(f"engine {plant.name}: plant {p.name} produces sample stream "
                                      f"{name}, which no SIM message of the DBC carries")
                skipped = [s for s in skipped if s != layout.message]
                self.streams.append((p, layout, [None, np.empty(0), np.empty(0)]))
                self._bulk[layout.name] = stream_encoder(db.message(layout.message), layout)
        if skipped:
            log.debug("engine %s sends none of %s", plant.name, ", ".join(skipped))
        #: received messages: frame key -> the signals of it that a plant consumes
        self.routes: dict[tuple[int, bool], tuple[Message, tuple[str, ...]]] = {}
        for m in db.messages:
            to_sim = tuple(s.name for s in m.signals
                           if NODE in (s.receivers or []) and s.name in plant.external)
            if to_sim:
                self.routes[(m.frame_id, m.is_extended_frame)] = (m, to_sim)

    @property
    def k(self) -> int:
        return self.plant.k

    @property
    def t(self) -> float:
        """Simulation time, s."""
        return self.plant.t

    @property
    def dt(self) -> float:
        return self.plant.dt

    def frames(self) -> list[can.Message]:
        """DBC-encoded frames due at the current step, stamped ``t0 + t``.

        A message with cycle time ``c`` is due when ``t`` is a multiple of ``c`` (so every
        message is sent at ``t`` = 0). Call once per step, before :meth:`step`.
        """
        k = self.plant.k
        out = self._stream_frames() if self.streams else []
        due = [(m, names) for m, period, names in self.schedule if k % period == 0]
        if not due:
            return out
        values = self.plant.signals
        ts = self.t0 + self.plant.t
        return out + [self.db.encode(m.name, {s: values[s] for s in names}, ts) for m, names in due]

    def _stream_frames(self) -> list[can.Message]:
        """Frames of the stream samples produced so far, ``n`` whole samples per frame.

        A frame starts at a sample whose index is a multiple of ``n`` and is stamped with
        its last sample's time; samples of an incomplete frame wait for the next call.
        Stream frames are stamped at or before the current step, so they come first.
        """
        frames: list[tuple[float, int, can.Message]] = []
        taken: dict[int, dict] = {}
        for p, layout, pend in self.streams:
            if id(p) not in taken:
                taken[id(p)] = p.take_samples()
            got = taken[id(p)].get(layout.name)
            if got is not None and len(got[1]):
                index, vals, times = got
                if pend[0] is None or pend[0] + len(pend[1]) != index:
                    # start (or restart after a discontinuity) at the next frame boundary
                    skip = (-index) % layout.n
                    index, vals, times = index + skip, vals[skip:], times[skip:]
                    pend[0], pend[1], pend[2] = index, np.empty(0), np.empty(0)
                pend[1] = np.concatenate([pend[1], vals])
                pend[2] = np.concatenate([pend[2], times])
            n = layout.n
            whole = (len(pend[1]) // n) * n
            bulk = self._bulk.get(layout.name)
            msgs = bulk(pend[0], pend[1][:whole], pend[2][:whole], self.t0) if bulk and whole else None
            for msg in msgs or ():
                frames.append((msg.timestamp, len(frames), msg))
            for j in range(0, whole if msgs is None else 0, n):
                ts = self.t0 + float(pend[2][j + n - 1])
                msg = self.db.encode(layout.message, layout.frame_values(pend[0] + j, pend[1][j:j + n]), ts)
                frames.append((ts, len(frames), msg))
            if whole:
                pend[0] += whole
                pend[1], pend[2] = pend[1][whole:], pend[2][whole:]
        frames.sort(key=lambda f: (f[0], f[1]))
        return [f[2] for f in frames]

    def receive(self, msg: can.Message) -> bool:
        """Hand a received frame's signals to the plants that consume them; True if routed.

        Frames that do not decode, that are not addressed to the simulator, or whose values
        are not finite are ignored (a bus carries all kinds of traffic).
        """
        route = self.routes.get((msg.arbitration_id, bool(msg.is_extended_id)))
        if route is None:
            return False
        message, names = route
        try:
            values = self.db.decode_payload(self.db.check(msg), bytes(msg.data))
        except FrameDecodeError:
            return False
        for name in names:
            v = values.get(name)
            if v is not None and math.isfinite(v):
                self.plant.set_input(name, v)
        return True

    def step(self) -> None:
        self.plant.step()
