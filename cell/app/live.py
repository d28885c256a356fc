"""The live cell: a thread that feeds bus frames to the runtime and puts its outputs on the bus.

Bus time comes from frame timestamps. When the bus falls silent (a receive times out), bus
time is carried on from the last frame with a monotonic clock (less a short grace for
frames in flight), so ticks keep coming and inputs can go stale.

When the bus goes away (a socket error, a deleted interface) the loop keeps ticking, so
everything turns stale, and reopens the bus with exponential backoff until it is back.
Each change of state (bus lost, bus back, bus silent, frames again) is logged once, never
once per frame or per attempt; ``/health`` shows the current problem (:attr:`bus_problem`).

The loop supervises itself. Whatever escapes one pass of it (the blocks' own faults never
do: :mod:`cell.runtime.faults`) is logged and counted, and the loop starts again after a
backoff (:attr:`restarts`, :attr:`last_error`). :meth:`problem` says when the loop cannot be
trusted now: its thread has ended, it is waiting to restart, or no MED tick has come for
more than :attr:`stall_s` seconds of wall clock (a step that hangs, a process that was
stopped); the façade then shows every channel ``stale`` with that reason and ``/health``
``failed``. A pass that comes more than :attr:`stall_s` after the one before is counted as a
stall (:attr:`stalls`): after ``SIGSTOP``/``SIGCONT`` the runtime catches up on the frames
the socket kept, and every output frame stamped more than one cycle before the bus time now
(the newest frame's, or the wall clock's estimate of it) is dropped and counted
(:attr:`dropped_stale`), so no stale output reaches the bus.
"""

from __future__ import annotations

import collections
import gc
import logging
import threading
import time

from cell.bus.drops import kernel_drops
from cell.bus.interface import CellBus
from cell.core.errors import BusError
from cell.runtime.faults import describe
from cell.runtime.scheduler import Runtime

log = logging.getLogger(__name__)


