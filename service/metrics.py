"""``GET /metrics``: the cell's counters for Prometheus, written by ``prometheus_client``.

Each app has its own :class:`~prometheus_client.CollectorRegistry` (:class:`Metrics`), so two
cells in one process never share a metric. A custom collector (:class:`CellCollector`) reads
the runtime's counters through the façade at every scrape, at one instant, so the runtime
keeps no Prometheus objects and pays nothing per frame. Frames are counted by the runtime
per arbitration ID; the frame rate per ID is taken over the last whole second of bus time
(:class:`FrameRates`, a MED-tick listener), so it needs no state per scraper. Names::

    testcell_frames_total{id,message}            counter   frames received, by ID
    testcell_frames_per_second{id,message}       gauge     over the last second of bus time
    testcell_decode_errors_total{kind}           counter   frames that could not be decoded
    testcell_late_frames_total                   counter
    testcell_ticks_total, testcell_tick_overruns_total   counter   ticks whose work outlasted their period
    testcell_tick_seconds_max                    gauge     slowest tick so far (wall seconds)
    testcell_tick_seconds                        histogram wall seconds of each tick's work
    testcell_block_step_seconds_{sum,count}{block,family}   summary of each block's step time
    testcell_block_errors_total{block}           counter
    testcell_block_faults_total{block,kind}      counter   refused, exception, nonfinite
    testcell_block_backoff_seconds{block}        gauge     a faulted block's backoff now (0: runs)
    testcell_missed_cycles_total{message}        counter   cycles of cyclic messages that never came
    testcell_kernel_drops_total                  counter   datagrams the kernel dropped (when reported)
    testcell_dropped_stale_total                 counter   outputs older than one cycle kept off the bus
    testcell_loop_stalls_total, testcell_loop_restarts_total   counter
    testcell_loop_lag_seconds                    gauge     the runtime behind the wall clock
    testcell_loop_up                             gauge     1 while the loop runs with no problem
    testcell_frame_to_api_seconds{route}         histogram age of the newest value an answer
                                                           carries (``channels``, ``stream``)
    testcell_websocket_clients                   gauge     open WS /stream connections
    testcell_stream_clients                      gauge     WS and SSE subscribers
    testcell_stream_dropped_total                counter   ticks skipped for slow subscribers
    testcell_bus_time_seconds                    gauge

The frame-to-API latency is the wall time an answer leaves minus the bus time of the newest
value in it; it is observed only where bus time is the wall clock (udp_multicast stamps each
frame with its receive time; a simulator at speed 1 stamps its send time): an age outside
0..:data:`MAX_AGE_S` is not a latency and is left out.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Iterator
from typing import Any

from prometheus_client import CollectorRegistry, Histogram, generate_latest
from prometheus_client.core import (CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily,
                                    Metric, SummaryMetricFamily)
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4
from prometheus_client.registry import Collector

from cell.app.cell import Cell
from cell.runtime.faults import FAULT_KINDS
from cell.runtime.health import OTHER_IDS

CONTENT_TYPE = CONTENT_TYPE_PLAIN_0_0_4

#: Ages (seconds) beyond which a value's bus time is not the wall clock: not observed.
MAX_AGE_S = 600.0

#: Buckets of the frame-to-API histogram (seconds).
LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
                   30.0)


class FrameRates:
    """Frames per second by ID over the last whole second of bus time."""

    def __init__(self, cell: Cell, window_s: float = 1.0) -> None:
        self.cell = cell
        self.window_s = window_s
        #: (previous, last) counts by ID with their bus times; swapped as one, so a reader
        #: in another thread never sees one without the other
        self._window: tuple[tuple[float, dict] | None, tuple[float, dict] | None] = (None, None)
        cell.on_tick(self.on_tick)

    def on_tick(self, t: float) -> None:
        last = self._window[1]
        if last is None or t - last[0] >= self.window_s - 1e-9:
            self._window = (last, (t, self.cell.frames_by_id()))

    def rates(self) -> dict[tuple[int, bool], float]:
        prev, last = self._window
        if prev is None or last is None:
            return {}
        (t0, c0), (t1, c1) = prev, last
        dt = t1 - t0
        return {k: (n - c0.get(k, 0)) / dt for k, n in c1.items()} if dt > 0 else {}


def _id_labels(key: tuple[int, bool], messages: dict) -> list[str]:
    if key == OTHER_IDS:
        return ["other", "unknown"]
    ident = f"0x{key[0]:08X}" if key[1] else f"0x{key[0]:03X}"
    return [ident, messages.get(key, "unknown")]


def _num(v: float | None) -> float:
    return float("nan") if v is None else float(v)


class CellCollector(Collector):
    """The cell's counters as metric families, read at each scrape (see the module notes)."""

    def __init__(self, cell: Cell, rates: FrameRates, hub: Any) -> None:
        self.cell, self.rates, self.hub = cell, rates, hub

    def collect(self) -> Iterator[Metric]:
        m = self.cell.metrics()
        yield from self._frames(m)
        yield from self._ticks(m)
        yield from self._blocks(m)
        yield from self._loop(m.get("loop"))
        yield from self._stream()

    def _frames(self, m: dict[str, Any]) -> Iterable[Metric]:
        by_id, messages, per_s = m["frames_by_id"], m["messages"], self.rates.rates()
        total = CounterMetricFamily("testcell_frames", "CAN frames received, by arbitration ID",
                                    labels=["id", "message"])
        rate = GaugeMetricFamily("testcell_frames_per_second", "CAN frames per second by "
                                 "arbitration ID, over the last second of bus time",
                                 labels=["id", "message"])
        for key in sorted(by_id):
            labels = _id_labels(key, messages)
            total.add_metric(labels, by_id[key])
            rate.add_metric(labels, per_s.get(key, 0.0))
        yield total
        yield rate
        errors = CounterMetricFamily("testcell_decode_errors", "frames that could not be "
                                     "decoded, by kind", labels=["kind"])
        for kind, n in sorted(m["decode_errors"].items()):
            errors.add_metric([kind], n)
        yield errors
        yield CounterMetricFamily("testcell_late_frames", "frames older than the newest one seen",
                                  value=m["late_frames"])
        missed = CounterMetricFamily("testcell_missed_cycles", "cycles of cyclic messages that "
                                     "never came (inter-arrival over 1.5 DBC cycles)",
                                     labels=["message"])
        for name, n in sorted(m["missed_cycles"].items()):
            missed.add_metric([name], n)
        yield missed
        yield GaugeMetricFamily("testcell_bus_time_seconds", "the runtime's bus time",
                                value=_num(m["bus_time"]))

    def _ticks(self, m: dict[str, Any]) -> Iterable[Metric]:
        yield CounterMetricFamily("testcell_ticks", "ticks run (FAS, MED and SLO together)",
                                  value=m["ticks"])
        yield CounterMetricFamily("testcell_tick_overruns", "ticks whose work took longer than "
                                  "their period", value=m["tick_overruns"])
        yield GaugeMetricFamily("testcell_tick_seconds_max", "wall seconds of the slowest tick "
                                "so far", value=m["tick_seconds_max"])
        buckets, total = m["tick_histogram"]
        hist = HistogramMetricFamily("testcell_tick_seconds", "wall seconds of each tick's work "
                                     "(block steps and MED listeners)")
        hist.add_metric([], [("+Inf" if math.isinf(b) else repr(b), n) for b, n in buckets],
                        sum_value=total)
        yield hist

    def _blocks(self, m: dict[str, Any]) -> Iterable[Metric]:
        steps = SummaryMetricFamily("testcell_block_step_seconds", "wall seconds spent in each "
                                    "block's step", labels=["block", "family"])
        for step in m["steps"]:
            steps.add_metric([step["block"], step["family"]], count_value=step["count"],
                             sum_value=step["seconds"])
        yield steps
        errors = CounterMetricFamily("testcell_block_errors", "block steps that failed, by block",
                                     labels=["block"])
        for name, n in sorted(m["block_errors"].items()):
            errors.add_metric([name], n)
        yield errors
        faults = CounterMetricFamily("testcell_block_faults", "block faults by kind: refused "
                                     "(ArithmeticError), exception (anything else: reset and "
                                     "backoff), nonfinite (a NaN or infinite output)",
                                     labels=["block", "kind"])
        backoff = GaugeMetricFamily("testcell_block_backoff_seconds", "the backoff a faulted "
                                    "block is in now (0: it runs)", labels=["block"])
        for name, f in m["block_faults"].items():
            for kind in FAULT_KINDS:
                faults.add_metric([name, kind], f[kind])
            backoff.add_metric([name], f["backoff_s"] if f["backing_off"] else 0.0)
        yield faults
        yield backoff

    def _loop(self, loop: dict[str, Any] | None) -> Iterable[Metric]:
        if loop is None:
            return  # an offline cell has no live loop
        yield GaugeMetricFamily("testcell_loop_up", "1 while the live loop runs with no problem",
                                value=1.0 if loop["running"] and not loop["problem"] else 0.0)
        yield CounterMetricFamily("testcell_loop_restarts", "times the live loop was started "
                                  "again after a failure", value=loop["restarts"])
        yield CounterMetricFamily("testcell_loop_stalls", "passes of the live loop that came "
                                  "later than the stall limit", value=loop["stalls"])
        yield GaugeMetricFamily("testcell_loop_lag_seconds", "the runtime's bus time behind the "
                                "wall clock's estimate of it", value=_num(loop["lag_s"]))
        yield CounterMetricFamily("testcell_dropped_stale", "output frames older than one cycle "
                                  "kept off the bus (after a stall)", value=loop["dropped_stale"])
        if loop["kernel_drops"] is not None:
            yield CounterMetricFamily("testcell_kernel_drops", "datagrams the kernel dropped on "
                                      "the bus socket", value=loop["kernel_drops"])

    def _stream(self) -> Iterable[Metric]:
        hub = self.hub
        clients = list(hub.clients)
        yield GaugeMetricFamily("testcell_websocket_clients", "open WebSocket /stream connections",
                                value=sum(1 for c in clients if getattr(c, "kind", "") == "ws"))
        yield GaugeMetricFamily("testcell_stream_clients", "WebSocket and SSE stream subscribers",
                                value=len(clients))
        yield CounterMetricFamily("testcell_stream_connections", "stream connections since start",
                                  value=hub.connections_total)
        yield CounterMetricFamily("testcell_stream_dropped", "ticks skipped for stream "
                                  "subscribers too slow to keep up", value=hub.dropped)


class Metrics:
    """The ``/metrics`` of one app: its own registry, the cell's collector and the
    frame-to-API histogram the routes observe into."""

    def __init__(self, cell: Cell, rates: FrameRates, hub: Any) -> None:
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(CellCollector(cell, rates, hub))
        self.latency = Histogram("testcell_frame_to_api_seconds",
                                 "wall time an API answer left minus the bus time of the newest "
                                 "value it carries (where bus time is the wall clock)",
                                 labelnames=["route"], buckets=LATENCY_BUCKETS,
                                 registry=self.registry)
        for route in ("channels", "stream"):
            self.latency.labels(route=route)  # shown from the start, at zero

    def served(self, route: str, newest: float | None) -> None:
        """An answer of ``route`` leaves now carrying a value of bus time ``newest``."""
        if newest is None:
            return
        age = time.time() - newest
        if 0.0 <= age <= MAX_AGE_S:
            self.latency.labels(route=route).observe(age)

    def render(self) -> bytes:
        """The text of ``GET /metrics`` (exposition format 0.0.4)."""
        return generate_latest(self.registry)


__all__ = ["CONTENT_TYPE", "CellCollector", "FrameRates", "LATENCY_BUCKETS", "MAX_AGE_S", "Metrics"]
