"""testcell up supervises its simulator process: ``kill -9`` of the simulator is named in
``/health`` within 2 s and, with ``--on-sim-exit restart`` (the default), the simulator is
back within 10 s; with ``--on-sim-exit stop`` up exits non-zero. Real processes on this test
process's private multicast group."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from service.simproc import EXIT_SIM_LOST
from tests.helpers.buses import NOT_ROUTED, private_bus, routed_over_loopback

pytestmark = [pytest.mark.slow, pytest.mark.multiprocess,
              pytest.mark.skipif(not routed_over_loopback(), reason=NOT_ROUTED)]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Up:
    def __init__(self, tmp: Path, *args: str):
        self.port = _free_port()
        self.log_path = tmp / f"up-{self.port}.log"
        self.log = open(self.log_path, "w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "cell", "--log-level", "WARNING", "up", "--bus", private_bus(),
             "--port", str(self.port), "--state", str(tmp / "tuning.json"), *args],
            stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)

    def get(self, path: str):
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{self.port}{path}", timeout=2) as r:
                return json.loads(r.read())
        except (urllib.error.URLError, ConnectionError, OSError, ValueError):
            return None

    def wait(self, cond, timeout: float, what: str) -> float:
        start = end = time.monotonic()
        end += timeout
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise AssertionError(f"up exited ({self.proc.returncode}) waiting for {what}:\n"
                                     f"{self.log_path.read_text()[-3000:]}")
            try:
                if cond():
                    return time.monotonic() - start
            except (KeyError, TypeError):
                pass
            time.sleep(0.05)
        raise AssertionError(f"timed out after {timeout} s waiting for {what}:\n"
                             f"{self.log_path.read_text()[-3000:]}")

    def close(self) -> None:
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)  # up and whatever simulator it has
        except ProcessLookupError:
            pass
        self.proc.wait(10)
        self.log.close()


def _ok(up: Up) -> bool:
    h = up.get("/health")
    return h is not None and h["status"] == "ok" and h["frames_per_s"] > 0


def test_a_killed_simulator_is_named_within_2_s_and_back_within_10_s(tmp_path):
    up = Up(tmp_path)
    try:
        up.wait(lambda: (up.get("/simulator") or {}).get("pid") is not None
                and up.get("/health") is not None, 40, "the API and the simulator")
        sim = up.get("/simulator")
        assert sim["running"] and sim["restarts"] == 0 and sim["on_sim_exit"] == "restart"
        os.kill(sim["pid"], signal.SIGKILL)
        named = up.wait(lambda: any("simulator exited (signal SIGKILL)" in r
                                    for r in up.get("/health")["reasons"]), 5, "/health naming it")
        assert named < 2.0, named
        h = up.get("/health")
        assert h["status"] == "degraded" and h["simulator"]["signal"] == "SIGKILL"
        down = up.get("/simulator")
        assert down["signal"] == "SIGKILL" and down["exit_code"] is None
        back = up.wait(lambda: up.get("/simulator")["restarts"] == 1
                       and up.get("/simulator")["running"], 10, "the simulator process back")
        assert back < 10.0, back
        again = up.get("/simulator")
        assert again["pid"] != sim["pid"] and "SIGKILL" in again["last_exit"]
        # its frames follow once the new process has loaded (seconds on a loaded machine)
        up.wait(lambda: _ok(up), 40, "frames from the restarted simulator")
    finally:
        up.close()


def test_with_stop_a_killed_simulator_stops_up_non_zero(tmp_path):
    up = Up(tmp_path, "--on-sim-exit", "stop")
    try:
        up.wait(lambda: (up.get("/simulator") or {}).get("pid") is not None
                and up.get("/health") is not None, 40, "the API and the simulator")
        os.kill(up.get("/simulator")["pid"], signal.SIGKILL)
        rc = up.proc.wait(15)
        assert rc == EXIT_SIM_LOST != 0
        assert "simulator exited (signal SIGKILL)" in up.log_path.read_text()
    finally:
        up.close()
