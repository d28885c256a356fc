"""The live loop is never shown as ok when it is not: a loop that fails is restarted with
backoff and, until it ticks again, every channel reads ``stale`` (in /channels, a channel,
its history and /stream) and /health is ``failed`` with the reason; a stopped loop likewise;
a loop that stalled is counted, and the outputs of the ticks it caught up on never reach the
bus when they are more than one cycle old."""

from __future__ import annotations

import threading
import time

import can
import pytest
from tests.helpers.client import local_client

from cell.app.cell import Cell
from cell.app.live import Backoff, LiveCell
from cell.bus.interface import open_bus
from cell.estimators.backpressure import native_filters
from cell.runtime.blocks import Block
from cell.runtime.scheduler import Runtime
from service.main import create_app


def wait(cond, timeout=10.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return False


class Hang(Block):
    """Passes EXH_BP_L on; its step hangs for ``hang`` seconds once when told to."""

    kind = family = "hang"

    def __init__(self):
        super().__init__("hang", ["EXH_BP_L"], ["HANG_OUT"])
        self.hang = 0.0
        self.returned = None

    def _step(self, t, inputs):
        if self.hang:
            hang, self.hang = self.hang, 0.0
            time.sleep(hang)
            self.returned = time.monotonic()
        return {"HANG_OUT": inputs["EXH_BP_L"]}


class Cellrig:
    """A live cell on a private virtual bus, with a sender of EXH_BP at 100 Hz stamped with
    the wall clock, and a listener recording what the runtime puts on the bus."""

    def __init__(self, db, blocks, **live_options):
        channel = f"live-faults-{time.monotonic_ns()}"
        self.db = db
        self.rt = Runtime(db, blocks)
        self.bus = open_bus(f"virtual:{channel}")
        self.live = LiveCell(self.rt, self.bus, **live_options)
        self.cell = Cell(runtime=self.rt, bus=f"virtual:{channel}", live=self.live)
        self.client = local_client(create_app(self.cell))
        self.tx = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.rx = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.received: list[tuple[float, can.Message]] = []
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._send, daemon=True),
                         threading.Thread(target=self._listen, daemon=True)]

    def _send(self):
        """Frames stamped on an exact 10 ms schedule of the wall clock (as a CAN controller
        sends them), sent when due; a late sender catches up with the frames due."""
        t0, k = time.time(), 0
        while not self._stop.is_set():
            due = t0 + 0.01 * k
            if time.time() < due:
                time.sleep(min(0.005, due - time.time()))
                continue
            self.tx.send(self.db.encode("EXH_BP", {"EXH_BP_L": 600.0, "EXH_BP_R": 610.0}, due))
            k += 1

    def _listen(self):
        while not self._stop.is_set():
            msg = self.rx.recv(0.05)
            if msg is not None and msg.arbitration_id != self.db.message("EXH_BP").frame_id:
                self.received.append((time.time(), msg))

    def __enter__(self):
        for t in self._threads:
            t.start()
        self.live.start()
        assert wait(lambda: self.rt.channels.get("EXH_BP_R_Kalman") is not None
                    and self.rt.channels["EXH_BP_R_Kalman"].status == "ok")
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self.live.stop()
        for t in self._threads:
            t.join(2)
        for b in (self.tx, self.rx):
            b.shutdown()
        self.bus.shutdown()


