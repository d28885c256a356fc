"""The `testcell sim` process on a private udp_multicast group: a garbage datagram does not stop
it, and it does not outlive its parent (kill -9 of the parent: safe state on the bus within
0.5 s, exit within 5 s). Slow: each test starts processes."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cell.bus.dbc import load
from cell.bus.interface import open_bus
from cell.sim.simulator import SAFE_PARENT_LOST
from tests.helpers.buses import NOT_ROUTED, private_bus, private_group, routed_over_loopback

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not routed_over_loopback(), reason=NOT_ROUTED)]

PY = sys.executable
ROOT = Path(__file__).resolve().parents[3]
DB = load()


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT)}


def _frames(bus, seconds: float):
    """``(receive time, message name, values)`` of the DBC frames for ``seconds``."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            msg = bus.recv(timeout=0.05)
        except Exception:  # the garbage datagram reaches this peer too
            continue
        if msg is None:
            continue
        try:
            message, values = DB.decode(msg)
        except ValueError:
            continue
        yield time.monotonic(), message.name, values


def _exited(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return True
    return state in ("Z", "X")  # a zombie has exited; its new parent reaps it


def test_a_garbage_datagram_is_counted_and_the_simulator_keeps_running(tmp_path):
    spec = private_bus()
    group, port = private_group()
    log = open(tmp_path / "sim.log", "w")
    proc = subprocess.Popen([PY, "-m", "cell", "sim", "--bus", spec, "--duration", "60"],
                            stdout=log, stderr=subprocess.STDOUT, env=_env(),
                            stdin=subprocess.DEVNULL)
    try:
        with open_bus(spec) as peer:
            first = next((v for _, n, v in _frames(peer, 40.0) if n == "SIM_STATUS"), None)
            assert first is not None, (tmp_path / "sim.log").read_text()
            assert first["SIM_UNDECODABLE"] == 0
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
            sock.sendto(b"\xc1" * 21, (group, port))  # 0xc1 is never valid msgpack
            sock.close()
            counted = [v["SIM_UNDECODABLE"] for _, n, v in _frames(peer, 1.5) if n == "SIM_STATUS"]
            later = [n for _, n, _ in _frames(peer, 0.5)]
        assert counted and counted[-1] == 1, (tmp_path / "sim.log").read_text()
        assert "EXH_BP" in later and proc.poll() is None  # still sending, still running
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        log.close()
    assert "undecodable datagram" in (tmp_path / "sim.log").read_text()  # the bus wrapper skips and logs it


PARENT = """
import subprocess, sys, time
p = subprocess.Popen([sys.executable, "-m", "cell", "sim", *sys.argv[1:]],
                     stdin=subprocess.DEVNULL)
print(p.pid, flush=True)
time.sleep(120)
"""


def test_kill_9_of_the_parent_makes_the_simulator_safe_then_exit(tmp_path):
    spec = private_bus()
    script = tmp_path / "parent.py"
    script.write_text(PARENT)
    log = open(tmp_path / "sim.log", "w")
    # the transient cycle starts at rated speed: the safe state's idle is a change to see
    parent = subprocess.Popen([PY, str(script), "--bus", spec, "--duty", "transient", "--speed", "5",
                               "--valve", "21"], stdout=subprocess.PIPE, stderr=log, text=True,
                              env=_env(), stdin=subprocess.DEVNULL)
    sim_pid = int(parent.stdout.readline())
    try:
        with open_bus(spec) as peer:
            speed = 0.0
            for _, name, v in _frames(peer, 30.0):
                if name == "ENGINE_1":
                    speed = v["ENGINE_SPEED"]
                    if speed > 1500.0:  # running, near rated
                        break
            assert speed > 1500.0, (tmp_path / "sim.log").read_text()
            os.kill(parent.pid, signal.SIGKILL)
            killed = time.monotonic()
            parent.wait(timeout=5)
            safe_at, speeds, valves = None, [], []
            for t, name, v in _frames(peer, 2.5):
                if name == "SIM_STATUS" and v["SAFE_STATE"] == SAFE_PARENT_LOST and safe_at is None:
                    safe_at = t
                if safe_at is not None and name == "ENGINE_1":
                    speeds.append(v["ENGINE_SPEED"])
                if safe_at is not None and name == "TRUTH_ENGINE":
                    valves.append(v["VALVE_POS_L_TRUE"])
        assert safe_at is not None and safe_at - killed < 0.5, (tmp_path / "sim.log").read_text()
        # the engine runs down to idle, the valve opens (5 %/s of simulation time)
        assert speeds[-1] < speeds[0] - 100.0 and speeds[-1] > 590.0
        assert valves[-1] > valves[0] + 20.0
        deadline = killed + 5.0
        while not _exited(sim_pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _exited(sim_pid), "the simulator outlived its parent by 5 s"
    finally:
        if not _exited(sim_pid):
            os.kill(sim_pid, signal.SIGKILL)
        if parent.poll() is None:
            parent.kill()
        log.close()
    assert "parent process" in (tmp_path / "sim.log").read_text()
