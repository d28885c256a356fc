"""The live cell: a thread that feeds bus frames to the runtime and puts its outputs on the bus.

Bus time comes from frame timestamps. When the bus falls silent (a receive times out), bus
time is carried on from the last frame with a monotonic clock (less a short grace for
frames in flight), so ticks keep coming and inputs can go stale.
"""

from __future__ import annotations

import gc
import logging
import threading
import time

from .bus import CellBus
from .errors import BusError
from .runtime import Runtime

log = logging.getLogger(__name__)


class LiveCell:
    """Run a :class:`~cell.runtime.Runtime` against a bus in a background thread.

    Parameters
    ----------
    runtime:
        The runtime to drive.
    bus:
        The open bus (frames in, outputs out).
    grace_s:
        How far behind the monotonic estimate of bus time ticks are run on a silent
        bus, so that frames still in flight are applied before their tick.
    """

    def __init__(self, runtime: Runtime, bus: CellBus, grace_s: float = 0.05) -> None:
        self.runtime = runtime
        self.bus = bus
        self.grace_s = grace_s
        self.send_errors = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._anchor: tuple[float, float] | None = None  # (bus time, monotonic) of newest frame

    def start(self) -> LiveCell:
        # A full garbage collection pauses every thread for as long as it takes to scan the
        # heap (100-400 ms for a large one), long enough to overrun ticks. What exists at
        # start (modules, the DBC, the blocks) lives as long as the cell: freeze it, so
        # collections scan only what the running cell allocates.
        gc.freeze()
        self._thread = threading.Thread(target=self._loop, name="testcell-runtime", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def estimated_bus_time(self) -> float | None:
        if self._anchor is None:
            return None
        ts, mono = self._anchor
        return ts + (time.monotonic() - mono)

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(timeout=0.01)
            except Exception as exc:  # a broken bus must not kill the cell silently
                log.error("bus receive failed: %s", exc)
                self._stop.wait(0.5)
                continue
            if msg is not None:
                self.runtime.ingest(msg)
                if self._anchor is None or msg.timestamp >= self._anchor[0]:
                    self._anchor = (msg.timestamp, time.monotonic())
            else:
                # the socket is drained: only now may ticks run ahead of the frames, or a
                # backlog of received but unread frames would miss their ticks
                est = self.estimated_bus_time()
                if est is not None:
                    self.runtime.advance(est - self.grace_s)
            for out in self.runtime.take_outbox():
                try:
                    self.bus.send(out)
                except BusError as exc:
                    self.send_errors += 1
                    if self.send_errors in (1, 10, 100) or self.send_errors % 1000 == 0:
                        log.warning("send failed (%d so far): %s", self.send_errors, exc)
