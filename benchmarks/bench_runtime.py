"""How fast the runtime eats cell traffic, against the CAN bus limit and real time.

Run: ``.venv/bin/python benchmarks/bench_runtime.py [SECONDS]``

Issue 4's goal: one hour of cell traffic through every native filter at >= 1000x real time.
The default replays 600 s of traffic (216 000 frames) and reports x real time; the cost per
frame does not depend on the length, and an hour of frames as Python objects would need
~0.5 GB.

The reference is the most frames a 500 kbit/s classic CAN bus can carry: an 8-byte
standard frame is at most 135 bits with worst-case stuffing (plus 3 bits interframe
space), so 500 000 / 138 ≈ 3623 frames/s. The cell's own traffic is ~360 frames/s.
"""

from __future__ import annotations

import time

from cell import app
from cell.bus.dbc import load
from cell.estimators.backpressure import native_filters
from cell.sim import simulate
from cell.sim.lockstep import feed
from cell.runtime.scheduler import Runtime

BUS_LIMIT_FPS = 500_000 / 138


def main(seconds: float = 600.0) -> dict[str, float]:
    app.load()  # the engine profiles and block sets, as the command line registers them
    db = load()
    frames = list(simulate(db, "transient", seed=0, duration=seconds))
    rt = Runtime(db, native_filters())
    t0 = time.perf_counter()
    feed(rt, frames)
    elapsed = time.perf_counter() - t0

    t1 = time.perf_counter()
    for msg in frames:
        db.decode(msg)
    decode_only = time.perf_counter() - t1

    fps = len(frames) / elapsed
    print(f"{len(frames)} frames ({seconds:.0f} s of cell traffic) through the runtime with "
          f"{len(rt.blocks)} native filters in {elapsed:.2f} s")
    print(f"  runtime:            {fps:10.0f} frames/s = {fps / BUS_LIMIT_FPS:6.2f} x the "
          f"500 kbit/s bus limit ({BUS_LIMIT_FPS:.0f} frames/s), {seconds / elapsed:6.1f} x real time")
    print(f"  cantools decode of every frame, for scale: {len(frames) / decode_only:8.0f} frames/s "
          "(the runtime decodes only the newest frame of each message per tick)")
    print(f"  goal: >= 1000 x real time -> {'met' if seconds / elapsed >= 1000 else 'NOT met'}")
    return {"frames": len(frames), "seconds": seconds, "elapsed_s": elapsed, "fps": fps,
            "decode_fps": len(frames) / decode_only}


if __name__ == "__main__":
    import argparse

    _p = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    _p.add_argument("seconds", nargs="?", type=float, default=600.0,
                    help="simulated seconds of traffic (default 600)")
    main(_p.parse_args().seconds)