def single_threaded_blas() -> None:
    """Limit the BLAS and LAPACK libraries numpy and scipy load to one thread each, for the
    rest of the process (threadpoolctl).

    The blocks work on small matrices (a few states, a gain table's Riccati equations). On
    them OpenBLAS's worker threads do no useful work in parallel, but on a machine whose
    cores are busy every call waits for them to be scheduled: a triangular solve of the SI
    air-path observer's gain table took 15 ms, its 35 Riccati solves 2.6 s in one MED step
    (an 0.9 s stall of the loop), against 0.14 s with one thread.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # not installed: the libraries keep their own thread counts
        log.debug("threadpoolctl is not installed: BLAS keeps its threads")
        return
    threadpool_limits(limits=1, user_api="blas")


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
    #: read the bus one python-can ``recv`` at a time, not in batches (the receive before
    #: :meth:`CellBus.recv_batch`; ``benchmarks/bench_ingest.py`` compares the two)
    per_frame = False

    def __init__(self, runtime: Runtime, bus: CellBus, grace_s: float = 0.05,
                 silent_s: float = 1.0, backoff: Backoff | None = None,
                 stall_periods: float = 3.0, restart_backoff: Backoff | None = None) -> None:
        self.runtime = runtime
        self.bus = bus
        self.grace_s = grace_s
        self.silent_s = silent_s
        self.backoff = backoff or Backoff()
        #: wall seconds without a MED tick after which the loop is stalled
        self.stall_s = stall_periods * runtime.rates.period("MED")
        self.restart_backoff = restart_backoff or Backoff(first=0.1, cap=5.0)
        #: times the loop was started again after something escaped it, and what
        self.restarts = 0
        self.last_error: str | None = None
        self._restart_at: float | None = None
        #: passes of the loop that came more than stall_s after the one before
        self.stalls = 0
        #: (wall seconds, time.time() at its end) of the longest recent stall
        self.last_stall: tuple[float, float] | None = None
        #: output frames not sent for being more than one cycle older than the bus time now
        self.dropped_stale = 0
        self._dropped_times: list[float] = []
        #: drops counted by the kernel on sockets this loop has closed (a reopen starts anew)
        self._drops_before = 0
        self._beat: float | None = None
        self._last_tick_wall: float | None = None
        self._newest: float | None = None  # newest frame time received
        self._limits: dict[tuple[int, bool], float] = {}
        self._drop_samples: collections.deque[tuple[float, int]] = collections.deque(maxlen=120)
        self._next_drop_sample = 0.0
        #: called with the bus time now, once per MED period, while the loop has a problem
        self.stall_listeners: list = []
        self._watchdog: threading.Thread | None = None
        runtime.tick_listeners.append(self._ticked)
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
        single_threaded_blas()
        self._thread = threading.Thread(target=self._run, name="testcell-runtime", daemon=True)
        self._thread.start()
        self._watchdog = threading.Thread(target=self._watch, name="testcell-watchdog", daemon=True)
        self._watchdog.start()
        return self

    def _watch(self) -> None:
        """While :meth:`problem` has something to say, call the stall listeners once per MED
        period with the wall clock's bus time, so that a stream shows every channel stale
        although no tick comes."""
        period = self.runtime.rates.period("MED")
        while not self._stop.wait(period):
            if not self.stall_listeners or self.problem() is None:
                continue
            t = self.estimated_bus_time()
            t = t if t is not None else self.runtime.now
            if t is None:
                continue
            for listener in list(self.stall_listeners):
                try:
                    listener(t)
                except Exception as exc:  # a listener's defect never ends the watch
                    log.debug("stall listener failed: %s", describe(exc))

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

    # -- supervision ------------------------------------------------------------------------
    def problem(self) -> str | None:
        """Why the loop's values cannot be trusted now (``None``: they can; see the module notes)."""
        if self._thread is None:
            return None  # never started: an offline cell
        if not self._thread.is_alive():
            if self._stop.is_set():
                return "the runtime loop has stopped"
            why = f": {self.last_error}" if self.last_error else ""
            return f"the runtime loop has stopped{why}"
        if self._restart_at is not None:
            return (f"the runtime loop failed ({self.last_error}); restart {self.restarts + 1} "
                    f"in {max(0.0, self._restart_at - time.monotonic()):.1f} s")
        if self._anchor is None:
            return None  # no frame yet: no tick is due
        since = self._last_tick_wall if self._last_tick_wall is not None else self._anchor[1]
        quiet = time.monotonic() - since
        if quiet > self.stall_s:
            return f"the runtime loop is stalled: no tick for {quiet:.1f} s (limit {self.stall_s:.2f} s)"
        return None

    def lag_s(self) -> float | None:
        """How far the runtime's bus time is behind the wall clock's estimate of it (seconds)."""
        est, now = self.estimated_bus_time(), self.runtime.now
        if est is None or now is None:
            return None
        return max(0.0, est - now)

    def kernel_drops(self) -> int | None:
        """Datagrams the kernel dropped on this loop's bus socket, as the loop last read them
        (once a second, never in a reader's request); ``None``: not reported."""
        if not self._drop_samples:
            return None
        return self._drops_before + self._drop_samples[-1][1]

    def recent_kernel_drops(self, seconds: float) -> int:
        """Datagrams the kernel dropped over about the last ``seconds`` of wall clock (sampled
        once a second by the loop)."""
        samples = self._drop_samples
        if not samples:
            return 0
        cut = time.monotonic() - seconds
        base = next((n for t, n in samples if t >= cut), samples[-1][1])
        return max(0, samples[-1][1] - base)

    def _sample_drops(self, now: float) -> None:
        if now < self._next_drop_sample:
            return
        self._next_drop_sample = now + 1.0
        n = kernel_drops(self.bus)
        if n is not None:
            self._drop_samples.append((now, n))

    def dropped_stale_since(self, seconds: float) -> int:
        """Stale output frames dropped over the last ``seconds`` of wall clock."""
        cut = time.monotonic() - seconds
        return sum(1 for t in self._dropped_times if t > cut)

    def status(self) -> dict:
        """The loop's part of ``/health``."""
        stall = self.last_stall
        return {"running": self.running, "problem": self.problem(), "restarts": self.restarts,
                "last_error": self.last_error, "stalls": self.stalls,
                "last_stall_s": stall[0] if stall else None,
                "last_stall_end": stall[1] if stall else None,
                "lag_s": self.lag_s(), "dropped_stale": self.dropped_stale,
                "kernel_drops": self.kernel_drops(), "stall_limit_s": self.stall_s}

    def _ticked(self, t: float) -> None:
        self._last_tick_wall = time.monotonic()

    def _run(self) -> None:
        """The thread: the loop, started again (with backoff) after anything escapes it."""
        while not self._stop.is_set():
            try:
                self._loop()
                return
            except BaseException as exc:  # noqa: B036 - nothing may end the cell's loop
                if self._stop.is_set():
                    return
                self.restarts += 1
                self.last_error = describe(exc)
                delay = self.restart_backoff.next()
                log.error("the runtime loop failed (%s); restarting in %.1f s (restart %d)",
                          self.last_error, delay, self.restarts, exc_info=True)
                self._restart_at = time.monotonic() + delay
                self._stop.wait(delay)
                self._restart_at = None
                self._beat = None

    def _heartbeat(self) -> None:
        now = time.monotonic()
        if self._beat is not None and now - self._beat > self.stall_s:
            gap = now - self._beat
            self.stalls += 1
            self.last_stall = (gap, time.time())
            log.warning("the runtime loop was stalled for %.1f s (a paused process, a step that "
                        "hung); outputs older than one cycle are dropped", gap)
        self._beat = now
        self._sample_drops(now)

    # -- the loop ---------------------------------------------------------------------------
    def _loop(self) -> None:
        while not self._stop.is_set():
            self._heartbeat()
            if self.bus_problem is not None:
                self._try_reopen()
                if self.bus_problem is not None:
                    self._tick_silent()
                    self._stop.wait(0.01)
                    continue
            batch: list = []
            failure: BaseException | None = None
            try:
                batch = self._receive(0.01)
            except Exception as exc:  # a broken bus must not kill the cell
                failure = exc
            # a batch short of BATCH emptied the socket: what it holds is the newest
            drained = 0 < len(batch) < self.BATCH
            if batch:
                if self.silent:
                    self.silent = False
                    log.info("frames again on %s", self.bus.spec)
                self.runtime.ingest_many(batch)
                newest = max(m.timestamp for m in batch)
                if self._newest is None or newest > self._newest:
                    self._newest = newest
                # the wall clock's bus time is anchored on a frame that has just arrived: the
                # newest of a batch that emptied the socket (a backlog after a stall is old),
                # or a frame ahead of the estimate (a sender faster than real time)
                est = self.estimated_bus_time()
                if est is None or (drained and newest >= self._anchor[0]) or newest > est:  # type: ignore[index]
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

    def _receive(self, timeout: float) -> list:
        """The frames already queued on the bus (at most :attr:`BATCH`), waiting up to
        ``timeout`` for the first: in one batch read where the bus offers it
        (:meth:`CellBus.recv_batch`), else frame by frame (:attr:`per_frame`)."""
        batch_read = None if self.per_frame else getattr(self.bus, "recv_batch", None)
        if batch_read is not None:
            return batch_read(timeout, self.BATCH)
        batch: list = []
        msg = self.bus.recv(timeout=timeout)
        while msg is not None:
            batch.append(msg)
            if len(batch) >= self.BATCH:
                break
            msg = self.bus.recv(timeout=0.0)
        return batch

    def _tick_silent(self) -> None:
        est = self.estimated_bus_time()
        if est is None:
            return
        self.runtime.advance(est - self.grace_s)
        if not self.silent and time.monotonic() - self._anchor[1] > self.silent_s:  # type: ignore[index]
            self.silent = True
            log.warning("no frame on %s for %.1f s: inputs turn stale", self.bus.spec, self.silent_s)

    def _limit(self, msg) -> float:
        """How old an output frame may be when it is sent: one cycle of its message (its DBC
        cycle time), and never less than one MED period."""
        key = (msg.arbitration_id, bool(msg.is_extended_id))
        limit = self._limits.get(key)
        if limit is None:
            m = self.runtime.db.by_id.get(key)
            cycle = m.cycle_time / 1000.0 if m is not None and m.cycle_time else 0.0
            limit = self._limits[key] = max(cycle, self.runtime.rates.period("MED"))
        return limit

    def _send_outbox(self) -> None:
        est = self.estimated_bus_time()
        now = max(t for t in (est, self._newest) if t is not None) if (
            est is not None or self._newest is not None) else None
        for out in self.runtime.take_outbox():
            if self.bus_problem is not None:
                return  # outputs of a tick without a bus are dropped, not queued
            if now is not None and out.timestamp < now - self._limit(out) - 1e-6:
                self.dropped_stale += 1  # a tick caught up after a stall: too old to send
                self._dropped_times.append(time.monotonic())
                if len(self._dropped_times) > 10_000:
                    del self._dropped_times[:5_000]
                continue
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
        before = kernel_drops(self.bus) or 0
        try:
            self.bus.reopen()
        except Exception as exc:  # still gone: try again later, quietly
            self._retry_at = time.monotonic() + self.backoff.next()
            log.debug("reopening %s failed (attempt %d): %s", self.bus.spec,
                      self.backoff.attempts, exc)
            return
        self.reconnects += 1
        self._drops_before += before
        log.warning("bus %s is back after %d attempt(s)", self.bus.spec, self.backoff.attempts)
        self.bus_problem = None
