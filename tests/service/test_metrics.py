"""``GET /metrics``: Prometheus text, counted against what the test fed in."""

from __future__ import annotations

import math
import re
import time

import can
import pytest
from tests.helpers.client import local_client

from cell.runtime.blocks import Block
from cell.app.cell import Cell
from cell.estimators.backpressure import native_filters
from cell.runtime.scheduler import Runtime
from service.main import create_app

LINE = re.compile(r'^([a-zA-Z_:][a-zA-Z0-9_:]*)(\{(?:[a-zA-Z_][a-zA-Z0-9_]*="(?:[^"\\]|\\.)*",?)*\})? (\S+)$')


class Slow(Block):
    """A MED block whose step outlasts the 0.1 s MED period."""

    kind = family = "slow"

    def _step(self, t, inputs):
        time.sleep(0.12)
        return {"SLOW_OUT": inputs["EXH_BP_L"]}


def parse(text: str) -> dict[str, float]:
    """``{'name{labels}': value}``, checking every line is exposition format 0.0.4."""
    samples, typed = {}, set()
    for line in text.splitlines():
        if line.startswith("# TYPE "):
            typed.add(line.split()[2])
            continue
        if line.startswith("# HELP ") or not line:
            continue
        m = LINE.match(line)
        assert m, f"not a Prometheus sample line: {line!r}"
        base = re.sub(r"_(sum|count|bucket)$", "", m.group(1))
        assert m.group(1) in typed or base in typed, f"{m.group(1)} has no # TYPE line"
        samples[m.group(1) + (m.group(2) or "")] = float(m.group(3))
    return samples


@pytest.fixture
def fed(db):
    rt = Runtime(db, [*native_filters(), Slow("SLOW", ["EXH_BP_L"], ["SLOW_OUT"])])
    exh = db.message("EXH_BP")
    t, n = 0.0, 0
    while t < 1.0 - 1e-9:
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 680.0, "EXH_BP_R": 680 + math.sin(t)}, t))
        t, n = round(t + 0.01, 6), n + 1
    for _ in range(3):
        rt.ingest(can.Message(timestamp=1.0, arbitration_id=0x7FE, data=b"\x00", is_extended_id=False))
    for _ in range(2):
        rt.ingest(can.Message(timestamp=1.0, arbitration_id=exh.frame_id, data=b"\x01", is_extended_id=False))
    rt.advance(1.0)
    return rt, n, exh


def test_metrics_count_frames_errors_overruns_and_step_times(fed):
    rt, n, exh = fed
    client = local_client(create_app(Cell(runtime=rt, bus="virtual:test")))
    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain; version=0.0.4")
    m = parse(r.text)
    ident = f"0x{exh.frame_id:03X}"
    assert m[f'testcell_frames_total{{id="{ident}",message="EXH_BP"}}'] == n + 2
    assert m['testcell_frames_total{id="0x7FE",message="unknown"}'] == 3
    assert m['testcell_decode_errors_total{kind="unknown_id"}'] == 3
    assert m['testcell_decode_errors_total{kind="bad_length"}'] == 2
    # the Kalman filter stepped at every MED tick at which its input had a value
    ok_ticks = sum(1 for _, _, s in rt.history("EXH_BP_R_Kalman", 60) if s == "ok")
    assert m['testcell_block_step_seconds_count{block="EXH_BP_R_Kalman",family="filter"}'] == ok_ticks
    assert 0 < m['testcell_block_step_seconds_sum{block="EXH_BP_R_Kalman",family="filter"}'] < 0.1
    slow_steps = m['testcell_block_step_seconds_count{block="SLOW",family="slow"}']
    assert slow_steps == ok_ticks
    assert m['testcell_block_step_seconds_sum{block="SLOW",family="slow"}'] >= 0.12 * slow_steps
    # each of the slow block's ticks outlasted the MED period; no other tick did
    assert m["testcell_tick_overruns_total"] == slow_steps
    assert m["testcell_tick_seconds_max"] >= 0.12
    assert m["testcell_bus_time_seconds"] == pytest.approx(1.0)
    assert m["testcell_websocket_clients"] == 0


def test_frames_per_second_by_id_over_the_last_second_of_bus_time(db):
    rt = Runtime(db, native_filters())
    client = local_client(create_app(Cell(runtime=rt, bus="virtual:test")))
    t = 0.0
    while t < 4.0 - 1e-9:  # EXH_BP at 100 Hz, ENGINE_1 at 20 Hz
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 680.0, "EXH_BP_R": 680.0}, t))
        if round(t * 100) % 5 == 0:
            rt.ingest(_engine(db, t))
        t = round(t + 0.01, 6)
    rt.advance(4.0)
    m = parse(client.get("/metrics").text)
    rates = {k: v for k, v in m.items() if k.startswith("testcell_frames_per_second")}
    for name, hz in (("EXH_BP", 100), ("ENGINE_1", 20)):
        key = f'testcell_frames_per_second{{id="0x{db.message(name).frame_id:03X}",message="{name}"}}'
        assert rates[key] == pytest.approx(hz, abs=1)


