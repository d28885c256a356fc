"""The runtime's parts besides the scheduler: its channels (:class:`ChannelStore`) and its
counts (:class:`HealthCounters`), alone and as the runtime composes them."""

from __future__ import annotations

import can
import pytest

from cell.core.errors import UnknownBlockError
from cell.estimators.backpressure import native_filters
from cell.runtime import health, scheduler
from cell.runtime.health import HealthCounters
from cell.runtime.scheduler import Runtime
from cell.runtime.store import ChannelStore


def test_a_bus_channel_takes_unit_and_staleness_from_the_dbc_an_output_never_ages(db):
    store = ChannelStore(db, history_len=10, stale_floor=0.15)
    cycle = db.signals["EXH_BP_R"].cycle_time_s
    bus = store.add("EXH_BP_R")
    assert store.add("EXH_BP_R") is bus and bus.unit == "mmH2O"
    assert bus.stale_after == max(2.5 * cycle, 0.15)
    out = store.add("EXH_BP_R_X", source="some_block")
    assert out.stale_after == float("inf") and out.unit == ""
    bus.update(680.0, 1.0)
    out.update(1.0, 1.0)
    readings = store.readings(100.0)
    assert readings == {"EXH_BP_R": (680.0, "stale", 1.0), "EXH_BP_R_X": (1.0, "ok", 1.0)}
    assert store.readings(1.0, ["EXH_BP_R_X", "NOPE"]) == {"EXH_BP_R_X": (1.0, "ok", 1.0)}
    assert [s["name"] for s in store.snapshot(1.0)] == ["EXH_BP_R", "EXH_BP_R_X"]


def test_history_is_taken_at_each_recorded_tick_and_dropped_with_its_channel(db):
    store = ChannelStore(db, history_len=3, stale_floor=0.15)
    ch = store.add("EXH_BP_R")
    for k in range(5):
        ch.update(float(k), k * 0.1)
        store.record(k * 0.1)
    assert [v for _, v, _ in store.history("EXH_BP_R", 10.0)] == [2.0, 3.0, 4.0]  # the ring holds 3
    store.drop("EXH_BP_R")
    assert store.unit_of("EXH_BP_R") is None
    with pytest.raises(UnknownBlockError, match="EXH_BP_R"):
        store.history("EXH_BP_R", 10.0)


def test_unknown_ids_are_counted_by_id_up_to_the_bound(monkeypatch):
    monkeypatch.setattr(health, "MAX_UNKNOWN_IDS", 2)
    c = HealthCounters()
    for k in (1, 2, 3, 1):
        c.count_decode_error("unknown_id", (k, False))
    c.count_decode_error("bad_length", (9, False))
    assert c.decode_errors["unknown_id"] == 4 and c.decode_errors["bad_length"] == 1
    assert c.unknown_id_counts() == {"0x1": 2, "0x2": 1}


def test_ticks_overruns_and_steps_are_counted():
    c = HealthCounters()
    c.count_tick(0.01)
    c.count_tick(0.3)
    c.count_overrun()
    c.count_step("b", 0.5)
    c.count_step("b", 0.25)
    assert (c.ticks, c.tick_overruns, c.tick_seconds_max) == (2, 1, 0.3)
    assert c.step_time == {"b": [0.75, 2]}
    report = c.report(now=2.0, last_frame_time=None, streams={})
    assert report["tick_overruns"] == 1 and report["frames_per_s"] == 0.0 and report["bus_time"] == 2.0


def test_the_runtime_counts_into_its_counters_and_keeps_its_channels_in_its_store(db):
    rt = Runtime(db, native_filters())
    for k in range(30):
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 680.0, "EXH_BP_R": 681.0}, k * 0.01))
    rt.ingest(can.Message(timestamp=0.3, arbitration_id=0x7AB, data=b"", is_extended_id=False))
    rt.advance(0.3)
    assert rt.frames == rt.counters.frames == 31
    assert rt.decode_errors is rt.counters.decode_errors and rt.decode_errors["unknown_id"] == 1
    assert rt.ticks == rt.counters.ticks > 0
    assert rt.channels is rt.store.by_name and rt.channels["EXH_BP_R"].value == 681.0
    assert rt.health() == rt.counters.report(rt.now, rt.last_frame_time, {})
    rt.tick_seconds_max = 0.0  # benchmarks reset it between runs
    assert rt.counters.tick_seconds_max == 0.0
    assert scheduler.MAX_COUNTED_IDS == health.MAX_COUNTED_IDS  # still importable from the scheduler
