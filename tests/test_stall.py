"""SIGSTOP for 5 s, then SIGCONT, of a runtime process (``testcell up --no-sim``) on a private
group, fed by a sender of the test's own: no output frame older than one cycle reaches the
bus after the stall (each frame carries the bus time of the tick that made it, read here
from the datagram, against the wall time it arrived), and ``/health`` reports the stall."""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import urllib.request

import can
import pytest

from cell.bus.dbc import load
from tests.helpers.buses import NOT_ROUTED, private_bus, private_group, routed_over_loopback

pytestmark = [pytest.mark.slow, pytest.mark.multiprocess]

if not routed_over_loopback():
    pytest.skip(NOT_ROUTED, allow_module_level=True)

BUS = private_bus()
GROUP, PORT = private_group()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get(url: str):
    try:
        with urllib.request.urlopen(url, timeout=3) as r:
            return json.loads(r.read())
    except OSError:
        return None


class Capture(threading.Thread):
    """Every datagram on the group, unpacked with its sender's timestamp, and when it came."""

    def __init__(self):
        super().__init__(daemon=True)
        from can.interfaces.udp_multicast.utils import unpack_message

        self.unpack = unpack_message
        self.frames: list[tuple[float, can.Message]] = []
        self.stop = threading.Event()
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        s.bind(("", PORT))
        s.setsockopt(socket.IPPROTO_IP, 49, 0)  # IP_MULTICAST_ALL off: this group only
        s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                     socket.inet_aton(GROUP) + struct.pack("@I", socket.INADDR_ANY))
        s.settimeout(0.1)
        self.sock = s

    def run(self):
        while not self.stop.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            self.frames.append((time.time(), self.unpack(data)))


def test_no_stale_output_reaches_the_bus_after_sigstop_and_health_reports_the_stall(tmp_path):
    db = load()
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    log = open(tmp_path / "up.log", "w")
    up = subprocess.Popen([sys.executable, "-m", "cell", "--log-level", "WARNING", "up", "--no-sim",
                           "--bus", BUS, "--port", str(port), "--state", str(tmp_path / "tuning.json")],
                          stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    tx = can.Bus(interface="udp_multicast", channel=GROUP, port=PORT, receive_own_messages=False)
    cap = Capture()
    stop = threading.Event()

    def send():
        t0, k = time.time(), 0
        while not stop.is_set():
            due = t0 + 0.01 * k
            if time.time() < due:
                time.sleep(min(0.005, due - time.time()))
                continue
            tx.send(db.encode("EXH_BP", {"EXH_BP_L": 600.0, "EXH_BP_R": 610.0}, due))
            k += 1

    sender = threading.Thread(target=send, daemon=True)
    out_id = db.message("BP_FILT_R").frame_id
    try:
        end = time.monotonic() + 30
        while _get(base + "/health") is None:
            assert up.poll() is None and time.monotonic() < end, (tmp_path / "up.log").read_text()
            time.sleep(0.2)
        cap.start()
        sender.start()
        end = time.monotonic() + 15
        while not any(m.arbitration_id == out_id for _, m in cap.frames):
            assert time.monotonic() < end, "no filter output on the bus"
            time.sleep(0.1)
        time.sleep(1.0)
        os.kill(up.pid, signal.SIGSTOP)
        stopped = time.time()
        time.sleep(5.0)
        os.kill(up.pid, signal.SIGCONT)
        time.sleep(2.0)
        h = _get(base + "/health")
    finally:
        stop.set()
        sender.join(2)
        cap.stop.set()
        cap.join(2)
        cap.sock.close()
        tx.shutdown()
        os.kill(up.pid, signal.SIGCONT)
        up.send_signal(signal.SIGTERM)
        try:
            up.wait(20)
        finally:
            try:
                os.killpg(up.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            log.close()
    outputs = [(seen, m) for seen, m in cap.frames if m.arbitration_id == out_id]
    after = [(seen, m) for seen, m in outputs if seen > stopped + 5.0]
    assert len(after) >= 10, "the runtime did not publish again after SIGCONT"
    cycle = 0.1  # BP_FILT_R's DBC cycle, one MED period
    ages = sorted(seen - m.timestamp for seen, m in outputs)
    print(f"\n  {len(outputs)} BP_FILT_R frames, {len(after)} after SIGCONT; oldest on arrival "
          f"{ages[-1] * 1000:.1f} ms; health: {h and h['loop']}")
    # on main: a burst of the ticks caught up after SIGCONT, up to 5 s old
    assert ages[-1] < cycle + 0.4, ages[-10:]  # one cycle, and what a loaded machine adds
    assert h is not None and h["loop"]["stalls"] >= 1 and h["loop"]["last_stall_s"] >= 4.5, h["loop"]
    # the ticks caught up from the socket's 5 s backlog made outputs, dropped instead of sent
    # (how many depends on how the backlog arrives in batches)
    assert h["loop"]["dropped_stale"] >= 1
    assert h["loop"]["kernel_drops"] is not None  # udp_multicast on Linux reports them
    assert any("runtime loop stalled" in r for r in h["reasons"]), h["reasons"]
    assert h["status"] == "degraded"
