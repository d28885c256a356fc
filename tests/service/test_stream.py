"""``WS /stream`` and ``GET /stream/sse`` over a real uvicorn on a free port, in process.

The runtime is fed by the test itself (frames at bus times it chooses), so what the stream
must carry is known independently: the values the DBC encodes and the filters' own outputs.
"""

from __future__ import annotations

import json
import math
import re
import signal
import threading
import time
import tracemalloc

import httpx
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from cell.app.cell import Cell
from cell.estimators.backpressure import native_filters
from cell.runtime.scheduler import Runtime
from cell.scripts.manager import ScriptManager
from service.main import create_app
from service.stream import BACKLOG, RING

from .served import served
from tests.helpers.frames import feed as bp_feed
from tests.helpers.frames import steady, wavy


def frame(db, t):
    return db.encode("EXH_BP", {"EXH_BP_L": 680.0, "EXH_BP_R": 680.0 + 10 * math.sin(t)}, t)


def feed(rt, db, t0, t1):
    bp_feed(rt, db, t0, t1, left=steady(680.0), right=wavy(680.0), advance=False)


def recv(ws, kind, timeout=5.0):
    """The next message of type ``kind`` (skipping others)."""
    deadline = time.monotonic() + timeout
    while True:
        m = json.loads(ws.recv(timeout=max(0.01, deadline - time.monotonic())))
        if m["type"] == kind:
            return m


@pytest.fixture
def cell(db):
    rt = Runtime(db, native_filters())
    feed(rt, db, 0.0, 5.0)
    return Cell(runtime=rt, bus="virtual:test")


@pytest.fixture
def app(cell):
    return create_app(cell)


@pytest.fixture
def url(app):
    with served(app) as base:
        yield base


def ws_url(url, query=""):
    return url.replace("http://", "ws://") + "/stream" + query


def test_subscribe_by_name_and_glob_then_values_then_stale(url, cell, db):
    rt = cell.runtime
    with connect(ws_url(url)) as ws:
        assert recv(ws, "hello")["time"] == pytest.approx(rt.now)
        ws.send(json.dumps({"subscribe": ["EXH_BP_R", "EXH_BP_*_Kalman", "NO_SUCH_*"]}))
        sub = recv(ws, "subscribed")
        assert [c["name"] for c in sub["channels"]] == ["EXH_BP_L_Kalman", "EXH_BP_R", "EXH_BP_R_Kalman"]
        assert {c["unit"] for c in sub["channels"]} == {"mmH2O"}
        assert sub["unmatched"] == ["NO_SUCH_*"]
        snap = recv(ws, "snapshot")
        assert snap["values"]["EXH_BP_R"][1] == "ok"
        feed(rt, db, 5.0, 5.5)
        got = [recv(ws, "data") for _ in range(5)]
        assert [m["seq"] for m in got] == list(range(got[0]["seq"], got[0]["seq"] + 5))
        for m in got:
            value, status, t = m["values"]["EXH_BP_R"]
            # the newest frame at or before the tick, as the DBC's 0.01 mmH2O scale has it
            want = db.decode_payload(db.message("EXH_BP"), frame(db, round(m["time"], 2)).data)["EXH_BP_R"]
            assert status == "ok" and value == pytest.approx(want) and t == pytest.approx(m["time"])
            kal = m["values"]["EXH_BP_R_Kalman"]
            assert kal[1] == "ok" and abs(kal[0] - 680) < 15
            assert set(m["values"]) == {"EXH_BP_L_Kalman", "EXH_BP_R", "EXH_BP_R_Kalman"}
            assert m["dropped"] == 0
        # the frames stop; bus time goes on: the raw channel turns stale, keeping its last value
        last = rt.last_frame_time
        rt.advance(last + 1.0)
        stale = None
        while stale is None:
            m = recv(ws, "data")
            if m["values"]["EXH_BP_R"][1] == "stale":
                stale = m
        value, status, t = stale["values"]["EXH_BP_R"]
        assert t == pytest.approx(last) and stale["time"] - last > 0.15
        assert stale["values"]["EXH_BP_R_Kalman"][1] == "stale"  # its input is stale
        ws.send(json.dumps({"unsubscribe": ["EXH_BP_*_Kalman"]}))
        assert [c["name"] for c in recv(ws, "subscribed")["channels"]] == ["EXH_BP_R"]


@pytest.mark.parametrize("raw, words", [
    ("not json", "not JSON"),
    ('{"subscribe": 5}', "list of strings"),
    ('{"subscribe": []}', "names no channel"),
    ('{"subscribe": ["EXH BP"]}', "not a channel name"),
    ('{"listen": ["EXH_BP_R"]}', "unknown key 'listen'"),
    ('["EXH_BP_R"]', 'send {"subscribe"'),
    ('{"unsubscribe": ["EXH_BP_L"]}', "was not subscribed"),
])
def test_bad_requests_get_an_error_and_the_subscription_stays(url, cell, db, raw, words):
    with connect(ws_url(url, "?channels=EXH_BP_R")) as ws:
        assert [c["name"] for c in recv(ws, "subscribed")["channels"]] == ["EXH_BP_R"]
        ws.send(raw)
        err = recv(ws, "error")
        assert words in err["message"]
        feed(cell.runtime, db, 5.0, 5.3)
        assert set(recv(ws, "data")["values"]) == {"EXH_BP_R"}


