"""The live cell: a thread that feeds bus frames to the runtime and puts its outputs on the bus.

Bus time comes from frame timestamps. When the bus falls silent (a receive times out), bus
time is carried on from the last frame with a monotonic clock (less a short grace for
frames in flight), so ticks keep coming and inputs can go stale.

When the bus goes away (a socket error, a deleted interface) the loop keeps ticking, so
everything turns stale, and reopens the bus with exponential backoff until it is back.
Each change of state (bus lost, bus back, bus silent, frames again) is logged once, never
once per frame or per attempt; ``/health`` shows the current problem (:attr:`bus_problem`).
"""

from __future__ import annotations

import gc
import logging
import threading
import time

from cell.bus.interface import CellBus
from cell.core.errors import BusError
from cell.runtime.scheduler import Runtime

log = logging.getLogger(__name__)


class Backoff:
    """Delays between reconnection attempts: ``first``, doubling, at most ``cap`` seconds."""

    def __init__(self, first: float = 0.1, cap: float = 5.0) -> None:
        self.first, self.cap = first, cap
        self.attempts = 0

    def next(self) -> float:
        delay = min(self.cap, self.first * 2.0 ** self.attempts)
        self.attempts += 1
        return delay

    def reset(self) -> None:
        self.attempts = 0


class LiveCell:
    """Run a :class:`~cell.runtime.scheduler.Runtime` against a bus in a background thread.

    Parameters
    ----------
    runtime:
        The runtime to drive.
    bus:
        The open bus (frames in, outputs out).
    grace_s:
        How far behind the monotonic estimate of bus time ticks are run on a silent
        bus, so that frames still in flight are applied before their tick.
    silent_s:
        Wall-clock seconds without a frame after which the bus is reported silent.
    backoff:
        Delays between attempts to reopen a bus that went away.
    """

    #: Most frames taken from the socket before they are handed to the runtime together.
    BATCH = 256

    def __init__(self, runtime: Runtime, bus: CellBus, grace_s: float = 0.05,
                 silent_s: float = 1.0, backoff: Backoff | None = None) -> None:
        self.runtime = runtime
        self.bus = bus
        self.grace_s = grace_s
        self.silent_s = silent_s
        self.backoff = backoff or Backoff()
        self.send_errors = 0
        self.reconnects = 0
        #: why the bus is not usable now (``None``: it is)
        self.bus_problem: str | None = None
        self.silent = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._anchor: tuple[float, float] | None = None  # (bus time, monotonic) of newest frame
        self._retry_at = 0.0

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
        """Stop the loop and wait for it; the bus may be closed safely afterwards."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    @property
    def undecodable(self) -> int:
        """Datagrams or frames the bus could not decode and skipped (:class:`CellBus`)."""
        return getattr(self.bus, "undecodable", 0)

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def estimated_bus_time(self) -> float | None:
        if self._anchor is None:
            return None
        ts, mono = self._anchor
        return ts + (time.monotonic() - mono)

    # -- the loop ---------------------------------------------------------------------------
    def _loop(self) -> None:
        while not self._stop.is_set():
            if self.bus_problem is not None:
                self._try_reopen()
                if self.bus_problem is not None:
                    self._tick_silent()
                    self._stop.wait(0.01)
                    continue
            batch: list = []
            failure: BaseException | None = None
            try:
                msg = self.bus.recv(timeout=0.01)
                if msg is not None:
                    batch.append(msg)
                    while len(batch) < self.BATCH:  # what is already queued, in one go
                        msg = self.bus.recv(timeout=0.0)
                        if msg is None:
                            break
                        batch.append(msg)
            except Exception as exc:  # a broken bus must not kill the cell
                failure = exc
            if batch:
                if self.silent:
                    self.silent = False
                    log.info("frames again on %s", self.bus.spec)
                self.runtime.ingest_many(batch)
                newest = max(m.timestamp for m in batch)
                if self._anchor is None or newest >= self._anchor[0]:
                    self._anchor = (newest, time.monotonic())
            if failure is not None:
                if self._stop.is_set():
                    break  # closed under us while stopping: not an error
                self._lost(failure)
                continue
            if not batch:
                # the socket is drained: only now may ticks run ahead of the frames, or a
                # backlog of received but unread frames would miss their ticks
                self._tick_silent()
            self._send_outbox()

    def _tick_silent(self) -> None:
        est = self.estimated_bus_time()
        if est is None:
            return
        self.runtime.advance(est - self.grace_s)
        if not self.silent and time.monotonic() - self._anchor[1] > self.silent_s:  # type: ignore[index]
            self.silent = True
            log.warning("no frame on %s for %.1f s: inputs turn stale", self.bus.spec, self.silent_s)

    def _send_outbox(self) -> None:
        for out in self.runtime.take_outbox():
            if self.bus_problem is not None:
                return  # outputs of a tick without a bus are dropped, not queued
            try:
                self.bus.send(out)
            except BusError as exc:
                self.send_errors += 1
                if self.send_errors in (1, 10, 100) or self.send_errors % 1000 == 0:
                    log.warning("send failed (%d so far): %s", self.send_errors, exc)

    def _lost(self, exc: BaseException) -> None:
        self.bus_problem = f"bus {self.bus.spec} lost: {exc}; reconnecting"
        log.error("bus receive failed on %s: %s; reconnecting with backoff", self.bus.spec, exc)
        self.backoff.reset()
        self._retry_at = time.monotonic() + self.backoff.next()

    def _try_reopen(self) -> None:
        if time.monotonic() < self._retry_at:
            return
        try:
            self.bus.reopen()
        except Exception as exc:  # still gone: try again later, quietly
            self._retry_at = time.monotonic() + self.backoff.next()
            log.debug("reopening %s failed (attempt %d): %s", self.bus.spec,
                      self.backoff.attempts, exc)
            return
        self.reconnects += 1
        log.warning("bus %s is back after %d attempt(s)", self.bus.spec, self.backoff.attempts)
        self.bus_problem = None
