"""Soak: the simulator, the runtime and the API under load for a while, each engine in turn.

Run: ``scripts/soak.sh MINUTES`` (or ``.venv/bin/python benchmarks/soak.py --seconds S``);
``--speed`` (default 20), ``--group`` and ``--port`` (a private udp_multicast group).

For each registered engine profile, ``testcell up --no-sim`` runs with every block and
shipped script loaded, and its simulator (``testcell sim``, its own process) at ``--speed``
times real time, crank-angle streams and all, on the group. Meanwhile:

- a client polls ``GET /channels`` at 20 Hz, timing each request;
- a client reads ``WS /stream`` (every channel) and takes, for each tick it is sent, the
  stream's lag: the wall time it arrives minus the tick's bus time (the runtime stamps
  frames with their receive time, so bus time is wall time);
- an independent listener joined to the group counts the simulator's frames on the wire.

Both clients send ``Host: 127.0.0.1`` and ``Content-Type: application/json``. Frames lost
are the frames the simulator says it sent (it logs its count when it stops) less the frames
the runtime counted (``/health``'s ``frames``). The report per engine: frames sent, on the
wire and received, lost, tick overruns, the stream's p50/p99 lag, the ``/channels``
request p99, the age of the newest value ``/channels`` carries, and the service's RSS
at start, after a warm-up (a quarter of the run, at most 10 s) and at the end.
Goals (issue 20): no frame lost, stream p99 under 100 ms; RSS growth under 20 MB.
The last line is the report as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

BUS_GROUP, BUS_PORT = "239.74.163.252", 43252
SPEED = 20.0
POLL_HZ = 20.0
HEADERS = {"Host": "127.0.0.1", "Content-Type": "application/json"}


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


class WireCounter(threading.Thread):
    """Counts frames the simulator puts on the group (an observer independent of the cell)."""

    def __init__(self, sim_ids: set[int], group: str, port: int) -> None:
        super().__init__(daemon=True)
        from can.interfaces.udp_multicast.utils import unpack_message

        self.unpack = unpack_message
        self.sim_ids = sim_ids
        self.count = 0
        self.by_id: dict[int, int] = {}
        self.stop = threading.Event()
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        try:
            s.setsockopt(socket.SOL_SOCKET, getattr(socket, "SO_RCVBUFFORCE", 33), 8 << 20)
        except OSError:
            pass
        s.bind(("", port))
        s.setsockopt(socket.IPPROTO_IP, 49, 0)  # IP_MULTICAST_ALL off: this group only
        s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                     socket.inet_aton(group) + struct.pack("@I", socket.INADDR_ANY))
        s.settimeout(0.2)
        self.sock = s

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            ident = self.unpack(data).arbitration_id
            if ident in self.sim_ids:
                self.count += 1
                self.by_id[ident] = self.by_id.get(ident, 0) + 1

    def close(self) -> None:
        self.stop.set()
        self.join(2)
        self.sock.close()


def get(url: str, timeout: float = 20.0) -> dict:
    req = urllib.request.Request(url, headers=HEADERS)
    with urllib.request.urlopen(req, timeout=timeout) as r:
        return json.loads(r.read())


def sim_frames_received(base: str, sim_ids: set[int]) -> dict[int, int] | None:
    """Frames of the simulator's IDs the runtime counted (``/metrics``' frames by ID), or
    None when ``/metrics`` does not say. The runtime's own frames, should an echo of one
    come back unrecognised, are not the simulator's."""
    req = urllib.request.Request(f"{base}/metrics", headers=HEADERS)
    text = None
    for _ in range(3):  # a loaded service may take a while: the count by ID is what is compared
        try:
            with urllib.request.urlopen(req, timeout=20) as r:
                text = r.read().decode()
            break
        except OSError:
            time.sleep(1.0)
    if text is None:
        return None
    by_id: dict[int, int] = {}
    seen = False
    for m in re.finditer(r'^testcell_frames_total\{[^}]*id="0x([0-9A-Fa-f]+)"[^}]*\} ([0-9.e+]+)$',
                         text, re.M):
        seen = True
        if int(m[1], 16) in sim_ids:
            by_id[int(m[1], 16)] = int(float(m[2]))
    return by_id if seen else None


def percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    v = sorted(values)
    return v[min(len(v) - 1, int(q * (len(v) - 1) + 0.5))]


def poll_channels(base: str, stop: threading.Event, rtts: list[float], ages: list[float],
                  errors: list[str]) -> None:
    """GET /channels at POLL_HZ: the request's time and the age of its newest bus value."""
    period = 1.0 / POLL_HZ
    due = time.monotonic()
    while not stop.is_set():
        due += period
        try:
            sent = time.time()
            chans = get(f"{base}/channels")
            now = time.time()
            rtts.append(now - sent)
            times = [c["time"] for c in chans if c.get("time") is not None and c.get("status") == "ok"]
            if times:
                ages.append(now - max(times))
        except Exception as exc:  # reported, not raised: the soak goes on
            errors.append(f"/channels: {type(exc).__name__}: {exc}")
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            due = time.monotonic()  # behind: no burst to catch up


