"""Two cells on one machine are isolated by multicast group and by port, and a clean stop
logs no error. These use udp_multicast on the test process's own group and port and their
neighbours (:mod:`tests.helpers.buses`, never the cell's default), so they do not meet other
cells on this machine."""

import json
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import can
import pytest

from cell.bus.interface import BusSpec, open_bus, resolve
from cell.core.errors import BusError
from tests.helpers.buses import private_group

#: this test process's private group and port, and a neighbour of each
GROUP_A, PORT_A = private_group()
GROUP_B = GROUP_A.rsplit(".", 1)[0] + "." + str(int(GROUP_A.rsplit(".", 1)[1]) + 1)
PORT_B = PORT_A + 1


def test_bus_spec_takes_a_port():
    assert resolve("udp_multicast:239.1.2.3:43200", env={}) == BusSpec("udp_multicast", "239.1.2.3", 43200)
    assert resolve("udp_multicast:239.1.2.3", env={}) == BusSpec("udp_multicast", "239.1.2.3")
    assert resolve("udp_multicast:[ff15::7]:43200", env={}) == BusSpec("udp_multicast", "ff15::7", 43200)
    assert str(BusSpec("udp_multicast", "239.1.2.3", 43200)) == "udp_multicast:239.1.2.3:43200"
    assert resolve(str(BusSpec("udp_multicast", "ff15::7", 43200)), env={}).port == 43200
    env = {"CAN_INTERFACE": "udp_multicast", "CAN_CHANNEL": "239.1.2.3:43201"}
    assert resolve(None, env=env) == BusSpec("udp_multicast", "239.1.2.3", 43201)
    for bad, why in (("udp_multicast:239.1.2.3:port", "not a number"),
                     ("udp_multicast:239.1.2.3:80", "1024..65535")):
        with pytest.raises(BusError, match=why):
            resolve(bad, env={})


def _drain(bus, seconds=0.3):
    got, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        m = bus.recv(0.05)
        if m is not None:
            got.append(m.arbitration_id)
    return got


def _send(group, port, arb_id):
    with can.Bus(interface="udp_multicast", channel=group, port=port) as tx:
        for _ in range(3):
            tx.send(can.Message(arbitration_id=arb_id, data=b"\x01" * 8, is_extended_id=False))
            time.sleep(0.02)


def test_cells_on_other_groups_or_ports_do_not_hear_each_other():
    a = open_bus(f"udp_multicast:{GROUP_A}:{PORT_A}")
    b = open_bus(f"udp_multicast:{GROUP_B}:{PORT_A}")  # same port, other group
    c = open_bus(f"udp_multicast:{GROUP_A}:{PORT_B}")  # same group, other port
    try:
        _drain(a, 0.1), _drain(b, 0.1), _drain(c, 0.1)
        _send(GROUP_B, PORT_A, 0x222)
        assert 0x222 not in _drain(a) and 0x222 in _drain(b)
        _send(GROUP_A, PORT_B, 0x333)
        assert 0x333 not in _drain(a) and 0x333 in _drain(c)
        _send(GROUP_A, PORT_A, 0x111)
        got_a = _drain(a)
        assert 0x111 in got_a and 0x111 not in _drain(b) and 0x111 not in _drain(c)
    finally:
        for bus in (a, b, c):
            bus.shutdown()


def test_sigterm_on_up_no_sim_stops_without_an_error(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "cell", "up", "--no-sim", "--bus",
                             f"udp_multicast:{GROUP_A}:{PORT_A}", "--port", str(port),
                             "--state", str(tmp_path / "t.json")],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline, up = time.monotonic() + 30, False
        while time.monotonic() < deadline and not up:
            time.sleep(0.3)
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=2) as r:
                    up = json.loads(r.read())["status"] == "waiting"
            except OSError:
                pass
        assert up
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0, out
    assert " ERROR " not in out and "Bad file descriptor" not in out and "Traceback" not in out, out
