"""The runtime's ingest path on CPU time: receive, decode, ticks and blocks, per frame.

Run: ``.venv/bin/python benchmarks/bench_ingest.py [--frames N] [--engine NAME] [--group G --port P]``

Each engine's own flood traffic (``bench_suite.py``'s: 20 s of its duty cycle, for si-turbo
the crank-angle streams too, packed once in python-can's udp_multicast wire format) is sent
over a private udp_multicast group to a consumer in this process, as fast as the consumer
takes it: the sender keeps at most ``--window`` frames outstanding (far less than the
socket's buffer holds), so the socket is never empty (the consumer works at saturation, as
at its lossless ceiling) and never overflows (the kernel's drop count is printed; it stays
0). The consumer's cost is the CPU time of its own thread
(``time.pthread_getcpuclockid``), which other processes on a loaded machine do not inflate
as they do the wall clock. Consumers, each run on the same traffic:

- **reference**: python-can's bare ``UdpMulticastBus.recv`` loop, counting frames and
  nothing else (no decode, no runtime);
- **previous path**: the live runtime (``LiveCell``, the engine's blocks loaded, as
  ``testcell up`` runs it) receiving frame by frame through python-can's ``recv``;
- **this build**: the same runtime with its batch receive (``CellBus.recv_batch``).

For each: CPU µs per frame, the lossless ceiling it implies on one core (1e6 / µs), the
ratio to the reference, and the share of the runtime thread's CPU spent in the blocks'
own steps and sample hand-overs (the observers' cost, measured with ``time.thread_time``
around each call). 45 000 frames/s on one core leave 22 µs per frame for everything.
The load average is printed beside the numbers. The last line is the result as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path[:0] = [str(ROOT), str(HERE)]

GROUP, PORT = "239.74.163.248", 43248
GOAL_FPS = 45_000


def traffic(engine: str) -> list[bytes]:
    """The engine's flood traffic, packed (``bench_suite.flood``'s)."""
    from can.interfaces.udp_multicast.utils import pack_message

    from bench_suite import FLOOD_DUTY, FLOOD_SIM_S
    from cell.bus.dbc import load
    from cell.sim import simulate

    return [pack_message(m) for m in simulate(load(), FLOOD_DUTY.get(engine, "rated"), seed=0,
                                              duration=FLOOD_SIM_S, engine=engine)]


def thread_cpu(thread: threading.Thread) -> float:
    """CPU seconds ``thread`` has used so far."""
    return time.clock_gettime(time.pthread_getcpuclockid(thread.ident))


def drive(packed: list[bytes], n: int, received, dest: tuple[str, int], window: int,
          chunk: int = 500) -> tuple[int, float]:
    """Send ``n`` datagrams, keeping at most ``window`` not yet ``received()``; then wait for
    the consumer to take them (or 3 s without progress). Returns (sent, wall seconds)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
    sent, total, t0 = 0, len(packed), time.perf_counter()
    try:
        while sent < n:
            if sent - received() > window - chunk:
                time.sleep(0.0005)
                continue
            for _ in range(min(chunk, n - sent)):
                sock.sendto(packed[sent % total], dest)
                sent += 1
        last, still = -1, time.monotonic()
        while received() < sent and time.monotonic() - still < 3.0:
            got = received()
            if got != last:
                last, still = got, time.monotonic()
            time.sleep(0.002)
    finally:
        sock.close()
    return sent, time.perf_counter() - t0


class BlockCpu:
    """The CPU time of the blocks' own calls (step, samples, gap), on the calling thread."""

    def __init__(self, runtime) -> None:
        self.seconds = 0.0
        for block in runtime.blocks.values():
            for name in ("step", "samples", "gap") if block.streams else ("step",):
                real = getattr(block, name)

                def timed(*args, _real=real, **kwargs):
                    t = time.thread_time()
                    try:
                        return _real(*args, **kwargs)
                    finally:
                        self.seconds += time.thread_time() - t

                setattr(block, name, timed)


