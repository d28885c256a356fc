"""The cell's façade (:class:`cell.app.cell.Cell`): what it answers is what its runtime holds,
every method waits for the runtime's lock, and commands land in the runtime's outbox."""

from __future__ import annotations

import math
import threading

import pytest

from cell.app.cell import Cell
from cell.bus.scenario import scenario_frames
from cell.core import registry
from cell.core.errors import UnknownBlockError
from cell.core.registry import BlockFamily
from cell.estimators.backpressure import native_filters
from cell.runtime.scheduler import Runtime
from cell.core.errors import ParamError
from cell.runtime.supervision import CONFIRM_SIGNAL, REQUEST_SIGNAL


def feed(rt, db, t0, t1):
    t = t0
    while t < t1 - 1e-9:
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 680.0, "EXH_BP_R": 680.0 + 10 * math.sin(t)}, t))
        t = round(t + 0.01, 6)
    rt.advance(t1 - 0.01)


@pytest.fixture
def cell(db):
    rt = Runtime(db, native_filters())
    feed(rt, db, 0.0, 5.0)
    return Cell(runtime=rt, bus="virtual:test")


def waits_for_the_lock(rt, call) -> bool:
    """Whether ``call()`` waits while another thread holds the runtime's lock (and then
    returns once it is released)."""
    held, release, done = threading.Event(), threading.Event(), threading.Event()

    def hold():
        with rt.lock:
            held.set()
            release.wait(5)

    def run():
        call()
        done.set()

    holder = threading.Thread(target=hold)
    holder.start()
    assert held.wait(5)
    worker = threading.Thread(target=run)
    worker.start()
    waited = not done.wait(0.2)
    release.set()
    holder.join(5)
    assert done.wait(5), "the call never returned"
    worker.join(5)
    return waited


CALLS = {
    "now": lambda c: c.now,
    "bus_time": lambda c: c.bus_time(),
    "snapshot": lambda c: c.snapshot(),
    "channel": lambda c: c.channel("EXH_BP_R"),
    "channel_names": lambda c: c.channel_names(),
    "describe_channels": lambda c: c.describe_channels(["EXH_BP_R"]),
    "history": lambda c: c.history("EXH_BP_R", 1.0),
    "readings": lambda c: c.readings(["EXH_BP_R"]),
    "on_tick": lambda c: c.on_tick(lambda t: None),
    "families": lambda c: c.families(),
    "names": lambda c: c.names("filter"),
    "block": lambda c: c.block("filter", "EXH_BP_R_Kalman"),
    "blocks": lambda c: c.blocks("filter"),
    "tune": lambda c: c.tune("filter", "EXH_BP_R_MAF", {"samples": 20}),
    "send": lambda c: c.send([]),
    "trip": lambda c: c.trip(),
    "reset_trip": lambda c: c.reset_trip(),
    "confirm_reset": lambda c: c.confirm_reset(c.reset_trip()["challenge"]),
    "health": lambda c: c.health(),
    "frames_by_id": lambda c: c.frames_by_id(),
    "metrics": lambda c: c.metrics(),
}


@pytest.mark.parametrize("name", sorted(CALLS))
def test_every_method_takes_the_runtime_lock_itself(cell, name):
    assert waits_for_the_lock(cell.runtime, lambda: CALLS[name](cell))


def test_send_scenario_takes_the_lock(db):
    rt = Runtime(db)
    c = Cell(runtime=rt)
    assert waits_for_the_lock(rt, lambda: c.send_scenario({"osc": 0.5}))


def test_snapshot_channel_and_history_are_the_runtimes_channels(cell):
    rt = cell.runtime
    snap = cell.snapshot()
    assert snap == rt.snapshot()
    assert [s["name"] for s in snap] == sorted(rt.channels) == cell.channel_names()
    for s in snap:
        ch = rt.channels[s["name"]]
        assert (s["value"], s["unit"], s["time"], s["source"]) == (ch.value, ch.unit, ch.t, ch.source)
        assert cell.channel(s["name"]) == s
    assert cell.history("EXH_BP_R_Kalman", 2.0) == rt.history("EXH_BP_R_Kalman", 2.0)
    assert len(cell.history("EXH_BP_R_Kalman", 2.0)) == 20  # MED ticks of the last 2 s
    assert cell.describe_channels(["EXH_BP_R_MAF", "NOPE", "EXH_BP_L"]) == [
        {"name": "EXH_BP_R_MAF", "unit": "mmH2O", "source": "EXH_BP_R_MAF"},
        {"name": "EXH_BP_L", "unit": "mmH2O", "source": "bus"}]
    with pytest.raises(UnknownBlockError, match="NOPE"):
        cell.channel("NOPE")
    with pytest.raises(UnknownBlockError, match="NOPE"):
        cell.history("NOPE", 1.0)


def test_readings_are_value_status_and_time_at_a_bus_time(cell):
    rt = cell.runtime
    now, values = cell.readings()
    assert now == rt.now and set(values) == set(rt.channels)
    ch = rt.channels["EXH_BP_R"]
    assert values["EXH_BP_R"] == (ch.value, "ok", ch.t)
    # ten seconds on, without frames, a bus input has gone stale; a block output keeps its mark
    later, some = cell.readings(["EXH_BP_R", "EXH_BP_R_Kalman", "NOPE"], at=rt.now + 10.0)
    assert later == rt.now + 10.0 and set(some) == {"EXH_BP_R", "EXH_BP_R_Kalman"}
    assert some["EXH_BP_R"] == (ch.value, "stale", ch.t)
    assert some["EXH_BP_R_Kalman"][1] == "ok"


