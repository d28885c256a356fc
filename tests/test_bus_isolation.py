"""The suite's bus tests pass while another cell runs on the default multicast group.

Other cells run on these machines, on the cell's default group (239.74.163.2, port 43113).
Here one such cell is started (``testcell up --bus udp_multicast``: its simulator floods the
default group), and while it runs, the suite's udp_multicast tests (a two-bus test and the
multi-process cell, with its ``can.logger`` recording) run in a pytest of their own on their
private group, and pass; the private bus hears none of the other cell's frames.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from cell.bus.interface import MULTICAST_GROUP, MULTICAST_PORT, open_bus
from tests.helpers.buses import NOT_ROUTED, private_bus, routed_over_loopback

ROOT = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.multiprocess,
              pytest.mark.skipif(not routed_over_loopback() or not routed_over_loopback(MULTICAST_GROUP),
                                 reason=NOT_ROUTED)]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _frames_on(spec: str, seconds: float) -> int:
    bus = open_bus(spec)
    n, end = 0, time.monotonic() + seconds
    try:
        while time.monotonic() < end:
            if bus.recv(0.05) is not None:
                n += 1
    finally:
        bus.shutdown()
    return n


@pytest.fixture(scope="module")
def other_cell(tmp_path_factory):
    """A cell on the default group, as another user's cell on this machine is."""
    port = _free_port()
    log = tmp_path_factory.mktemp("other") / "up.log"
    with open(log, "w") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "cell", "--log-level", "WARNING", "up", "--bus", "udp_multicast",
             "--port", str(port), "--state", str(log.with_name("tuning.json"))],
            stdout=out, stderr=subprocess.STDOUT, start_new_session=True, cwd=ROOT)
    try:
        end = time.monotonic() + 60
        while time.monotonic() < end:
            assert proc.poll() is None, log.read_text()[-2000:]
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=2) as r:
                    if json.loads(r.read()).get("frames", 0) > 0:
                        break
            except OSError:
                pass
            time.sleep(0.3)
        yield proc
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)


def test_the_other_cell_is_on_the_default_group_and_the_private_bus_hears_none_of_it(other_cell):
    assert _frames_on(f"udp_multicast:{MULTICAST_GROUP}:{MULTICAST_PORT}", 1.0) > 100
    assert _frames_on(private_bus(), 1.0) == 0


def test_the_bus_tests_pass_beside_it(other_cell):
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
         "tests/cell/bus/test_interface.py::test_udp_multicast_between_two_buses_without_echo",
         "tests/test_multiprocess.py::test_filtered_channel_goes_ok_within_seconds",
         "tests/test_multiprocess.py::test_rated_steady_state_mean_tracks_truth"],
        cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert "3 passed" in r.stdout
    assert other_cell.poll() is None  # the other cell ran all along
