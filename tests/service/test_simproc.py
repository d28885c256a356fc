"""testcell up's simulator child, supervised: reaped when it exits (never a zombie), its exit
(code or signal) reported, restarted with backoff or the cell stopped. A stand-in child (a
sleeping Python) is enough to prove the supervision; tests/test_up_supervised.py does it
with the real simulator under ``up``."""

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from cell.app.live import Backoff
from service.simproc import SimSupervisor, describe_exit


def child(code: str = "import time; time.sleep(60)") -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", code])


def wait(cond, timeout=10.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return False


def is_zombie(pid: int) -> bool:
    stat = Path(f"/proc/{pid}/stat")
    return stat.exists() and stat.read_text().rsplit(")", 1)[1].split()[0] == "Z"


def test_exits_are_described_by_code_or_signal_name():
    assert describe_exit(0) == (0, None, "code 0")
    assert describe_exit(7) == (7, None, "code 7")
    assert describe_exit(-9) == (None, "SIGKILL", "signal SIGKILL")


def test_a_killed_child_is_reaped_reported_and_restarted_with_backoff():
    starts = []

    def start():
        starts.append(time.monotonic())
        return child()

    sup = SimSupervisor(start, backoff=Backoff(first=0.2, cap=0.4)).start()
    try:
        first = sup.proc.pid
        assert sup.status()["running"] and sup.reasons() == []
        os.kill(first, signal.SIGKILL)
        assert wait(lambda: sup.problem is not None)
        st = sup.status()
        assert st["signal"] == "SIGKILL" and st["exit_code"] is None
        assert "simulator exited (signal SIGKILL)" in sup.reasons()[0]
        assert not is_zombie(first) and not Path(f"/proc/{first}").exists()  # reaped
        assert wait(lambda: sup.restarts == 1 and sup.running)
        assert sup.proc.pid != first and sup.reasons() == []
        assert sup.status()["last_exit"] == "simulator exited (signal SIGKILL)"
        os.kill(sup.proc.pid, signal.SIGKILL)  # again: the backoff doubles
        assert wait(lambda: sup.restarts == 2 and sup.running)
        gaps = [b - a for a, b in zip(starts, starts[1:])]
        assert gaps[1] >= 0.4 > 0.2 <= gaps[0]
    finally:
        sup.stop()
    assert not sup.running and sup.restarts == 2  # a stop is not an exit to restart after


def test_with_stop_an_exit_stops_the_cell_with_the_exit_code():
    stopped = threading.Event()
    reasons = []

    def on_stop(reason):
        reasons.append(reason)
        stopped.set()

    sup = SimSupervisor(lambda: child("import sys, time; time.sleep(0.2); sys.exit(7)"),
                        on_exit="stop", on_stop=on_stop).start()
    try:
        assert stopped.wait(10)
        assert sup.failed is not None and "simulator exited (code 7)" in reasons[0]
        assert "--on-sim-exit stop" in reasons[0]
        assert sup.status()["exit_code"] == 7 and sup.restarts == 0
        time.sleep(0.3)
        assert sup.restarts == 0 and not sup.running
    finally:
        sup.stop()


def test_a_bad_choice_is_refused_by_name():
    with pytest.raises(ValueError, match="--on-sim-exit must be one of restart, stop"):
        SimSupervisor(child, on_exit="ignore")