def test_send_puts_the_frames_in_the_outbox(cell, db):
    rt = cell.runtime
    rt.take_outbox()
    frames = [db.encode("ENGINE_CMD", {REQUEST_SIGNAL: 7, CONFIRM_SIGNAL: 0}, 1.0)]
    cell.send(frames)
    assert rt.take_outbox() == frames


def test_send_scenario_encodes_at_the_bus_time_and_sends(db):
    rt = Runtime(db)
    feed(rt, db, 0.0, 1.0)
    c = Cell(runtime=rt)
    sent = c.send_scenario({"osc": 0.5})
    out = rt.take_outbox()
    expect = scenario_frames(db, {"osc": 0.5}, rt.now)

    def payload(m):  # the E2E counter differs from frame to frame, so the CRC does too
        message, values = db.decode(m)
        return m.arbitration_id, m.timestamp, {k: values[k] for k in db.payload_signals(message)}
    assert [payload(m) for m in out] == [payload(m) for m in expect]
    assert sent[0]["message"] == "SCENARIO_TWC" and sent[0]["signals"]["OSC"] == pytest.approx(0.5)
    assert {k["key"] for k in c.scenario_keys()} >= {"osc"}


def test_a_reset_is_a_request_with_a_random_challenge_then_its_confirm(cell):
    rt = cell.runtime
    rt.take_outbox()
    first = cell.reset_trip()
    second = cell.reset_trip()  # a newer request replaces the older
    assert first["window_s"] == 2.0 and 1 <= first["challenge"] <= 65535
    sent = [rt.db.decode(m)[1] for m in rt.take_outbox()]
    assert [(v[REQUEST_SIGNAL], v[CONFIRM_SIGNAL]) for v in sent] == \
        [(first["challenge"], 0), (second["challenge"], 0)]
    wrong = second["challenge"] % 65535 + 1
    for bad in (wrong, "1", 1.0, True, None):
        with pytest.raises(ParamError, match="challenge"):
            cell.confirm_reset(bad)
    assert rt.take_outbox() == []  # a refused confirm sends nothing, the request stays
    assert cell.confirm_reset(second["challenge"]) == second["challenge"]
    sent = [rt.db.decode(m)[1] for m in rt.take_outbox()]
    assert [(v[REQUEST_SIGNAL], v[CONFIRM_SIGNAL]) for v in sent] == [(0, second["challenge"])]
    with pytest.raises(ParamError, match="no reset request is pending"):
        cell.confirm_reset(second["challenge"])  # one confirm per request
    assert cell.trip() is None  # no ENGINE_STATE on this bus


def test_families_list_every_registered_family_with_its_blocks(db, monkeypatch):
    monkeypatch.setattr(registry, "FAMILIES", dict(registry.FAMILIES))
    registry.family(BlockFamily("probe", "probes", "test probes", ({"samples": 3},)))
    blocks = native_filters()
    blocks[0].family = "probe"
    c = Cell(runtime=Runtime(db, blocks))
    fams = {f["name"]: f for f in c.families()}
    assert list(fams) == list(registry.FAMILIES)
    assert fams["probe"] == {"name": "probe", "section": "probes", "description": "test probes",
                             "examples": [{"samples": 3}], "blocks": [blocks[0].name]}
    assert fams["filter"]["section"] == "filters"
    assert fams["filter"]["blocks"] == [b.name for b in blocks[1:]] == c.names("filter")
    assert fams["controller"]["blocks"] == []
    assert fams["filter"]["examples"] == [dict(e) for e in registry.FAMILIES["filter"].examples]


def test_block_and_blocks_describe_what_the_runtime_runs(cell):
    rt = cell.runtime
    assert cell.blocks("filter") == [rt.block(n).describe() for n in cell.names("filter")]
    assert cell.block("filter", "EXH_BP_R_Kalman") == rt.block("EXH_BP_R_Kalman").describe()
    assert cell.find("filter", "EXH_BP_R_Kalman") is rt.block("EXH_BP_R_Kalman")
    with pytest.raises(UnknownBlockError):
        cell.block("controller", "EXH_BP_R_Kalman")
    assert cell.period("MED") == rt.rates.period("MED")


def test_health_and_metrics_are_the_runtimes_counts(cell):
    rt = cell.runtime
    h = cell.health()
    assert h["status"] == "ok" and h["bus"] == "virtual:test" and h["runtime_running"] is False
    assert {k: h[k] for k in rt.health()} == rt.health()
    m = cell.metrics()
    assert m["frames_by_id"] == rt.frames_by_id == cell.frames_by_id()
    assert m["frames_by_id"] is not rt.frames_by_id  # a copy, read under the lock
    exh = rt.db.message("EXH_BP")
    assert m["messages"] == {(exh.frame_id, False): "EXH_BP"}
    assert (m["ticks"], m["tick_overruns"], m["late_frames"]) == (rt.ticks, rt.tick_overruns, 0)
    assert [s["block"] for s in m["steps"]] == sorted(rt.step_time)
    assert all(s["count"] == rt.step_time[s["block"]][1] for s in m["steps"])
    assert m["bus_time"] == rt.now
