"""The live loop: silence turns inputs stale and is logged once; a bus that goes away is
reopened with backoff (logged once per change of state); a stop never logs an error."""

import logging
import time

import can
import pytest

from cell.bus.interface import BusSpec, CellBus, open_bus
from cell.estimators.backpressure import native_filters
from cell.app.live import Backoff, LiveCell
from cell.runtime.scheduler import Runtime
from tests.helpers.buses import NOT_ROUTED, private_bus, private_group, routed_over_loopback


def wait(cond, timeout=10.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.01)
    return False


def test_backoff_doubles_up_to_its_cap():
    b = Backoff(first=0.1, cap=1.0)
    assert [b.next() for _ in range(6)] == pytest.approx([0.1, 0.2, 0.4, 0.8, 1.0, 1.0])
    b.reset()
    assert b.next() == 0.1


class ClosingBus:
    """A bus closed under the loop while it stops (what SIGTERM did to ``up --no-sim``)."""

    def __init__(self, live_ref):
        self.live_ref = live_ref

    def recv(self, timeout=None):
        self.live_ref[0]._stop.set()
        raise OSError(9, "Bad file descriptor")

    def send(self, msg):
        pass

    def shutdown(self):
        pass


def test_a_bus_closed_while_stopping_logs_no_error(db, caplog):
    ref = []
    live = LiveCell(Runtime(db, native_filters()), CellBus(ClosingBus(ref), BusSpec("virtual", "x")))
    ref.append(live)
    with caplog.at_level(logging.DEBUG, logger="cell.app.live"):
        live.start()
        assert wait(lambda: not live.running)
    assert [r for r in caplog.records if r.levelno >= logging.WARNING] == []


def test_bus_going_away_is_reopened_with_backoff_and_logged_once_per_change(db, caplog):
    channel = f"live-{time.monotonic_ns()}"
    rt = Runtime(db, native_filters())
    bus = open_bus(f"virtual:{channel}")
    live = LiveCell(rt, bus, silent_s=0.3, backoff=Backoff(first=0.1, cap=0.4))
    tx = can.Bus(interface="virtual", channel=channel)
    t0 = time.time()

    def send(n):
        for _ in range(n):
            tx.send(db.encode("EXH_BP", {"EXH_BP_L": 600.0, "EXH_BP_R": 600.0}, time.time() - t0))
            time.sleep(0.005)

    with caplog.at_level(logging.INFO, logger="cell.app.live"):
        live.start()
        try:
            send(100)
            assert wait(lambda: rt.channels.get("EXH_BP_R_Kalman") is not None
                        and rt.channels["EXH_BP_R_Kalman"].status == "ok")
            # the bus goes away under the loop (a socket error, a deleted interface)
            broken = bus.bus
            broken.recv = lambda timeout=None: (_ for _ in ()).throw(OSError(19, "No such device"))
            reopen = bus.reopen
            attempts = []

            def flaky_reopen():  # the interface is back only at the third attempt
                attempts.append(time.monotonic())
                if len(attempts) < 3:
                    raise can.CanInitializationError("no such device")
                reopen()

            bus.reopen = flaky_reopen
            assert wait(lambda: live.bus_problem is not None)
            assert wait(lambda: rt.channels["EXH_BP_R"].status_at(rt.now)[0] == "stale")
            assert wait(lambda: rt.channels["EXH_BP_R_Kalman"].status == "stale")
            assert wait(lambda: live.bus_problem is None and live.reconnects == 1)
            gaps = [b - a for a, b in zip(attempts, attempts[1:])]
            assert gaps[1] > gaps[0] * 1.5  # backoff grows
            send(100)  # frames return: everything derived turns ok again
            assert wait(lambda: rt.channels["EXH_BP_R_Kalman"].status == "ok")
        finally:
            live.stop()
            bus.shutdown()
            tx.shutdown()
    msgs = [r.getMessage() for r in caplog.records]
    assert sum("reconnecting" in m for m in msgs) == 1, msgs
    assert sum("is back after 3 attempt" in m for m in msgs) == 1, msgs
    # each silence is logged once when it starts and once when frames return (a loaded
    # machine may pause the sender too, which is a silence of its own)
    silences = sum("inputs turn stale" in m for m in msgs)
    assert silences >= 1 and sum("frames again" in m for m in msgs) == silences, msgs
    assert len(msgs) == 2 + 2 * silences, msgs


@pytest.mark.skipif(not routed_over_loopback(), reason=NOT_ROUTED)
def test_a_garbage_datagram_is_counted_and_the_loop_runs_on(db):
    """21 bytes of non-msgpack on the group used to make python-can's receive raise, which
    the loop took for a lost bus ("bus lost", reopen, "bus silent" for ever)."""
    import socket

    from cell.app.cell import Cell

    group, port = private_group()
    rt = Runtime(db, native_filters())
    bus, tx = open_bus(private_bus()), open_bus(private_bus())
    live = LiveCell(rt, bus)
    cell = Cell(runtime=rt, bus=private_bus(), live=live)
    t0 = time.time()
    live.start()
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
            for i in range(60):
                if i % 20 == 0:
                    s.sendto(b"\xc1" * 21, (group, port))
                tx.send(db.encode("EXH_BP", {"EXH_BP_L": 600.0, "EXH_BP_R": 600.0 + i},
                                  time.time() - t0))
                time.sleep(0.005)
        assert wait(lambda: live.undecodable == 3 and rt.channels.get("EXH_BP_R") is not None
                    and rt.channels["EXH_BP_R"].value == 659.0)
        health = cell.health()
        assert health["undecodable"] == 3
        assert live.running and live.bus_problem is None and live.reconnects == 0
        assert not any("lost" in r for r in health["reasons"]), health["reasons"]
    finally:
        live.stop()
        bus.shutdown()
        tx.shutdown()