def _engine(db, t):
    msg = db.message("ENGINE_1")
    return db.encode("ENGINE_1", {s.name: 0.0 for s in msg.signals}, t)


def test_websocket_clients_are_counted_while_connected(db):
    rt = Runtime(db, native_filters())
    client = local_client(create_app(Cell(runtime=rt, bus="virtual:test")))
    with client.websocket_connect("/stream?channels=EXH_BP_R") as ws:
        assert ws.receive_json()["type"] == "hello"
        assert ws.receive_json()["type"] == "subscribed"
        m = parse(client.get("/metrics").text)
        assert m["testcell_websocket_clients"] == 1 and m["testcell_stream_clients"] == 1
    deadline = time.monotonic() + 5
    while parse(client.get("/metrics").text)["testcell_websocket_clients"] != 0:
        assert time.monotonic() < deadline
        time.sleep(0.05)


def test_a_bus_of_random_ids_keeps_the_counts_bounded(db, monkeypatch):
    import cell.runtime.health as runtime

    monkeypatch.setattr(runtime, "MAX_COUNTED_IDS", 8)
    rt = Runtime(db)
    for k in range(40):  # 40 distinct unknown IDs
        rt.ingest(can.Message(timestamp=k * 0.01, arbitration_id=0x10000 + k, data=b"", is_extended_id=True))
    assert len(rt.frames_by_id) == 9
    m = parse(local_client(create_app(Cell(runtime=rt, bus="virtual:test"))).get("/metrics").text)
    assert m['testcell_frames_total{id="other",message="unknown"}'] == 32
    assert m['testcell_frames_total{id="0x00010000",message="unknown"}'] == 1
    assert m['testcell_decode_errors_total{kind="unknown_id"}'] == 40


def test_metrics_parse_with_prometheus_client_and_carry_the_histograms(db):
    from prometheus_client.parser import text_string_to_metric_families

    rt = Runtime(db, native_filters())
    client = local_client(create_app(Cell(runtime=rt, bus="virtual:test")))
    t0 = round(time.time() - 2.0, 2)  # frames stamped with the wall clock, as udp_multicast does
    t = t0
    while t < t0 + 2.0 - 1e-9:
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 680.0, "EXH_BP_R": 680.0}, t))
        t = round(t + 0.01, 6)
    newest = t - 0.01
    rt.advance(newest)
    lower = upper = 0.0
    for path in ("/channels", "/channels", "/channels/EXH_BP_R"):
        before = time.time()
        assert client.get(path).status_code == 200
        lower, upper = lower + before - newest, upper + time.time() - newest
    fams = {f.name: f for f in text_string_to_metric_families(client.get("/metrics").text)}
    for name in ("testcell_frames", "testcell_frames_per_second", "testcell_decode_errors",
                 "testcell_late_frames", "testcell_ticks", "testcell_tick_overruns",
                 "testcell_tick_seconds_max", "testcell_block_step_seconds", "testcell_block_errors",
                 "testcell_websocket_clients", "testcell_stream_clients", "testcell_stream_dropped",
                 "testcell_bus_time_seconds", "testcell_missed_cycles", "testcell_block_faults"):
        assert name in fams, name
    ticks = fams["testcell_tick_seconds"]
    assert ticks.type == "histogram"
    samples = {(s.name, s.labels.get("le")): s.value for s in ticks.samples}
    buckets = [v for (n, le), v in samples.items() if n.endswith("_bucket")]
    assert buckets == sorted(buckets) and samples[("testcell_tick_seconds_bucket", "+Inf")] == rt.ticks
    assert samples[("testcell_tick_seconds_count", None)] == rt.ticks == 20
    assert 0 < samples[("testcell_tick_seconds_sum", None)] <= rt.ticks * rt.tick_seconds_max
    lat = fams["testcell_frame_to_api_seconds"]
    assert lat.type == "histogram"
    got = {(s.name, s.labels["route"]): s.value for s in lat.samples if "le" not in s.labels}
    assert got[("testcell_frame_to_api_seconds_count", "channels")] == 3
    assert lower <= got[("testcell_frame_to_api_seconds_sum", "channels")] <= upper
    assert got[("testcell_frame_to_api_seconds_count", "stream")] == 0


def test_values_whose_bus_time_is_not_the_wall_clock_give_no_latency(fed):
    from prometheus_client.parser import text_string_to_metric_families

    rt, _, _ = fed  # bus time from 0 s: a replayed log, a virtual bus
    client = local_client(create_app(Cell(runtime=rt, bus="virtual:test")))
    client.get("/channels")
    fams = {f.name: f for f in text_string_to_metric_families(client.get("/metrics").text)}
    counts = [s.value for s in fams["testcell_frame_to_api_seconds"].samples if s.name.endswith("_count")]
    assert counts == [0, 0]
