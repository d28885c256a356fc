"""The air-path observer's step cost at 100 Hz, against real time.

Run: ``.venv/bin/python benchmarks/bench_si_airpath.py [SECONDS]`` (``--help``)

Issue 10's goal: seed 003's constant-gain EKF (augmented, feedback P_IC and P_IM) steps at
>= 100 x real time on one core at a 100 Hz tick. The reference is the real-time budget of a
tick, 10 ms. The inputs are those of a throttle-steps run (sampled once through the bus and
the runtime, not timed), so the cost includes the Jacobian refreshes of the W-method step
during the transients, not only the cheap stationary ticks. Reported: x real time over the
whole run (on the wall clock and on this process's CPU time), and the mean and
99th-percentile tick cost. The observer is stepped through the observer contract, as the
runtime steps it.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from cell import app
from cell.estimators.si_airpath import AirPathObserver
from cell.experiments.si_airpath import simulate

TICK = 0.01  # s, 100 Hz


def main(seconds: float = 104.0) -> None:
    app.load()  # the engine profiles and block sets, as the command line registers them
    from cell.plant.si_engine import throttle_steps_cycle

    cycle = throttle_steps_cycle(seconds / 13.0)
    run = simulate(seed=0, cycle=cycle)
    obs = AirPathObserver()
    names = obs.inputs
    rows = [{n: float(run[n][k]) for n in names} for k in range(run["t"].size)]
    times = run["t"].tolist()
    costs = np.empty(len(rows))
    t0, c0 = time.perf_counter(), time.process_time()
    for k, (t, inputs) in enumerate(zip(times, rows)):
        a = time.perf_counter()
        obs.step(t, inputs)
        costs[k] = time.perf_counter() - a
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    sim_s = len(rows) * TICK
    ratio = sim_s / elapsed
    print(f"air-path observer (augmented, feedback P_IC+P_IM, {len(obs.table.points)}-point table): "
          f"{len(rows)} ticks at 100 Hz ({sim_s:.0f} s of throttle steps) in {elapsed:.3f} s")
    print(f"  mean tick {costs.mean() * 1e6:7.1f} us, p99 {np.percentile(costs, 99) * 1e6:7.1f} us, "
          f"Jacobian refreshes {obs.refreshes} ({100 * obs.refreshes / len(rows):.1f} % of ticks)")
    print(f"  {ratio:7.1f} x real time (CPU {sim_s / cpu:.1f} x; budget {TICK * 1e3:.0f} ms per "
          f"tick); goal >= 100 x -> {'met' if ratio >= 100 else 'NOT met'}")


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Step cost of the SI air-path observer (seed 003, through the observer "
                    "contract) at 100 Hz against real time on one core.")
    parser.add_argument("seconds", nargs="?", type=float, default=104.0,
                        help="seconds of throttle steps to simulate and step (default 104)")
    return parser.parse_args(argv)


if __name__ == "__main__":
    main(parse().seconds)
