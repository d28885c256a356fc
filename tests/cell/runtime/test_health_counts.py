"""Honest health counts: missed cycles of cyclic messages, overruns per minute, and the
kernel's drop count of a UDP socket, each against a count made plainly in the test."""

from __future__ import annotations

import socket
import time

import pytest

from cell.app.cell import Cell
from cell.runtime.blocks import Block

from cell.bus.drops import socket_drops
from cell.estimators.backpressure import native_filters
from cell.runtime.health import HealthCounters
from cell.runtime.scheduler import Runtime


def _run(db, times, blocks=None):
    rt = Runtime(db, native_filters() if blocks is None else blocks)
    for t in times:
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 600.0, "EXH_BP_R": 600.0}, t))
    rt.advance(times[-1])
    return rt.health()["frames_lost"], rt


def test_lost_frames_are_counted_as_missed_cycles(db):
    grid = [round(0.01 * k, 6) for k in range(600)]  # EXH_BP's 10 ms DBC cycle, 6 s
    lost = {50, 51, 52, 300, 420}  # five frames never arrive
    got, rt = _run(db, [t for k, t in enumerate(grid) if k not in lost])
    assert got["missed_cycles"] == len(lost) and got["by_message"] == {"EXH_BP": len(lost)}
    assert got["missed_cycles_last_min"] == len(lost) and got["outages"] == {}
    h = Cell(runtime=rt).health()
    assert h["status"] == "degraded"
    assert h["reasons"] == ["frames lost: 5 missed cycles in the last minute (EXH_BP 5 in all)"]


def test_a_late_sender_that_catches_up_and_a_slow_one_miss_nothing(db):
    late = [round(0.01 * k, 6) for k in range(600)]
    for k in (100, 101, 102, 350):  # due frames delayed by 25 ms and sent in a burst
        late[k] = late[103] if k < 103 else round(late[k] + 0.009, 6)
    assert _run(db, sorted(late))[0]["missed_cycles"] == 0
    slow = [round(0.0106 * k, 6) for k in range(600)]  # 6 % slower than its DBC cycle
    assert _run(db, slow)[0]["missed_cycles"] == 0


def test_a_sender_that_stops_for_seconds_is_an_outage_not_lost_frames(db):
    times = [round(0.01 * k, 6) for k in range(200)] + [round(4.0 + 0.01 * k, 6) for k in range(200)]
    got, _ = _run(db, times)
    assert got["missed_cycles"] == 0 and got["outages"] == {"EXH_BP": 1}


class Slow(Block):
    """A MED block whose step outlasts the 0.1 s MED period."""

    kind = family = "slow"

    def _step(self, t, inputs):
        time.sleep(0.11)
        return {"SLOW_OUT": inputs["EXH_BP_L"]}


def test_more_than_six_overruns_a_minute_degrade_health_naming_them(db):
    _, rt = _run(db, [round(0.01 * k, 6) for k in range(80)], [Slow("slow", ["EXH_BP_L"], ["SLOW_OUT"])])
    assert rt.tick_overruns == 8  # MED ticks 0.0 .. 0.7, each outlasting its period
    h = Cell(runtime=rt).health()
    assert h["tick_overruns_per_min"] == 8 and h["status"] == "degraded"
    assert h["reasons"] == ["tick overruns: 8 in the last minute (limit 6)"]


def test_overruns_per_minute_count_the_last_minute_of_bus_time():
    c = HealthCounters()
    for t in (0.0, 10.0, 50.0, 70.0):
        c.count_overrun(t)
    assert c.tick_overruns == 4
    assert c.overruns_per_minute(75.0) == 2 and c.overruns_per_minute(69.0) == 3  # after 15, after 9
    assert c.overruns_per_minute(200.0) == 0


def test_the_kernels_drop_count_of_a_udp_socket_is_read():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        rx.bind(("127.0.0.1", 0))
        if socket_drops(rx) is None:
            pytest.skip("this platform does not report UDP drops in /proc/net/udp")
        assert socket_drops(rx) == 0
        sent = 500
        for _ in range(sent):  # nobody reads: the small buffer overflows
            tx.sendto(b"x" * 64, rx.getsockname())
        rx.setblocking(False)
        received = 0
        while True:
            try:
                rx.recv(128)
            except BlockingIOError:
                break
            received += 1
        assert received < sent
        assert socket_drops(rx) == sent - received
    finally:
        rx.close()
        tx.close()
    assert socket_drops(rx) is None  # closed