def test_subscribers_beyond_the_limit_are_refused_and_told_why(url, monkeypatch):
    import service.stream

    monkeypatch.setattr(service.stream, "MAX_CLIENTS", 1)
    with connect(ws_url(url, "?channels=EXH_BP_R")) as first:
        recv(first, "subscribed")
        with connect(ws_url(url)) as second:
            err = recv(second, "error")
            assert "at most 1" in err["message"]
            with pytest.raises(ConnectionClosed) as closed:
                second.recv(timeout=5)
            assert closed.value.rcvd.code == 1013
        r = httpx.get(url + "/stream/sse", params={"channels": "EXH_BP_R"}, timeout=5)
        assert r.status_code == 503 and "at most 1" in r.text
        recv(first, "snapshot")  # the first one is served on


def test_sse_serves_the_same_data_to_curl(url, cell, db):
    stop = threading.Event()

    def feeder():  # bus time runs on while the client reads
        t = 5.0
        while not stop.is_set():
            feed(cell.runtime, db, t, t + 0.1)
            t = round(t + 0.1, 6)
            time.sleep(0.01)

    th = threading.Thread(target=feeder, daemon=True)
    th.start()
    try:
        with httpx.stream("GET", url + "/stream/sse", params={"channels": "EXH_BP_R*", "count": 4},
                          timeout=10) as r:
            assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
            text = r.read().decode()
    finally:
        stop.set()
        th.join()
    blocks = text.strip().split("\n\n")
    events = [dict(line.split(": ", 1) for line in block.splitlines()) for block in blocks]
    assert [e["event"] for e in events] == ["subscribed", "snapshot", "data", "data", "data", "data"]
    sub = json.loads(events[0]["data"])
    assert [c["name"] for c in sub["channels"]] == ["EXH_BP_R", "EXH_BP_R_Kalman", "EXH_BP_R_MAF"]
    data = [json.loads(e["data"]) for e in events[2:]]
    assert [int(e["id"]) for e in events[2:]] == [d["seq"] for d in data]
    assert [d["seq"] for d in data] == list(range(data[0]["seq"], data[0]["seq"] + 4))
    assert all(d["values"]["EXH_BP_R"][1] == "ok" for d in data)
    assert all(b["time"] - a["time"] == pytest.approx(0.1) for a, b in zip(data, data[1:]))


def test_streams_end_when_the_server_is_asked_to_stop(url, app):
    """An event stream never ends by itself: on SIGTERM the server ends them (service.serve)."""
    lines: list[str] = []
    done = threading.Event()

    def read():
        with httpx.stream("GET", url + "/stream/sse", params={"channels": "EXH_BP_R"}, timeout=30) as r:
            for line in r.iter_lines():
                lines.append(line)
        done.set()

    threading.Thread(target=read, daemon=True).start()
    with connect(ws_url(url, "?channels=EXH_BP_R")) as ws:
        recv(ws, "subscribed")
        deadline = time.monotonic() + 5
        while not any(line.startswith("event: snapshot") for line in lines):
            assert time.monotonic() < deadline
            time.sleep(0.02)
        app.state.hub.close()  # what Server.handle_exit does first
        assert done.wait(5), "the event stream did not end"
        with pytest.raises(ConnectionClosed) as closed:
            while True:
                ws.recv(timeout=5)
        assert closed.value.rcvd.code == 1001


def test_sigterm_to_the_server_closes_the_apps_streams(cell):
    import uvicorn

    from service.serve import Server

    app = create_app(cell)
    Server(uvicorn.Config(app)).handle_exit(signal.SIGTERM, None)
    assert app.state.hub.closed


@pytest.mark.parametrize("query, words", [({}, "channels"), ({"channels": " , "}, "names no channel"),
                                          ({"channels": "A", "count": 0}, "count")])
def test_sse_bad_query_is_422_naming_it(url, query, words):
    r = httpx.get(url + "/stream/sse", params=query, timeout=5)
    assert r.status_code == 422 and words in r.text


