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
from cantools.database.can import Message

from ..dbc import CellDatabase, FrameDecodeError
from ..errors import ConfigError
from ..plant.composition import Composition

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
        due = [(m, names) for m, period, names in self.schedule if k % period == 0]
        if not due:
            return []
        values = self.plant.signals
        ts = self.t0 + self.plant.t
        return [self.db.encode(m.name, {s: values[s] for s in names}, ts) for m, names in due]

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