def run_reference(packed: list[bytes], n: int, bus_spec: str, dest, window: int) -> dict:
    """python-can's bare recv loop: frames counted, nothing decoded."""
    from cell.bus.drops import kernel_drops
    from cell.bus.interface import open_bus

    bus = open_bus(bus_spec)
    raw = bus.bus
    count = [0]
    stop = threading.Event()

    def loop() -> None:
        recv = raw.recv
        while not stop.is_set():
            if recv(0.01) is not None:
                count[0] += 1

    th = threading.Thread(target=loop, daemon=True)
    th.start()
    try:
        cpu0 = thread_cpu(th)
        sent, wall = drive(packed, n, lambda: count[0], dest, window)
        cpu = thread_cpu(th) - cpu0
        drops = kernel_drops(bus)
    finally:
        stop.set()
        th.join(2)
        bus.shutdown()
    return {"sent": sent, "received": count[0], "cpu_s": cpu, "wall_s": wall,
            "kernel_drops": drops, "blocks_cpu_s": 0.0}


def run_runtime(engine: str, packed: list[bytes], n: int, bus_spec: str, dest, window: int,
                per_frame: bool) -> dict:
    """The live runtime of ``engine`` (its blocks loaded) on the traffic."""
    from bench_suite import full_runtime
    from cell.app.live import LiveCell
    from cell.bus.drops import kernel_drops
    from cell.bus.interface import open_bus

    rt = full_runtime(engine)
    blocks = BlockCpu(rt)
    bus = open_bus(bus_spec)
    live = LiveCell(rt, bus)
    live.per_frame = per_frame
    live.start()
    try:
        time.sleep(0.2)
        cpu0, b0 = thread_cpu(live._thread), blocks.seconds
        sent, wall = drive(packed, n, lambda: rt.frames, dest, window)
        cpu, bcpu = thread_cpu(live._thread) - cpu0, blocks.seconds - b0
        drops = kernel_drops(bus)
    finally:
        live.stop()
        bus.shutdown()
    return {"sent": sent, "received": rt.frames, "cpu_s": cpu, "wall_s": wall,
            "kernel_drops": drops, "blocks_cpu_s": bcpu, "blocks": len(rt.blocks)}


def measure(engine: str, n: int, bus_spec: str, window: int) -> list[dict]:
    from cell.bus.interface import resolve

    spec = resolve(bus_spec)
    dest = (spec.channel, spec.port)
    packed = traffic(engine)
    runs = [("python-can recv loop alone (reference)",
             lambda: run_reference(packed, n, bus_spec, dest, window)),
            ("runtime, python-can recv frame by frame (previous receive)",
             lambda: run_runtime(engine, packed, n, bus_spec, dest, window, per_frame=True)),
            ("runtime, batch receive (this build)",
             lambda: run_runtime(engine, packed, n, bus_spec, dest, window, per_frame=False))]
    rows = []
    ref_us = None
    for name, run in runs:
        r = run()
        us = r["cpu_s"] / max(1, r["received"]) * 1e6
        ref_us = us if ref_us is None else ref_us
        row = {"engine": engine, "path": name, **r, "us_per_frame": us,
               "ceiling_fps": 1e6 / us if us > 0 else float("inf"),
               "x_reference": us / ref_us,
               "blocks_share": r["blocks_cpu_s"] / r["cpu_s"] if r["cpu_s"] else 0.0,
               "load_1min": round(os.getloadavg()[0], 2)}
        rows.append(row)
        print(f"  {engine:13s} {name:52s} {us:6.2f} µs/frame  ceiling {row['ceiling_fps']:8,.0f}/s  "
              f"{row['x_reference']:5.2f} x ref  blocks {row['blocks_share']:5.1%}  "
              f"(got {r['received']:,} of {r['sent']:,}, kernel drops {r['kernel_drops']}, "
              f"load {row['load_1min']})", flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("--frames", type=int, default=60_000, help="frames per run (default 60000)")
    p.add_argument("--engine", action="append", default=None,
                   help="this engine's traffic and blocks (repeatable; default every engine)")
    p.add_argument("--group", default=GROUP, help=f"udp_multicast group (default {GROUP})")
    p.add_argument("--port", type=int, default=PORT, help=f"udp_multicast port (default {PORT})")
    p.add_argument("--window", type=int, default=4_000,
                   help="most frames outstanding at the consumer (default 4000)")
    args = p.parse_args(argv)
    from cell import app
    from cell.core import registry

    app.load()
    engines = args.engine or sorted(registry.ENGINES)
    bus_spec = f"udp_multicast:{args.group}:{args.port}"
    print(f"load average {os.getloadavg()[0]:.2f}; {args.frames:,} frames per run; goal "
          f"{GOAL_FPS:,} frames/s = {1e6 / GOAL_FPS:.1f} µs/frame", flush=True)
    rows = [r for e in engines for r in measure(e, args.frames, bus_spec, args.window)]
    print(json.dumps(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
