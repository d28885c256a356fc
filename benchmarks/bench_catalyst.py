"""How fast the catalyst's dual EKF steps, against its real-time budget; and the plant.

Run: ``.venv/bin/python benchmarks/bench_catalyst.py [SECONDS]``

Issue 8's goal: the observer (``twc``, seed 000's dual EKF) at >= 200 x real time on one
core. Its real-time budget is its tick period: at MED (10 Hz) one step must take less
than 100 ms. The benchmark records SECONDS (default 600) of the FTP-like cycle's inputs once
(the simulator, in lockstep with a runtime), then times the observer alone over them, tick
by tick, as the runtime steps it, and reports the mean step cost and x real time. It also
times the ``si-turbo`` plant alone (100 Hz) over the same span, for the 1800 s runs that
must be faster than real time.
"""

from __future__ import annotations

import math
import time

from cell.estimators.catalyst import TWCObserver
from cell.experiments.catalyst import INPUTS, record
from cell.plant.si_turbo import si_turbo

RATE_HZ = 10.0  # MED
GOAL = 200.0


def main(seconds: float = 600.0) -> None:
    rec = record(1.0, seconds)
    cols = [rec.inputs[k].tolist() for k in INPUTS]
    ticks = [(t, dict(zip(INPUTS, vals))) for t, *vals in zip(rec.t.tolist(), *cols)
             if not any(math.isnan(v) for v in vals)]
    ob = TWCObserver()
    t0 = time.perf_counter()
    for t, u in ticks:
        ob.step(t, u)
    elapsed = time.perf_counter() - t0
    per_step = elapsed / len(ticks)
    budget = 1.0 / RATE_HZ
    ratio = budget / per_step
    print(f"twc observer: {len(ticks)} ticks ({seconds:.0f} s of the FTP-like cycle at "
          f"{RATE_HZ:g} Hz) in {elapsed:.2f} s")
    print(f"  step cost {per_step * 1e6:8.1f} us against the real-time budget of "
          f"{budget * 1e3:.0f} ms per tick: {ratio:8.0f} x real time")
    print(f"  (iterated updates: {ob.iterated}, blanked ticks: {ob.blanked})")
    print(f"  goal: >= {GOAL:g} x real time -> {'met' if ratio >= GOAL else 'NOT met'}")

    plant = si_turbo("ftp")
    n = round(seconds / plant.dt)
    t1 = time.perf_counter()
    for _ in range(n):
        plant.step()
    plant_s = time.perf_counter() - t1
    print(f"si-turbo plant (engine, breathing, catalyst at {1 / plant.dt:g} Hz): {seconds:.0f} s "
          f"in {plant_s:.2f} s = {seconds / plant_s:6.1f} x real time")


if __name__ == "__main__":
    import argparse

    _p = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    _p.add_argument("seconds", nargs="?", type=float, default=600.0,
                    help="simulated seconds of the run (default 600)")
    main(_p.parse_args().seconds)