def test_a_failing_loop_is_restarted_and_meanwhile_every_channel_is_stale(db):
    rig = Cellrig(db, native_filters(), restart_backoff=Backoff(first=0.3, cap=0.6))
    with rig:
        c, rt = rig.client, rig.rt
        assert c.get("/health").json()["status"] == "ok"
        rt.ingest_many = lambda msgs: (_ for _ in ()).throw(RuntimeError("loop defect"))
        assert wait(lambda: rig.live.restarts >= 1 and rig.cell.loop_problem() is not None)
        chans = c.get("/channels").json()
        assert chans and all(ch["status"] == "stale" for ch in chans), chans[:3]
        assert all("RuntimeError: loop defect" in ch["reason"] for ch in chans)
        one = c.get("/channels/EXH_BP_R_Kalman").json()
        assert one["status"] == "stale" and "runtime loop failed" in one["reason"]
        hist = c.get("/channels/EXH_BP_R/history?seconds=5").json()["points"]
        assert hist[-1]["status"] == "stale" and hist[-1]["value"] is None
        h = c.get("/health").json()
        assert h["status"] == "failed" and "runtime loop failed" in h["reasons"][0], h["reasons"]
        assert h["loop"]["last_error"] == "RuntimeError: loop defect" and h["loop"]["restarts"] >= 1
        with c.websocket_connect("/stream?channels=EXH_BP_R,EXH_BP_R_Kalman") as ws:
            assert ws.receive_json()["type"] == "hello"
            assert ws.receive_json()["type"] == "subscribed"
            snap = ws.receive_json()
            assert {v[1] for v in snap["values"].values()} == {"stale"}
            data = ws.receive_json()  # pushed although no tick comes
            assert data["type"] == "data" and {v[1] for v in data["values"].values()} == {"stale"}
        del rt.ingest_many  # the defect goes: the restarted loop ticks again
        assert wait(lambda: c.get("/channels/EXH_BP_R_Kalman").json()["status"] == "ok")
        h = c.get("/health").json()
        assert h["status"] != "failed" and h["loop"]["problem"] is None and h["runtime_running"]


def test_a_stopped_loop_is_failed_and_every_channel_stale(db):
    rig = Cellrig(db, native_filters())
    with rig:
        c = rig.client
        rig.live.stop()
        assert wait(lambda: not rig.live.running)
        chans = c.get("/channels").json()
        assert all(ch["status"] == "stale" and ch["reason"] == "the runtime loop has stopped"
                   for ch in chans)
        h = c.get("/health").json()
        assert h["status"] == "failed" and h["reasons"][0] == "the runtime loop has stopped"
        m = c.get("/metrics").text
        assert "testcell_loop_up 0.0" in m


def test_a_stalled_loop_is_counted_and_no_output_older_than_a_cycle_reaches_the_bus(db):
    hang = Hang()
    rig = Cellrig(db, [*native_filters(), hang])
    with rig:
        assert wait(lambda: len(rig.received) > 20)  # outputs flow
        hang.hang = 1.0  # the loop is stuck in a step for 1 s; frames queue up meanwhile
        assert wait(lambda: rig.live.stalls >= 1, 5)
        assert wait(lambda: rig.live.dropped_stale >= 5, 5)
        time.sleep(0.5)
        h = rig.client.get("/health").json()
    limit = rig.rt.rates.period("MED")
    ages = [(seen - msg.timestamp) for seen, msg in rig.received]
    assert max(ages) < limit + 0.15, sorted(ages)[-5:]  # on main: up to 1 s old after the hang
    assert h["loop"]["stalls"] >= 1 and h["loop"]["last_stall_s"] >= 0.9
    assert h["loop"]["dropped_stale"] >= 5
    assert any("runtime loop stalled" in r for r in h["reasons"]), h["reasons"]
    assert any("stale outputs dropped" in r for r in h["reasons"]), h["reasons"]
    assert h["status"] == "degraded"


def test_while_a_step_hangs_readers_answer_at_once_all_stale_and_health_failed(db):
    hang = Hang()
    rig = Cellrig(db, [*native_filters(), hang])
    with rig:
        c = rig.client
        c.get("/channels")
        c.get("/health")
        hang.hang = 1.5  # the loop holds the runtime's lock in this step
        assert wait(lambda: rig.cell.loop_problem() is not None, 3)
        chans = c.get("/channels").json()
        one = c.get("/channels/EXH_BP_R").json()
        h = c.get("/health").json()
        answered = time.monotonic()
        assert wait(lambda: rig.cell.loop_problem() is None, 10)  # the step returned
    assert answered < hang.returned  # answered while the step still hung
    assert one["status"] == "stale" and one["name"] == "EXH_BP_R"
    assert chans and all(ch["status"] == "stale" and "stalled" in ch["reason"] for ch in chans)
    assert h["status"] == "failed" and "stalled" in h["reasons"][0]


def test_lag_and_kernel_drops_are_reported_as_the_bus_allows(db):
    rig = Cellrig(db, native_filters())
    with rig:
        loop = rig.client.get("/health").json()["loop"]
    assert loop["kernel_drops"] is None  # a virtual bus has no kernel socket: not available
    assert loop["lag_s"] is not None and 0.0 <= loop["lag_s"] < 0.5
    assert loop["stall_limit_s"] == pytest.approx(0.3)
