"""The simulator against real time: each engine's plants stepped and every frame encoded.

Run: ``.venv/bin/python benchmarks/bench_sim.py [SECONDS] [--engine NAME] [--bus SPEC]``

Real time allows one plant step of ``dt`` (10 ms) per ``dt`` of wall time, with the frames
of that step encoded, in CPU time (for si-turbo the crank-angle streams too: 1 610 frames per simulated
second). The ratio printed is simulated seconds over wall seconds: the ``--speed`` the
simulator can offer. Goal (issue 20 point 8): >= 20x real time for si-turbo, crank
streams on. ``--bus`` also sends every frame on that bus (a private udp_multicast group:
``udp_multicast:239.74.163.206:43206``), as ``testcell sim`` does.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

GOAL = 20.0


def measure(engine: str, seconds: float, bus_spec: str | None = None,
            reference: bool = False) -> dict[str, float]:
    """Time ``seconds`` of ``engine``; ``reference``: with the air path's reference
    integrator (:func:`cell.plant.si_airpath.rk4` over ``airpath_rhs``) in place of the
    plant's compiled one, and every frame encoded by :meth:`CellDatabase.encode` (stream
    frames one by one instead of in bulk, cyclic frames through cantools instead of
    :mod:`cell.sim.frame_encode`), the same run otherwise. Times are CPU time
    (``time.process_time``), so other load on the machine does not count."""
    from cell.core.settings import Settings
    from cell.plant.si_airpath import SIAirPath, rk4
    from cell.sim import build

    sim = build(Settings.build({"engine": engine}, environ={}))
    if reference:
        sim._bulk = {}
        sim._fast = {}
        for plant in sim.plant.plants:
            if isinstance(plant, SIAirPath):
                plant._rk4 = lambda x, u, h, n, _p=plant.params: rk4(x, u, _p, h, n)
    bus = None
    if bus_spec:
        from cell.bus.interface import open_bus

        bus = open_bus(bus_spec)
    steps = round(seconds / sim.dt)
    for _ in range(round(1.0 / sim.dt)):  # one simulated second of warm-up
        sim.frames()
        sim.step()
    frames = 0
    t0 = time.process_time()
    try:
        for _ in range(steps):
            out = sim.frames()
            if bus is not None:
                for msg in out:
                    bus.send(msg)
            frames += len(out)
            sim.step()
    finally:
        if bus is not None:
            bus.shutdown()
    wall = time.process_time() - t0
    return {"engine": engine, "sim_s": seconds, "wall_s": wall, "x_real_time": seconds / wall,
            "frames": frames, "frames_per_s": frames / wall}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    p.add_argument("seconds", nargs="?", type=float, default=20.0,
                   help="simulated seconds timed (default 20)")
    p.add_argument("--engine", action="append", default=None,
                   help="engine profile (repeatable; default every registered one)")
    p.add_argument("--bus", default=None, help="also send every frame on this bus")
    args = p.parse_args(argv)
    from cell import app
    from cell.core import registry

    app.load()
    for engine in args.engine or sorted(registry.ENGINES):
        r = measure(engine, args.seconds, args.bus)
        load = os.getloadavg()[0]
        goal = "" if engine != "si-turbo" else (
            f" (goal {GOAL:g}x: {'met' if r['x_real_time'] >= GOAL else 'not yet'})")
        print(f"{engine:<14} {r['x_real_time']:6.1f} x real time{goal}, {r['frames_per_s']:,.0f} "
              f"frames/s ({r['frames'] / r['sim_s']:,.0f} per simulated second)"
              f"{' sent on ' + args.bus if args.bus else ', encoded, not sent'}; CPU time, load "
              f"{load:.1f}", flush=True)
        if engine == "si-turbo":
            ref = measure(engine, args.seconds, args.bus, reference=True)
            gain = r["x_real_time"] / ref["x_real_time"]
            print(f"{'':<14} {ref['x_real_time']:6.1f} x real time with the reference air-path "
                  f"integrator and cantools encoding, same process: {gain:.2f} x as fast now",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
