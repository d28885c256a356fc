"""Step cost of seed 002's air-path observers (default and augmented EKF) against real time.

Run: ``.venv/bin/python benchmarks/bench_diesel_airpath.py [SECONDS]`` (``--help``)

Issue 11's goal: each observer stepped at 100 Hz runs at >= 100x real time on one core.
The inputs are those of the large diesel on the ``etc`` cycle (the first SECONDS, default
60 s, recorded from the plant first, so only the observers are timed). The reference is
real time: SECONDS of bus time at 100 Hz. For scale, the same ObserverBlock/KalmanCore
stepping a trivial linear model of three states with analytic Jacobians is timed too: the
estimator platform's own cost per step, which no model can go below.

Each observer is stepped through the whole observer contract (``Block.step``: plausibility,
gap policy, divergence checks, confidence and sigma outputs), as the runtime steps it. The
ratio is given on the wall clock and on this process's CPU time (``time.process_time``): on
a loaded machine the second is what the code costs, the first what the machine gave it.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from cell.estimators.diesel_airpath import (
    SHIPPED_DESIGN,
    augmented_observer,
    default_observer,
    load_design,
)
from cell.estimators.core import Model
from cell.estimators.observer import ObserverBlock
from cell.plant.large_diesel import large_diesel

RATE_HZ = 100.0


def inputs(seconds: float) -> list[dict[str, float]]:
    plant = large_diesel("etc", 0, pem_sensor=False)
    names = ("FUEL_RATE", "ENGINE_SPEED", "VGT_POS", "EGR_POS", "EXH_BP_L", "EXH_BP_R", "DSL_P_IM", "N_T")
    rows = []
    for _ in range(round(seconds * RATE_HZ)):
        plant.step()
        rows.append({n: float(plant.signals[n]) for n in names})
    return rows


def trivial_observer() -> ObserverBlock:
    """x' = -x + u on three states, two measured: the platform's floor."""
    A = -np.eye(3)
    H = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    model = Model(("a", "b", "c"), ("FUEL_RATE",), ("DSL_P_IM", "N_T"),
                  lambda t, x, u, p: A @ x + u[0], lambda t, x, u, p: H @ x,
                  F=lambda t, x, u, p: A, H=lambda t, x, u, p: H, method="euler", max_step=0.01)
    return ObserverBlock("platform-floor", model, Q=[1.0] * 3, R=[1.0, 1.0], rate="FAS")


def main(seconds: float = 60.0) -> None:
    rows = inputs(seconds)
    ticking = frozenset({"FAS"})
    blocks = [default_observer(), augmented_observer(load_design(SHIPPED_DESIGN)), trivial_observer()]
    total = 0.0
    print(f"{len(rows)} steps at {RATE_HZ:g} Hz ({seconds:g} s of etc), inputs recorded beforehand")
    for block in blocks:
        t0, c0 = time.perf_counter(), time.process_time()
        for k, row in enumerate(rows):
            block.step(k / RATE_HZ, row, ticking)
        elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
        what = (f"{1e6 * elapsed / len(rows):7.1f} us/step = {seconds / elapsed:6.1f} x real time "
                f"(CPU {seconds / cpu:6.1f} x)")
        if block.name == "platform-floor":
            print(f"  {block.name:<20} {what} (a trivial model: the platform alone)")
            continue
        total += elapsed
        print(f"  {block.name:<20} {what} (goal >= 100: "
              f"{'met' if seconds / elapsed >= 100 else 'NOT met'})")
    print(f"  both side by side    {1e6 * total / len(rows):7.1f} us/step = "
          f"{seconds / total:6.1f} x real time")


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Step cost of the diesel air-path observers (default and augmented EKF, "
                    "through the observer contract) at 100 Hz against real time on one core.")
    parser.add_argument("seconds", nargs="?", type=float, default=60.0,
                        help="seconds of the etc cycle to record and step (default 60)")
    return parser.parse_args(argv)


if __name__ == "__main__":
    main(parse().seconds)