def test_a_client_that_stops_reading_keeps_server_memory_bounded_and_is_told_its_drops(db, tmp_path):
    rt = Runtime(db, native_filters())
    ScriptManager(rt, None).load_defaults()  # the shipped scripts: some 300 channels a tick
    feed(rt, db, 0.0, 2.0)
    app = create_app(Cell(runtime=rt, bus="virtual:test"))
    hub = app.state.hub
    with served(app, sndbuf=32_768) as url, connect(ws_url(url, "?channels=*"), max_queue=4) as ws:
        recv(ws, "subscribed")
        recv(ws, "snapshot")
        # the client reads nothing from here on: fill the shared ring (and the runtime's
        # history), then count the bytes the server holds after 600 and after 1200 more ticks
        feed(rt, db, 2.0, 2.0 + RING / rt.rates.MED + 5.0)
        ticks, held = 600, []
        # what the runtime itself keeps (its outbox, frame times, the test's frames) is not
        # the stream's: count every other allocation (the hub, uvicorn, websockets, asyncio)
        not_stream = [tracemalloc.Filter(False, pat) for pat in
                      ("*/cell/*", "*/can/*", __file__, tracemalloc.__file__)]
        tracemalloc.start()
        try:
            for _ in range(2):
                t0 = rt.now + 0.01
                feed(rt, db, t0, t0 + ticks / rt.rates.MED)
                time.sleep(0.3)  # let the server's writer run as far as the socket lets it
                snap = tracemalloc.take_snapshot().filter_traces(not_stream)
                held.append(sum(st.size for st in snap.statistics("filename")))
        finally:
            tracemalloc.stop()
        (client,) = hub.clients
        size = len(client.message(hub.records[-1]))
        grown = held[1] - held[0]
        print(f"slow client: server memory grew {grown / 1e3:.0f} kB over {ticks} more ticks of {size} B "
              f"messages (an unbounded queue: {ticks * size / 1e6:.1f} MB)")
        assert size > 5_000, size  # large messages, so an unbounded queue would show
        assert len(hub.records) == RING  # the shared ring is full and no bigger
        # bounded: a small fraction of what a queue would hold (other threads' allocations in
        # the same window add noise of some 100 kB on a loaded machine)
        assert grown < 0.25 * ticks * size, (grown, ticks * size)
        # reading again: told of the drops, then the newest ticks; seq gaps add up to the drops
        seqs, told = [], 0
        while not seqs or seqs[-1] < hub.seq:
            m = json.loads(ws.recv(timeout=5))
            if m["type"] == "dropped":
                told = m["total"]
            elif m["type"] == "data":
                seqs.append(m["seq"])
                dropped = m["dropped"]
        gaps = sum(b - a - 1 for a, b in zip(seqs, seqs[1:])) + seqs[0] - 1
        assert told == dropped == gaps == client.dropped > 0
        assert len(seqs) < hub.seq / 2  # the newest, not everything
        metrics = httpx.get(url + "/metrics", timeout=5).text
        assert f"testcell_stream_dropped_total {dropped}" in metrics
        assert "testcell_websocket_clients 1" in metrics
    assert BACKLOG < RING


#: N WebSocket clients in a process of their own (as browsers would be): each records the
#: seq, drop count and number of values of every data message for SECONDS
CLIENTS = """
import asyncio, json, sys, time
import websockets
url, n, seconds = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
async def one(ready):
    async with websockets.connect(url) as ws:
        ready.append(1)
        while len(ready) < n:
            await asyncio.sleep(0.01)
        seqs, end = [], time.monotonic() + seconds
        while time.monotonic() < end:
            m = json.loads(await asyncio.wait_for(ws.recv(), 5))
            if m["type"] == "data":
                seqs.append((m["seq"], m["dropped"], len(m["values"])))
        return seqs
async def main():
    ready = []
    print(json.dumps(await asyncio.gather(*[one(ready) for _ in range(n)])))
asyncio.run(main())
"""


def test_fifty_clients_get_every_tick_while_the_runtime_keeps_up(tmp_path):
    import subprocess
    import sys

    from .livecell import live_cell

    n, seconds = 50, 4.0
    with live_cell(tmp_path) as (url, cell):
        rt = cell.runtime
        deadline = time.monotonic() + 20
        while rt.now is None or rt.ticks < 20:
            assert time.monotonic() < deadline, "the live cell did not start"
            time.sleep(0.1)
        # what this machine does to the runtime without clients, over as long a window
        overruns0 = rt.tick_overruns
        time.sleep(seconds)
        baseline = rt.tick_overruns - overruns0
        overruns0 = rt.tick_overruns
        query = "?channels=EXH_BP_*,VALVE_*,ENGINE_SPEED"
        proc = subprocess.Popen([sys.executable, "-c", CLIENTS, ws_url(url, query), str(n), str(seconds)],
                                stdout=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 20
        while _ws_clients(url) < n:  # GET /metrics counts them
            assert time.monotonic() < deadline and proc.poll() is None, "the clients did not connect"
            time.sleep(0.05)
        out, _ = proc.communicate(timeout=30)
        assert proc.returncode == 0
        results = json.loads(out)
        overruns = rt.tick_overruns - overruns0
        lag = cell.live.estimated_bus_time() - rt.now
        for seqs in results:
            assert len(seqs) >= seconds * rt.rates.MED * 0.7, len(seqs)
            nums = [s for s, _, _ in seqs]
            assert nums == list(range(nums[0], nums[0] + len(nums)))  # every tick, in order
            assert all(d == 0 for _, d, _ in seqs) and all(v >= 9 for _, _, v in seqs)
        # the runtime keeps up: the clients add no tick overruns to what the machine causes
        # without them (none, on a machine not busy with other work), and no lag
        assert overruns <= baseline, (overruns, baseline, rt.tick_seconds_max)
        assert lag < 0.5, lag


def _ws_clients(url: str) -> int:
    text = httpx.get(url + "/metrics", timeout=5).text
    return int(float(re.search(r"^testcell_websocket_clients (\S+)$", text, re.M).group(1)))
