"""A composition of plants on the DBC: which frames go out when, and where received ones go.

The DBC says everything: the simulator (node ``SIM``) sends every message whose sender is
``SIM`` and whose signals its plants produce, at the message's ``GenMsgCycleTime``; it
receives every message with a signal addressed to ``SIM`` (demands, scenario commands) and
hands each such signal to the plant that consumes it.

It stands for the engine controller and the valve actuators, so it trusts no frame blindly:

- **Integrity.** A frame of an E2E-protected message (:mod:`cell.bus.e2e`) with a wrong CRC,
  a repeated or skipped alive counter, or older than one cycle of its message on the
  simulator's clock is discarded and counted by message and reason (``SIM_E2E`` frame,
  the log). A frame of a routed message that does not decode is counted as undecodable.
- **Command watchdog.** Each E2E demand the runtime sends cyclically (``VALVE_DEMAND``) is
  watched once its first valid frame has arrived: when no valid frame came for
  ``demand_timeout_cycles`` of its cycles, the plants go to their safe state (valves fully
  open, engine at idle) and ``SAFE_STATE`` says ``DEMAND_TIMEOUT``; they leave it when valid
  demand resumes. A cell whose controllers never sent a demand (disabled, ``--no-controllers``)
  is not in fault, so the watchdog stays unarmed; a controller switched off after sending is
  a demand that stopped, and the cell goes safe until demand resumes.
- **Parent lost** (:meth:`Simulator.parent_lost`): safe state for good, ``PARENT_LOST``.

The simulator's own status (``SIM_STATUS``, ``SIM_E2E``) goes out at its cycle time like any
plant's frame.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import can
import numpy as np
from cantools.database.can import Message

from cell.bus.dbc import CellDatabase, FrameDecodeError
from cell.bus.e2e import E2ESpec, Receiver
from cell.core.errors import ConfigError
from cell.plant.composition import Composition
from cell.runtime.samples import SampleLayout, find_sample_streams
from cell.sim.frame_encode import frame_encoder
from cell.sim.stream_encode import stream_encoder

log = logging.getLogger(__name__)

#: The simulator's node name in the DBC files.
NODE = "SIM"
#: The node whose cyclic demands the command watchdog watches.
DEMANDER = "RUNTIME"
#: ``SAFE_STATE`` values (DBC ``VAL_ 262 SAFE_STATE``).
SAFE_NONE, SAFE_DEMAND_TIMEOUT, SAFE_PARENT_LOST = 0, 1, 2
#: Default of ``--demand-timeout-cycles``.
DEMAND_TIMEOUT_CYCLES = 3.0
_COUNT_MAX = 65535  # the status frames' counters saturate


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
    demand_timeout_cycles:
        Cycles of a watched demand without a valid frame before the safe state.
    clock:
        The bus time now, s, on the clock of received frames' timestamps; default
        ``t0 + t`` (lockstep). The live loop passes the wall clock that the bus stamps
        received frames with.

    Raises
    ------
    ConfigError
        A ``SIM`` message without a cycle time, or one only some of whose signals the
        plants produce (the message names the missing signals).
    """

    def __init__(self, plant: Composition, db: CellDatabase, t0: float = 0.0,
                 demand_timeout_cycles: float = DEMAND_TIMEOUT_CYCLES,
                 clock: Callable[[], float] | None = None) -> None:
        if not demand_timeout_cycles > 0 or not math.isfinite(demand_timeout_cycles):
            raise ConfigError(f"--demand-timeout-cycles must be a number > 0, got "
                              f"{demand_timeout_cycles}")
        self.plant = plant
        self.db = db
        self.t0 = float(t0)
        self.clock = clock if clock is not None else (lambda: self.t0 + self.plant.t)
        self.e2e = Receiver()
        self.undecodable = 0
        self.safe_state = SAFE_NONE
        self.schedule: list[tuple[Message, int, tuple[str, ...]]] = []
        own = self._own = self._own_signals()
        self._own_messages: set[str] = set()
        skipped = []
        for m in db.messages:
            if NODE not in (m.senders or []):
                continue
            names = tuple(s.name for s in m.signals)
            missing = [n for n in plant.missing(names) if n not in own]
            if any(n in own for n in names):
                self._own_messages.add(m.name)
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
        #: each cyclic message's fast encoder (:mod:`cell.sim.frame_encode`); None: ``db.encode``
        self._fast = {m.name: frame_encoder(db, m) for m, _, _ in self.schedule}
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
        #: watched demands: message name -> (timeout s, bus time of the last valid frame)
        self.watched: dict[str, list] = {}
        for m, _ in self.routes.values():
            spec = db.e2e.get(m.name)
            if spec is not None and spec.cycle_s and DEMANDER in (m.senders or []):
                self.watched[m.name] = [demand_timeout_cycles * spec.cycle_s, None]

    def _own_signals(self) -> dict[str, Callable[[], float]]:
        """The signals of the simulator's own status frames, by name."""
        def count(reason: str) -> Callable[[], float]:
            return lambda: float(min(self.e2e.by_reason()[reason], _COUNT_MAX))
        return {
            "SAFE_STATE": lambda: float(self.safe_state),
            "SIM_UNDECODABLE": lambda: float(min(self.undecodable, _COUNT_MAX)),
            "E2E_DISCARDED": lambda: float(min(sum(self.e2e.discarded.values()), _COUNT_MAX)),
            "E2E_CRC_ERRORS": count("crc"),
            "E2E_REPEATED": count("repeated"),
            "E2E_SKIPPED": count("skipped"),
            "E2E_TOO_OLD": count("too_old"),
        }

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
        own = self._own
        ts = self.t0 + self.plant.t
        fast = self._fast
        for m, names in due:
            enc = fast.get(m.name)
            if m.name in self._own_messages:
                vals = {s: own[s]() if s in own else values[s] for s in names}
            elif enc is not None:
                out.append(enc(values, ts))  # reads the message's signals only
                continue
            else:
                vals = {s: values[s] for s in names}
            out.append(enc(vals, ts) if enc is not None else self.db.encode(m.name, vals, ts))
        return out

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

        Frames not addressed to the simulator are ignored (a bus carries all kinds of
        traffic); a routed frame that does not decode is counted (``undecodable``), one that
        fails its E2E check is discarded and counted, non-finite values are dropped.
        """
        route = self.routes.get((msg.arbitration_id, bool(msg.is_extended_id)))
        if route is None:
            return False
        message, names = route
        try:
            data = bytes(msg.data)
            values = self.db.decode_payload(self.db.check(msg), data)
        except (FrameDecodeError, TypeError, ValueError):
            self.undecodable += 1
            return False
        spec = self.db.e2e.get(message.name)
        now = self.clock()
        if spec is not None and not self._valid(spec, data, values, msg, now):
            return False
        watch = self.watched.get(message.name)
        if watch is not None:
            watch[1] = now
        commands = {}
        for name in names:
            v = values.get(name)
            if v is None or not math.isfinite(v):
                continue
            if name in self.plant.commander:
                commands[name] = v
            else:
                self.plant.set_input(name, v)
        if commands:
            self.plant.command(commands)
        return True

    def _valid(self, spec: E2ESpec, data: bytes, values: dict[str, float], msg: can.Message,
               now: float) -> bool:
        age = now - float(msg.timestamp or 0.0)
        reason = self.e2e.check(spec, data, int(values[spec.counter]), age)
        if reason is None:
            return True
        n = self.e2e.discarded[(spec.message, reason)]
        if n & (n - 1) == 0:  # the 1st, 2nd, 4th, 8th ... of each kind: a flood stays readable
            log.warning("discarded %s frame #%d for %s (age %.3f s, counter %d); discarded so "
                        "far: %s", spec.message, n, reason, age, int(values[spec.counter]),
                        self.discards())
        return False

    def discards(self) -> str:
        """The frames discarded so far, by message and reason, as one line."""
        return ", ".join(f"{m} {r} {n}" for (m, r), n in sorted(self.e2e.discarded.items())) \
            or "none"

    def watchdog(self) -> None:
        """Enter or leave the safe state as the watched demands say (see the module notes)."""
        if self.safe_state == SAFE_PARENT_LOST:
            return
        now = self.clock()
        late = [name for name, (timeout, last) in self.watched.items()
                if last is not None and now - last > timeout + 1e-9]
        if late and self.safe_state == SAFE_NONE:
            log.warning("at t=%.2f s no valid %s for %.2f s: safe state (valves open, engine "
                        "idle)", self.t, ", ".join(late), now - self.watched[late[0]][1])
            self.safe_state = SAFE_DEMAND_TIMEOUT
            self.plant.set_safe(True)
        elif not late and self.safe_state == SAFE_DEMAND_TIMEOUT:
            log.info("at t=%.2f s valid demand resumed: safe state left", self.t)
            self.safe_state = SAFE_NONE
            self.plant.set_safe(False)

    def parent_lost(self) -> None:
        """The process that commands this simulator died: safe state for good."""
        if self.safe_state != SAFE_PARENT_LOST:
            self.safe_state = SAFE_PARENT_LOST
            self.plant.set_safe(True)

    def step(self) -> None:
        self.watchdog()
        self.plant.step()
