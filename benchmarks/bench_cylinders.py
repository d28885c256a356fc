"""Seed 001's observers against the real-time budget of a 6 deg stream at 6000 rpm.

Run: ``.venv/bin/python benchmarks/bench_cylinders.py [SECONDS]``

At 6000 rpm a crank-angle stream brings 6000 samples/s (one every 6 deg), so real time allows
1/6000 s = 167 µs per sample for each observer. Goal: >= 20x real time on one core, i.e.
<= 8.3 µs per sample. The observers are vectorised per frame: each is a linear periodic
system whose transitions over a frame's four samples are multiplied out once per start angle
(:class:`cell.estimators.periodic.LinearPeriodic`), so a frame costs two small matrix
products and no per-sample Python loop (no numba).

Three lines per observer: the observer alone (``samples()`` on frames already decoded), and
the whole runtime path (each stream frame unpacked from its bytes, the order tracker, both
observers), against the same budget.

Last, the AFR inversion over ``--ftp`` seconds of the FTP cycle (a drive sweeping the speed):
the designs its speed grid made in the runtime's thread (issue 18: 701 redesigns in 120 s,
~19 ms each, before the grid) and the longest single frame of samples.
"""

from __future__ import annotations

import time

from cell.bus.dbc import load
from cell.estimators.cylinders import RodInversion, UegoInversion
from cell.sim.lockstep import Lockstep
from cell.plant.si_engine import steady_cycle
from cell.plant.si_turbo import si_turbo
from cell.runtime.scheduler import Runtime
from cell.sim.simulator import Simulator
from cell.runtime.samples import find_sample_streams

RPM = 6000.0
BUDGET_SPS = RPM / 60.0 * 360.0 / 6.0  # samples per second of one stream


def main(seconds: float = 10.0) -> None:
    db = load()
    sim = Simulator(si_turbo(steady_cycle(RPM, 0.5, seconds), 0), db)
    frames = list(Lockstep(sim).frames(round(seconds / sim.dt)))
    layouts = {db.message(la.message).frame_id: la for la in find_sample_streams(db.messages).values()}
    decoded: dict[str, list] = {"AFR_UEGO": [], "N_CRANK": []}
    for f in frames:
        la = layouts.get(f.arbitration_id)
        if la is not None and la.name in decoded:
            decoded[la.name].append((*la.unpack(db.decode(f)[1]), f.timestamp))
    n = {k: 4 * len(v) for k, v in decoded.items()}
    print(f"{seconds:g} s at {RPM:.0f} rpm: {n['AFR_UEGO']} samples per stream "
          f"(budget: real time is {BUDGET_SPS:.0f} samples/s = {1e6 / BUDGET_SPS:.0f} µs/sample)")
    for block, stream in ((UegoInversion(), "AFR_UEGO"), (RodInversion(), "N_CRANK")):
        block.step(0.0, {"ENGINE_SPEED": RPM})
        block.samples(stream, *decoded[stream][0])  # designs and caches outside the timing
        grid = getattr(block, "_grid", None)
        while grid is not None and not grid.idle():  # the neighbouring bands, made ahead
            time.sleep(0.01)
        t0 = time.perf_counter()
        for index, values, t in decoded[stream]:
            block.samples(stream, index, values, t)
        dt = time.perf_counter() - t0
        sps = n[stream] / dt
        print(f"  {block.name:<14} {1e6 / sps:6.2f} µs/sample = {sps / BUDGET_SPS:6.1f} x real time "
              f"(goal 20x: {'met' if sps / BUDGET_SPS >= 20 else 'NOT met'})")
    stream_frames = [f for f in frames if f.arbitration_id in
                     {db.message(m).frame_id for m in ("CRANK_AFR_UEGO", "CRANK_N")}]
    rt = Runtime(db, [UegoInversion(), RodInversion()])
    eng = [f for f in frames if f.arbitration_id == db.message("ENGINE_1").frame_id]
    rt.ingest_many(eng[:2])
    rt.advance(eng[1].timestamp + 0.1)  # a tick gives the AFR observer the engine speed
    later = [f for f in stream_frames if f.timestamp > eng[1].timestamp + 0.1]
    t0 = time.perf_counter()
    rt.ingest_many(later)
    dt = time.perf_counter() - t0
    sps = 4 * len(later) / 2 / dt
    print(f"  runtime path (decode + tracker + both observers): {1e6 / sps:6.2f} µs per sample "
          f"of each stream = {sps / BUDGET_SPS:6.1f} x real time for the two streams together")
    counts = rt.health()["streams"]
    assert all(c["samples"] == 4 * c["frames"] for c in counts.values())  # every sample taken


def ftp_designs(seconds: float) -> None:
    """Designs made in the caller's thread over ``seconds`` of the FTP cycle (module notes)."""
    from cell import app
    from cell.sim import simulate

    app.load()  # the engine profiles, as the command line registers them
    db = load()
    frames = list(simulate(db, "ftp", engine="si-turbo", seed=0, duration=seconds))
    block = UegoInversion()
    rt = Runtime(db, [block])
    grid = block._grid
    inline0, made0 = grid.designed_inline, grid.designed
    worst = 0.0
    real = block.samples

    def timed(*a):
        nonlocal worst
        t0 = time.perf_counter()
        real(*a)
        worst = max(worst, time.perf_counter() - t0)

    block.samples = timed
    rt.ingest_many(frames)
    speeds = [v for v in (rt.channels["ENGINE_SPEED"].value,) if v is not None]
    print(f"  afr_inversion over {seconds:g} s of the FTP cycle: {grid.designed - made0} bands "
          f"designed, {grid.designed_inline - inline0} of them in the runtime's thread (the first, "
          f"and any the background thread had not reached); longest frame of samples "
          f"{worst * 1e3:.1f} ms; last speed {speeds[0] if speeds else float('nan'):.0f} rpm")


if __name__ == "__main__":
    import argparse

    _p = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    _p.add_argument("seconds", nargs="?", type=float, default=10.0,
                    help="simulated seconds at 6000 rpm (default 10)")
    _p.add_argument("--ftp", type=float, default=60.0,
                    help="seconds of the FTP cycle for the design count (default 60; 0: skip)")
    _a = _p.parse_args()
    main(_a.seconds)
    if _a.ftp > 0:
        ftp_designs(_a.ftp)
