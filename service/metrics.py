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

from cell.runtime.scheduler import OTHER_IDS, Runtime

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


class FrameRates:
    """Frames per second by ID over the last whole second of bus time."""

    def __init__(self, runtime: Runtime, window_s: float = 1.0) -> None:
        self.runtime = runtime
        self.window_s = window_s
        self._prev: tuple[float, dict] | None = None
        self._last: tuple[float, dict] | None = None
        runtime.tick_listeners.append(self.on_tick)

    def on_tick(self, t: float) -> None:
        if self._last is None or t - self._last[0] >= self.window_s - 1e-9:
            self._prev, self._last = self._last, (t, dict(self.runtime.frames_by_id))

    def rates(self) -> dict[tuple[int, bool], float]:
        if self._prev is None or self._last is None:
            return {}
        (t0, c0), (t1, c1) = self._prev, self._last
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


def render(runtime: Runtime, rates: FrameRates, hub: Any) -> str:
    """The text of ``GET /metrics``."""
    lines: list[str] = []

    def metric(name: str, kind: str, help_: str, samples: list[tuple[str, float]]) -> None:
        lines.append(f"# HELP {name} {help_}")
        lines.append(f"# TYPE {name} {kind}")
        lines.extend(f"{name}{labels} {_num(v)}" for labels, v in samples)

    with runtime.lock:
        db = runtime.db
        by_id = dict(runtime.frames_by_id)
        per_s = rates.rates()

        def id_labels(key: tuple[int, bool]) -> str:
            if key == OTHER_IDS:
                return _labels(id="other", message="unknown")
            msg = db._by_id.get(key)
            ident = f"0x{key[0]:08X}" if key[1] else f"0x{key[0]:03X}"
            return _labels(id=ident, message=msg.name if msg is not None else "unknown")

        keys = sorted(by_id)
        metric("testcell_frames_total", "counter", "CAN frames received, by arbitration ID",
               [(id_labels(k), by_id[k]) for k in keys])
        metric("testcell_frames_per_second", "gauge",
               "CAN frames per second by arbitration ID, over the last second of bus time",
               [(id_labels(k), per_s.get(k, 0.0)) for k in keys])
        metric("testcell_decode_errors_total", "counter", "frames that could not be decoded, by kind",
               [(_labels(kind=k), n) for k, n in sorted(runtime.decode_errors.items())])
        metric("testcell_late_frames_total", "counter", "frames older than the newest one seen",
               [("", runtime.late_frames)])
        metric("testcell_ticks_total", "counter", "ticks run (FAS, MED and SLO together)",
               [("", runtime.ticks)])
        metric("testcell_tick_overruns_total", "counter",
               "ticks whose work took longer than their period", [("", runtime.tick_overruns)])
        metric("testcell_tick_seconds_max", "gauge", "wall seconds of the slowest tick so far",
               [("", runtime.tick_seconds_max)])
        blocks = [(n, runtime.blocks[n].family, runtime.step_time[n])
                  for n in sorted(runtime.step_time) if n in runtime.blocks]
        lines.append("# HELP testcell_block_step_seconds wall seconds spent in each block's step")
        lines.append("# TYPE testcell_block_step_seconds summary")
        for n, fam, (secs, count) in blocks:
            lines.append(f"testcell_block_step_seconds_sum{_labels(block=n, family=fam)} {_num(secs)}")
            lines.append(f"testcell_block_step_seconds_count{_labels(block=n, family=fam)} {count}")
        metric("testcell_block_errors_total", "counter", "block steps that failed, by block",
               [(_labels(block=n), c) for n, c in sorted(runtime.block_errors.items())])
        now = runtime.now
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