def stream_ws(port: int, stop: threading.Event, lags: list[float], got: list[int],
              errors: list[str]) -> None:
    try:
        from websockets.sync.client import connect
    except ImportError:
        errors.append("websockets not installed")
        return
    try:
        with connect(f"ws://127.0.0.1:{port}/stream?channels=*", open_timeout=10,
                     additional_headers={"Content-Type": HEADERS["Content-Type"]},
                     max_size=None) as ws:
            while not stop.is_set():
                try:
                    text = ws.recv(timeout=1.0)
                except TimeoutError:
                    continue
                now = time.time()
                msg = json.loads(text)
                if msg.get("type") == "data":
                    got[0] += 1
                    lags.append(now - msg["time"])
                    got[1] = max(got[1], msg.get("dropped", 0))
    except Exception as exc:
        if not stop.is_set():
            errors.append(f"/stream: {type(exc).__name__}: {exc}")


def soak_engine(engine: str, seconds: float, state_dir: Path, speed: float, group: str,
                bus_port: int) -> dict:
    from cell.bus.dbc import load
    from cell.core.settings import Settings
    from cell.sim import build

    db = load()
    sim = build(Settings.build({"engine": engine}, environ={}), db)
    sim_ids = {m.frame_id for m, _, _ in sim.schedule}
    sim_ids |= {db.message(layout.message).frame_id for _, layout, _ in sim.streams}  # crank frames
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    base = f"http://127.0.0.1:{port}"
    bus = f"udp_multicast:{group}:{bus_port}"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("TESTCELL_TOKEN", None)
    up = subprocess.Popen([sys.executable, "-m", "cell", "--log-level", "WARNING", "up", "--no-sim",
                           "--engine", engine, "--bus", bus, "--port", str(port),
                           "--state", str(state_dir / f"{engine}.json")],
                          cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    counter = WireCounter(sim_ids, group, bus_port)
    counter.start()
    sim_proc = None
    stop = threading.Event()
    lags: list[float] = []
    rtts: list[float] = []
    ages: list[float] = []
    errors: list[str] = []
    ws_got = [0, 0]
    sim_log = ""
    threads: list[threading.Thread] = []
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                get(f"{base}/health")
                break
            except OSError:
                time.sleep(0.2)
        rss_start = rss_mb(up.pid)
        threads = [threading.Thread(target=poll_channels, args=(base, stop, rtts, ages, errors),
                                    daemon=True),
                   threading.Thread(target=stream_ws, args=(port, stop, lags, ws_got, errors),
                                    daemon=True)]
        for t in threads:
            t.start()
        time.sleep(1.0)  # the clients are connected before the first frame
        h0 = get(f"{base}/health")
        by_id0 = sim_frames_received(base, sim_ids)
        sim_proc = subprocess.Popen([sys.executable, "-m", "cell", "--log-level", "INFO", "sim",
                                     "--engine", engine, "--bus", bus, "--speed", f"{speed:g}"],
                                    cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.PIPE, text=True)
        start_by = time.monotonic() + 120  # the simulator starts (its plants settle) first
        while counter.count == 0 and time.monotonic() < start_by and sim_proc.poll() is None:
            time.sleep(0.05)
        t_sim = time.monotonic()
        time.sleep(min(10.0, seconds / 4))  # warm-up: buffers and caches fill once
        rss_warm = rss_mb(up.pid)
        time.sleep(max(0.0, seconds - (time.monotonic() - t_sim)))
        sim_proc.send_signal(signal.SIGTERM)
        _, sim_log = sim_proc.communicate(timeout=60)
        sim_wall = time.monotonic() - t_sim
        last, settle = -1, time.monotonic() + 10  # frames in flight reach the runtime
        while time.monotonic() < settle:
            frames = get(f"{base}/health")["frames"]
            if frames == last:
                break
            last = frames
            time.sleep(0.5)
        stop.set()
        for t in threads:
            t.join(5)
        h = get(f"{base}/health")
        by_id1 = sim_frames_received(base, sim_ids)
        rss_end = rss_mb(up.pid)
    finally:
        stop.set()
        if sim_proc is not None and sim_proc.poll() is None:
            sim_proc.kill()
            sim_proc.communicate()
        up.terminate()
        try:
            out, _ = up.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            up.kill()
            out, _ = up.communicate()
        counter.close()
    m = re.findall(r"sim sent (\d+) frames", sim_log)
    sent = int(m[-1]) if m else None
    # without /metrics' count by ID, the frames of every sender (the runtime's own echoes
    # too, should any be missed) are all the soak has: said so in the report
    received = h["frames"] - h0["frames"]
    by_id_known = by_id0 is not None and by_id1 is not None
    over: dict[str, int] = {}
    if by_id0 is not None and by_id1 is not None:
        got = {k: v - by_id0.get(k, 0) for k, v in by_id1.items()}
        received = sum(got.values())  # the simulator's frames only
        over = {f"0x{k:X}": n - counter.by_id.get(k, 0) for k, n in got.items()
                if n != counter.by_id.get(k, 0)}
    sim_s = re.findall(r"at t=([\d.]+) s", sim_log)
    return {
        "engine": engine, "seconds": round(sim_wall, 1), "speed": speed,
        "sim_sent": sent, "wire_frames": counter.count, "runtime_frames": received,
        "lost": max(0, sent - received) if sent is not None else None,
        "counted_beyond_sent": max(0, received - sent) if sent is not None else None,
        "runtime_minus_wire_by_id": over,
        "counted_by_id": by_id_known,
        "bus_fps": round(counter.count / sim_wall) if sim_wall else 0,
        "tick_overruns": h.get("tick_overruns", "not counted on this branch"),
        "stream_messages": ws_got[0], "stream_dropped": ws_got[1],
        "stream_p50_ms": round(percentile(lags, 0.5) * 1000, 1),
        "stream_p99_ms": round(percentile(lags, 0.99) * 1000, 1),
        "channels_requests": len(rtts),
        "channels_p99_request_ms": round(percentile(rtts, 0.99) * 1000, 1),
        "channels_p99_age_ms": round(percentile(ages, 0.99) * 1000, 1),
        "rss_start_mb": round(rss_start, 1), "rss_warm_mb": round(rss_warm, 1),
        "rss_end_mb": round(rss_end, 1), "rss_growth_mb": round(rss_end - rss_warm, 1),
        "errors": errors[:5], "service_errors": [ln for ln in out.splitlines() if " ERROR " in ln][:5],
        "sim_errors": [ln for ln in sim_log.splitlines() if " ERROR " in ln or "Traceback" in ln][:5],
        "status": h["status"], "bad_frames": {k: v for k, v in h.get("decode_errors", {}).items() if v},
        "sim_last_event_s": float(sim_s[-1]) if sim_s else None,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="soak the cell under load, each engine in turn")
    p.add_argument("minutes", nargs="?", type=float, default=None,
                   help="total length over all engines, minutes (default 2)")
    p.add_argument("--seconds", type=float, default=None, help="total length, s (overrides minutes)")
    p.add_argument("--speed", type=float, default=SPEED, help=f"simulator speed (default {SPEED:g})")
    p.add_argument("--speed-for", action="append", default=[], metavar="ENGINE=SPEED",
                   help="another speed for one engine (repeatable), e.g. si-turbo=2")
    p.add_argument("--engine", action="append", default=None,
                   help="soak only this engine (repeatable; default every registered one)")
    p.add_argument("--group", default=BUS_GROUP, help=f"udp_multicast group (default {BUS_GROUP})")
    p.add_argument("--port", type=int, default=BUS_PORT, help=f"udp_multicast port (default {BUS_PORT})")
    args = p.parse_args(argv)
    total = args.seconds if args.seconds is not None else (args.minutes or 2.0) * 60.0
    from cell import app
    from cell.core import registry

    app.load()
    engines = args.engine or sorted(registry.ENGINES)
    speeds = {e: args.speed for e in engines}
    for item in args.speed_for:
        name, sep, value = item.partition("=")
        if not sep or name not in speeds:
            p.error(f"--speed-for {item!r}: give ENGINE=SPEED with ENGINE one of {', '.join(engines)}")
        speeds[name] = float(value)
    state_dir = Path(os.environ.get("TMPDIR", "/tmp")) / f"testcell-soak-{os.getpid()}"
    state_dir.mkdir(parents=True, exist_ok=True)
    results = []
    load0 = os.getloadavg()[0]
    for engine in engines:
        print(f"soak {engine}: {total / len(engines):.0f} s at --speed {speeds[engine]:g} ...",
              file=sys.stderr, flush=True)
        r = soak_engine(engine, total / len(engines), state_dir, speeds[engine], args.group,
                        args.port)
        r["load_1min"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
        print(f"  simulator sent {r['sim_sent']} frames ({r['bus_fps']}/s on the wire), runtime "
              f"counted {r['runtime_frames']}, lost {r['lost']}; stream p50 {r['stream_p50_ms']} ms, "
              f"p99 {r['stream_p99_ms']} ms over {r['stream_messages']} ticks "
              f"(dropped {r['stream_dropped']}); /channels p99 {r['channels_p99_request_ms']} ms "
              f"over {r['channels_requests']} requests; tick overruns {r['tick_overruns']}; RSS "
              f"{r['rss_start_mb']} -> {r['rss_warm_mb']} -> {r['rss_end_mb']} MB; "
              f"status {r['status']}", file=sys.stderr, flush=True)
        results.append(r)
    print(json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
