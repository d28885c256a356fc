"""Soak: the simulator, the runtime and the API under load for a while, each engine in turn.

Run: ``scripts/soak.sh MINUTES`` (or ``.venv/bin/python benchmarks/soak.py --seconds S``).

For each registered engine profile, ``testcell up`` runs with every block and shipped script
loaded and its simulator at a ``--speed`` that puts at least 5 000 frames/s on the bus (a
private udp_multicast group and port). Meanwhile:

- an independent listener joined to the group counts the simulator's frames on the wire;
- a client polls REST (a bus channel's value, ``/health``) as fast as it can, timing each
  request;
- a client reads ``/stream`` over WebSocket when the API has that route.

It reports per engine: frames on the wire, frames the runtime counted, frames lost by the
runtime, tick overruns (when ``/health`` counts them), p99 latency from frame to API (the age
of the newest value an API answer carries: wall time of the answer minus the frame's
receive time, which udp_multicast stamps) and the RSS of the service at start, after a
warm-up (a quarter of the run, at most 10 s) and at the end; growth is counted from the
warm-up.
Goals for 30 minutes (issue 13): no frame lost, RSS growth under 20 MB, p99 under 20 ms.
The last line is the report as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
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
TARGET_FPS = 5000


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


class WireCounter(threading.Thread):
    """Counts frames the simulator puts on the group (an observer independent of the cell)."""

    def __init__(self, sim_ids: set[int]) -> None:
        super().__init__(daemon=True)
        from can.interfaces.udp_multicast.utils import unpack_message

        self.unpack = unpack_message
        self.sim_ids = sim_ids
        self.count = 0
        self.stop = threading.Event()
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        try:
            s.setsockopt(socket.SOL_SOCKET, getattr(socket, "SO_RCVBUFFORCE", 33), 8 << 20)
        except OSError:
            pass
        s.bind(("", BUS_PORT))
        s.setsockopt(socket.IPPROTO_IP, 49, 0)  # IP_MULTICAST_ALL off: this group only
        s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                     socket.inet_aton(BUS_GROUP) + struct.pack("@I", socket.INADDR_ANY))
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
            if self.unpack(data).arbitration_id in self.sim_ids:
                self.count += 1

    def close(self) -> None:
        self.stop.set()
        self.join(2)
        self.sock.close()


def get(url: str, token: str | None = None) -> dict:
    req = urllib.request.Request(url)
    with urllib.request.urlopen(req, timeout=5) as r:
        return json.loads(r.read())


def poll_rest(base: str, channel: str, stop: threading.Event, ages: list[float],
              errors: list[str], rtts: list[float] | None = None) -> None:
    seen = False
    while not stop.is_set():
        try:
            sent = time.time()
            ch = get(f"{base}/channels/{channel}")
            now = time.time()
            if rtts is not None:
                rtts.append(now - sent)
            seen = True
            if ch["time"] is not None and ch["status"] == "ok":
                ages.append(now - ch["time"])
            get(f"{base}/health")
        except Exception as exc:  # reported, not raised: the soak goes on
            if seen or "404" not in str(exc):  # before the first frame the channel is unknown
                errors.append(f"{type(exc).__name__}: {exc}")
            time.sleep(0.05)


def stream_ws(port: int, stop: threading.Event, got: list[int], errors: list[str]) -> None:
    try:
        from websockets.sync.client import connect
    except ImportError:
        errors.append("websockets not installed")
        return
    try:
        with connect(f"ws://127.0.0.1:{port}/stream", open_timeout=5) as ws:
            while not stop.is_set():
                try:
                    ws.recv(timeout=1.0)
                    got[0] += 1
                except TimeoutError:
                    continue
    except Exception as exc:
        errors.append(f"/stream: {type(exc).__name__}: {exc}")


def soak_engine(engine: str, seconds: float, state_dir: Path) -> dict:
    from cell.core import registry
    from cell.bus.dbc import load
    from cell.core.settings import Settings
    from cell.sim import build

    db = load()
    sim = build(Settings.build({"engine": engine}, environ={}), db)
    # frames per simulated second, counted over the first 5 s (crank-angle streams included)
    steps = round(5.0 / sim.dt)
    sent = 0
    for _ in range(steps):
        sent += len(sim.frames())
        sim.step()
    fps_real = sent / 5.0
    speed = max(1.0, round(TARGET_FPS / fps_real + 0.5))
    sim_ids = {m.frame_id for m, _, _ in sim.schedule}
    sim_ids |= {db.message(layout.message).frame_id for _, layout, _ in sim.streams}  # crank frames
    probe = next((s for m, _, names in sim.schedule for s in names if not s.endswith("_TRUE")), None)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    base = f"http://127.0.0.1:{port}"
    bus = f"udp_multicast:{BUS_GROUP}:{BUS_PORT}"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("TESTCELL_TOKEN", None)
    up = subprocess.Popen([sys.executable, "-m", "cell", "--log-level", "WARNING", "up", "--no-sim",
                           "--engine", engine, "--bus", bus, "--port", str(port),
                           "--state", str(state_dir / f"{engine}.json")],
                          cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    counter = WireCounter(sim_ids)
    counter.start()
    sim_proc = None
    stop = threading.Event()
    ages: list[float] = []
    rtts: list[float] = []
    errors: list[str] = []
    ws_got = [0]
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                get(f"{base}/health")
                break
            except OSError:
                time.sleep(0.2)
        paths = get(f"{base}/openapi.json")["paths"]
        rss_start = rss_mb(up.pid)
        h0 = get(f"{base}/health")
        sim_proc = subprocess.Popen([sys.executable, "-m", "cell", "--log-level", "WARNING", "sim",
                                     "--engine", engine, "--bus", bus, "--speed", str(speed),
                                     "--duration", str(seconds * speed)],
                                    cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.DEVNULL)
        threads = [threading.Thread(target=poll_rest, args=(base, probe, stop, ages, errors, rtts),
                                    daemon=True)]
        if "/stream" in paths or any(p.startswith("/stream") for p in paths):
            threads.append(threading.Thread(target=stream_ws, args=(port, stop, ws_got, errors),
                                            daemon=True))
        for t in threads:
            t.start()
        time.sleep(min(10.0, seconds / 4))  # warm-up: buffers and caches fill once
        rss_warm = rss_mb(up.pid)
        sim_proc.wait(seconds + 60)
        time.sleep(1.0)  # frames in flight
        stop.set()
        for t in threads:
            t.join(5)
        h = get(f"{base}/health")
        rss_end = rss_mb(up.pid)
    finally:
        stop.set()
        if sim_proc is not None and sim_proc.poll() is None:
            sim_proc.kill()
        up.terminate()
        try:
            out, _ = up.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            up.kill()
            out, _ = up.communicate()
        counter.close()
    ages.sort()
    rtts.sort()
    p99 = ages[int(0.99 * (len(ages) - 1))] * 1000 if ages else float("nan")
    p99_rtt = rtts[int(0.99 * (len(rtts) - 1))] * 1000 if rtts else float("nan")
    received = h["frames"] - h0["frames"]
    return {
        "engine": engine, "seconds": seconds, "speed": speed,
        "bus_fps": round(counter.count / seconds),
        "wire_frames": counter.count, "runtime_frames": received,
        "lost": counter.count - received,
        "tick_overruns": h.get("tick_overruns", "not counted on this branch"),
        "p99_latency_ms": round(p99, 2), "p99_request_ms": round(p99_rtt, 2),
        "api_samples": len(ages),
        "stream_messages": ws_got[0] if len(threads) > 1 else "no /stream on this branch",
        "rss_start_mb": round(rss_start, 1), "rss_warm_mb": round(rss_warm, 1),
        "rss_end_mb": round(rss_end, 1), "rss_growth_mb": round(rss_end - rss_warm, 1),
        "errors": errors[:5], "service_errors": [ln for ln in out.splitlines() if " ERROR " in ln][:5],
        "status": h["status"], "bad_frames": {k: v for k, v in h["decode_errors"].items() if v},
        "registered_engines": sorted(registry.ENGINES),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="soak the cell under load, each engine in turn")
    p.add_argument("minutes", nargs="?", type=float, default=None)
    p.add_argument("--seconds", type=float, default=None, help="total length, s (overrides minutes)")
    args = p.parse_args(argv)
    total = args.seconds if args.seconds is not None else (args.minutes or 2.0) * 60.0
    from cell import app
    from cell.core import registry

    app.load()
    engines = sorted(registry.ENGINES)
    state_dir = Path(os.environ.get("TMPDIR", "/tmp")) / f"testcell-soak-{os.getpid()}"
    state_dir.mkdir(parents=True, exist_ok=True)
    results = []
    for engine in engines:
        print(f"soak {engine}: {total / len(engines):.0f} s ...", file=sys.stderr, flush=True)
        r = soak_engine(engine, total / len(engines), state_dir)
        print(f"  {r['wire_frames']} frames on the wire ({r['bus_fps']}/s at --speed {r['speed']}), "
              f"runtime counted {r['runtime_frames']}, lost {r['lost']}; p99 frame->API "
              f"{r['p99_latency_ms']} ms over {r['api_samples']} answers (p99 request "
              f"{r['p99_request_ms']} ms); RSS {r['rss_start_mb']} MB "
              f"at start, {r['rss_warm_mb']} after warm-up, {r['rss_end_mb']} at the end "
              f"({r['rss_growth_mb']:+} MB); tick overruns {r['tick_overruns']}", file=sys.stderr)
        results.append(r)
    print(json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
