"""The simulator child of ``testcell up``, supervised: reaped, reported, restarted or fatal.

:class:`SimSupervisor` starts the simulator process and watches it from a thread blocked in
:meth:`subprocess.Popen.wait`, so a simulator that exits is reaped at once (never left a
zombie) and its end is known: ``simulator exited (code N)`` or ``(signal NAME)``. What
happens next is ``--on-sim-exit``:

- ``restart`` (default): it is started again after a backoff of 1 s, 2 s, 4 s, ... at most
  :data:`BACKOFF_CAP_S`; the backoff starts again from 1 s once a simulator has run for
  :data:`STABLE_S`. ``/health`` names the exit (degraded) until the new one runs.
- ``stop``: the cell stops, and ``testcell up`` exits with :data:`EXIT_SIM_LOST`, so that
  whatever supervises ``up`` (systemd, docker) sees a failure.

``GET /simulator`` shows :meth:`SimSupervisor.status` (``running``, ``pid``, the last exit's
``exit_code`` and ``signal``, ``restarts``).
"""

from __future__ import annotations

import logging
import signal
import subprocess
import threading
import time
from collections.abc import Callable
from typing import Any

from cell.app.live import Backoff

log = logging.getLogger("testcell")

ON_EXIT = ("restart", "stop")
BACKOFF_FIRST_S = 1.0
BACKOFF_CAP_S = 30.0
#: Seconds a simulator must run before its next exit's backoff starts again from the first.
STABLE_S = 30.0
#: ``testcell up``'s exit status when it stopped because its simulator exited (``stop``).
EXIT_SIM_LOST = 3


def describe_exit(returncode: int) -> tuple[int | None, str | None, str]:
    """``(exit code, signal name, text)`` of a :attr:`Popen.returncode` (negative: a signal)."""
    if returncode < 0:
        try:
            name = signal.Signals(-returncode).name
        except ValueError:
            name = f"signal {-returncode}"
        return None, name, f"signal {name}"
    return returncode, None, f"code {returncode}"


def stop_process(proc: subprocess.Popen | None, timeout: float = 5.0) -> None:
    """SIGTERM, then SIGKILL after ``timeout`` s; reaped either way."""
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class SimSupervisor:
    """Start, reap and (as ``on_exit`` says) restart the simulator process.

    Parameters
    ----------
    start:
        Starts one simulator process and returns it.
    on_exit:
        ``"restart"`` or ``"stop"`` (see the module notes).
    on_stop:
        Called once, from the watcher thread, with the reason, when the simulator exited and
        ``on_exit`` is ``"stop"``: it stops the cell.
    backoff:
        Delays between an exit and the restart.
    """

    def __init__(self, start: Callable[[], subprocess.Popen], on_exit: str = "restart",
                 on_stop: Callable[[str], None] | None = None,
                 backoff: Backoff | None = None, stable_s: float = STABLE_S) -> None:
        if on_exit not in ON_EXIT:
            raise ValueError(f"--on-sim-exit must be one of {', '.join(ON_EXIT)}, got {on_exit!r}")
        self._start = start
        self.on_exit = on_exit
        self._on_stop = on_stop
        self.backoff = backoff or Backoff(first=BACKOFF_FIRST_S, cap=BACKOFF_CAP_S)
        self.stable_s = stable_s
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self.proc: subprocess.Popen | None = None
        self._started_at = 0.0
        #: how often the simulator was started again after it exited
        self.restarts = 0
        #: the last exit: its code (``None`` after a signal), its signal's name, its text
        self.exit_code: int | None = None
        self.signal: str | None = None
        self.last_exit: str | None = None
        #: why the simulator is not running now (``None``: it runs)
        self.problem: str | None = None
        #: the reason the cell was stopped for (``on_exit`` ``"stop"``), else ``None``
        self.failed: str | None = None

    # -- life ---------------------------------------------------------------------------
    def start(self) -> SimSupervisor:
        """Start the simulator and its watcher; a failure to start raises here."""
        self.proc = self._start()
        self._started_at = time.monotonic()
        self._thread = threading.Thread(target=self._watch, name="testcell-sim-watch", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the simulator (SIGTERM, then SIGKILL) and the watcher; no restart follows."""
        self._stopping.set()
        with self._lock:
            proc = self.proc
        stop_process(proc, timeout)
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    @property
    def running(self) -> bool:
        proc = self.proc
        return proc is not None and proc.poll() is None

    # -- the watcher --------------------------------------------------------------------
    def _watch(self) -> None:
        while True:
            proc = self.proc
            assert proc is not None
            returncode = proc.wait()  # reaps the child
            if self._stopping.is_set():
                return
            self._exited(proc, returncode)
            if self.on_exit == "stop":
                self.failed = f"{self.problem}; --on-sim-exit stop: stopping the cell"
                log.error("%s", self.failed)
                if self._on_stop is not None:
                    self._on_stop(self.failed)
                return
            if not self._restart():
                return

    def _exited(self, proc: subprocess.Popen, returncode: int) -> None:
        code, name, text = describe_exit(returncode)
        with self._lock:
            self.exit_code, self.signal = code, name
            self.last_exit = f"simulator exited ({text})"
            self.problem = self.last_exit
        log.error("simulator (pid %d) exited (%s)", proc.pid, text)

    def _restart(self) -> bool:
        """Start the simulator again after the backoff; False when stopping meanwhile."""
        if time.monotonic() - self._started_at >= self.stable_s:
            self.backoff.reset()
        while True:
            delay = self.backoff.next()
            with self._lock:
                self.problem = f"{self.last_exit}; restarting in {delay:g} s"
            log.warning("restarting the simulator in %g s", delay)
            if self._stopping.wait(delay):
                return False
            with self._lock:
                if self._stopping.is_set():
                    return False
                try:
                    self.proc = self._start()
                except OSError as exc:
                    self.last_exit = f"{self.last_exit}; restart failed: {exc}"
                    log.error("cannot restart the simulator: %s", exc)
                    continue
                self._started_at = time.monotonic()
                self.restarts += 1
                self.problem = None
            log.warning("simulator restarted (pid %d, restart %d)", self.proc.pid, self.restarts)
            return True

    # -- what the service shows ---------------------------------------------------------
    def status(self) -> dict[str, Any]:
        """``running``, ``pid``, ``restarts``, the last exit (``exit_code``, ``signal``,
        ``last_exit``), ``problem`` and ``on_sim_exit``."""
        with self._lock:
            proc = self.proc
            return {"running": self.running, "pid": proc.pid if proc is not None else None,
                    "restarts": self.restarts, "exit_code": self.exit_code,
                    "signal": self.signal, "last_exit": self.last_exit,
                    "problem": self.problem, "on_sim_exit": self.on_exit}

    def reasons(self) -> list[str]:
        """``/health``'s reasons: the exit while the simulator is not running."""
        with self._lock:
            if self.problem is not None:
                return [self.problem]
        if not self.running and not self._stopping.is_set():
            return ["simulator is not running"]  # exited, not reaped yet: a moment
        return []


__all__ = ["BACKOFF_CAP_S", "BACKOFF_FIRST_S", "EXIT_SIM_LOST", "ON_EXIT", "STABLE_S",
           "SimSupervisor", "describe_exit", "stop_process"]
