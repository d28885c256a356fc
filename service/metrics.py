"""``GET /metrics``: the cell's counters in the Prometheus text exposition format (0.0.4).

Frames are counted by the runtime per arbitration ID; the frame rate per ID is taken over
the last whole second of bus time (:class:`FrameRates`, a MED-tick listener), so it needs
no state per scraper. Names::

    testcell_frames_total{id,message}            counter   frames received, by ID
    testcell_frames_per_second{id,message}       gauge     over the last second of bus time
    testcell_decode_errors_total{kind}           counter   frames that could not be decoded
    testcell_late_frames_total                   counter
    testcell_ticks_total, testcell_tick_overruns_total   counter   ticks whose work outlasted their period
    testcell_tick_seconds_max                    gauge     slowest tick so far (wall seconds)
    testcell_block_step_seconds_{sum,count}{block,family}   summary of each block's step time
    testcell_block_errors_total{block}           counter
    testcell_websocket_clients                   gauge     open WS /stream connections
    testcell_stream_clients                      gauge     WS and SSE subscribers
    testcell_stream_dropped_total                counter   ticks skipped for slow subscribers
    testcell_bus_time_seconds                    gauge
"""

from __future__ import annotations

from typing import Any

from cell.app.cell import Cell
from cell.runtime.health import OTHER_IDS

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


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


def _esc(v: Any) -> str:
    return str(v).replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _labels(**kv: Any) -> str:
    return "{" + ",".join(f'{k}="{_esc(v)}"' for k, v in kv.items()) + "}"


def _num(v: float) -> str:
    if isinstance(v, int):
        return str(v)
    return repr(float(v)) if v == v else "NaN"


def render(cell: Cell, rates: FrameRates, hub: Any) -> str:
    """The text of ``GET /metrics``."""
    lines: list[str] = []

    def metric(name: str, kind: str, help_: str, samples: list[tuple[str, float]]) -> None:
        lines.append(f"# HELP {name} {help_}")
        lines.append(f"# TYPE {name} {kind}")
        lines.extend(f"{name}{labels} {_num(v)}" for labels, v in samples)

    m = cell.metrics()
    by_id, messages = m["frames_by_id"], m["messages"]
    per_s = rates.rates()

    def id_labels(key: tuple[int, bool]) -> str:
        if key == OTHER_IDS:
            return _labels(id="other", message="unknown")
        ident = f"0x{key[0]:08X}" if key[1] else f"0x{key[0]:03X}"
        return _labels(id=ident, message=messages.get(key, "unknown"))

    keys = sorted(by_id)
    metric("testcell_frames_total", "counter", "CAN frames received, by arbitration ID",
           [(id_labels(k), by_id[k]) for k in keys])
    metric("testcell_frames_per_second", "gauge",
           "CAN frames per second by arbitration ID, over the last second of bus time",
           [(id_labels(k), per_s.get(k, 0.0)) for k in keys])
    metric("testcell_decode_errors_total", "counter", "frames that could not be decoded, by kind",
           [(_labels(kind=k), n) for k, n in sorted(m["decode_errors"].items())])
    metric("testcell_late_frames_total", "counter", "frames older than the newest one seen",
           [("", m["late_frames"])])
    metric("testcell_ticks_total", "counter", "ticks run (FAS, MED and SLO together)",
           [("", m["ticks"])])
    metric("testcell_tick_overruns_total", "counter",
           "ticks whose work took longer than their period", [("", m["tick_overruns"])])
    metric("testcell_tick_seconds_max", "gauge", "wall seconds of the slowest tick so far",
           [("", m["tick_seconds_max"])])
    lines.append("# HELP testcell_block_step_seconds wall seconds spent in each block's step")
    lines.append("# TYPE testcell_block_step_seconds summary")
    for step in m["steps"]:
        labels = _labels(block=step["block"], family=step["family"])
        lines.append(f"testcell_block_step_seconds_sum{labels} {_num(step['seconds'])}")
        lines.append(f"testcell_block_step_seconds_count{labels} {step['count']}")
    metric("testcell_block_errors_total", "counter", "block steps that failed, by block",
           [(_labels(block=n), c) for n, c in sorted(m["block_errors"].items())])
    now = m["bus_time"]
    metric("testcell_bus_time_seconds", "gauge", "the runtime's bus time",
           [("", now if now is not None else float("nan"))])
    ws = sum(1 for c in list(hub.clients) if getattr(c, "kind", "") == "ws")
    metric("testcell_websocket_clients", "gauge", "open WebSocket /stream connections", [("", ws)])
    metric("testcell_stream_clients", "gauge", "WebSocket and SSE stream subscribers",
           [("", len(hub.clients))])
    metric("testcell_stream_connections_total", "counter", "stream connections since start",
           [("", hub.connections_total)])
    metric("testcell_stream_dropped_total", "counter",
           "ticks skipped for stream subscribers too slow to keep up", [("", hub.dropped)])
    return "\n".join(lines) + "\n"
