"""The dashboard's redraw time and the stream's fan-out, against their real-time budgets.

Run: ``.venv/bin/python benchmarks/bench_dashboard.py [CLIENTS ...]`` (default 50)

1. Redraw: the page's own plot (``TC.bench`` in ``service/static/dashboard.js``) with 20
   traces of 10 minutes at 10 Hz (6000 samples each) in a 1200 px wide plot, redrawn 60
   times with a new sample each time, in headless Chromium (``/usr/bin/chromium``). The
   budgets: one display frame at 60 Hz (16.7 ms) and one MED tick (100 ms), the rate the
   data arrives at.
2. Fan-out: a runtime fed frames in real time (the cell's EXH_BP traffic at 100 Hz, by a
   feeder thread) served by uvicorn on a free port; N WebSocket clients subscribe to
   ``EXH_BP_*`` for 8 s. Reported: messages delivered per client against the ticks run,
   drops, tick overruns (ticks whose work outlasted their period, the runtime's own
   count) and the runtime's slowest tick against the MED period.
"""

from __future__ import annotations

import asyncio
import gc
import json
import math
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cell.app.cell import Cell  # noqa: E402
from cell.bus.dbc import load  # noqa: E402
from cell.estimators.backpressure import native_filters  # noqa: E402
from cell.runtime.scheduler import Runtime  # noqa: E402
from service.main import create_app  # noqa: E402
from tests.service.served import served  # noqa: E402

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync"]


class Feeder:
    """EXH_BP frames at 100 Hz, stamped with wall time, in 10 ms batches."""

    def __init__(self, rt: Runtime, db) -> None:
        self.rt, self.db, self.stop = rt, db, threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)

    def run(self) -> None:
        t0 = time.time()
        k = 0
        while not self.stop.is_set():
            now = time.time()
            while k * 0.01 <= now - t0:
                t = t0 + k * 0.01
                self.rt.ingest(self.db.encode("EXH_BP", {"EXH_BP_L": 680.0 + 5 * math.sin(t),
                                                         "EXH_BP_R": 680.0 + 5 * math.cos(t)}, t))
                k += 1
            self.rt.take_outbox()
            time.sleep(0.005)


def redraw() -> dict:
    from playwright.sync_api import sync_playwright

    db = load()
    rt = Runtime(db, native_filters())
    feeder = Feeder(rt, db)
    feeder.thread.start()
    try:
        with served(create_app(Cell(runtime=rt, bus="virtual:bench"))) as url, sync_playwright() as pw, \
                tempfile.TemporaryDirectory() as profile:
            ctx = pw.chromium.launch_persistent_context(profile, executable_path="/usr/bin/chromium",
                                                        headless=True, args=FLAGS)
            page = ctx.new_page()
            page.goto(url + "/")
            page.wait_for_function("window.TC && TC.ready", timeout=30_000)
            result = page.evaluate("TC.bench(20, 600, 10, 60)")
            ctx.close()
    finally:
        feeder.stop.set()
    return result


def fan_out(n: int, seconds: float = 8.0) -> dict:
    import websockets

    db = load()
    rt = Runtime(db, native_filters())
    feeder = Feeder(rt, db)
    gc.freeze()  # as the live cell does at start (cell/app/live.py)
    feeder.thread.start()
    try:
        with served(create_app(Cell(runtime=rt, bus="virtual:bench"))) as url:
            time.sleep(1.0)
            base = url.replace("http://", "ws://") + "/stream?channels=EXH_BP_*"

            async def one():
                async with websockets.connect(base) as ws:
                    got, dropped, end = 0, 0, time.monotonic() + seconds
                    while time.monotonic() < end:
                        m = json.loads(await asyncio.wait_for(ws.recv(), 5))
                        if m["type"] == "data":
                            got, dropped = got + 1, m["dropped"]
                    return got, dropped

            async def many():
                return await asyncio.gather(*[one() for _ in range(n)])

            overruns0, ticks0 = rt.tick_overruns, rt.ticks
            rt.tick_seconds_max = 0.0
            med0 = rt.now
            results = asyncio.run(many())
            med_ticks = (rt.now - med0) * rt.rates.MED
    finally:
        feeder.stop.set()
    got = [g for g, _ in results]
    return {"clients": n, "med_ticks": med_ticks, "min_msgs": min(got), "mean_msgs": sum(got) / n,
            "dropped": sum(d for _, d in results), "overruns": rt.tick_overruns - overruns0,
            "ticks": rt.ticks - ticks0, "slowest_tick_ms": 1e3 * rt.tick_seconds_max}


def main(clients: list[int]) -> None:
    if Path("/usr/bin/chromium").exists():
        r = redraw()
        print(f"redraw: {r['traces']} traces x {r['points']} samples (10 min at 10 Hz), {r['draws']} "
              f"redraws in Chromium: median {r['median_ms']:.1f} ms, mean {r['mean_ms']:.1f} ms, "
              f"max {r['max_ms']:.1f} ms")
        print(f"  = {r['mean_ms'] / (1000 / 60):.2f} x a 60 Hz display frame (16.7 ms), "
              f"{r['mean_ms'] / 100:.3f} x the 10 Hz data period (100 ms)")
    else:
        print("redraw: skipped, /usr/bin/chromium is missing (scripts/setup-browser.sh)")
    for n in clients:
        f = fan_out(n)
        print(f"fan-out: {f['clients']} WebSocket clients, {f['med_ticks']:.0f} MED ticks in 8 s: every "
              f"client got >= {f['min_msgs']} messages (mean {f['mean_msgs']:.1f}), {f['dropped']} dropped; "
              f"{f['overruns']} tick overruns in {f['ticks']} ticks; slowest tick "
              f"{f['slowest_tick_ms']:.2f} ms = {f['slowest_tick_ms'] / 100:.3f} x the MED period")


if __name__ == "__main__":
    import argparse

    _p = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    _p.add_argument("clients", nargs="*", type=int, default=[50],
                    help="numbers of simultaneous dashboard clients to time (default 50)")
    main(_p.parse_args().clients)
