"""Step cost of seed 002's air-path observers (default and augmented EKF) against real time.

Run: ``.venv/bin/python benchmarks/bench_diesel_airpath.py [SECONDS] [--repeat N]`` (``--help``)

Issue 11's goal: each observer stepped at 100 Hz runs at >= 100x real time on one core.
The inputs are those of the large diesel on the ``etc`` cycle (the first SECONDS, default
60 s, recorded from the plant first, so only the observers are timed). The reference is
real time: SECONDS of bus time at 100 Hz. For scale, the same ObserverBlock/KalmanCore
stepping a trivial linear model of three states with analytic Jacobians is timed too: the
estimator platform's own cost per step, which no model can go below.

Each observer is stepped through the whole observer contract (``Block.step``: plausibility,
gap policy, divergence checks, confidence and sigma outputs), as the runtime steps it. The
ratio is on this process's CPU time (``time.process_time``, best of ``--repeat`` runs), with
the wall clock beside it: on a loaded machine the first is what the code costs, the second
what the machine gave it (``_common.py``).
"""

from __future__ import annotations

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

from _common import best_of, load_line, parse, verdict

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


def main(seconds: float = 60.0, repeat: int = 3) -> None:
    rows = inputs(seconds)
    ticking = frozenset({"FAS"})
    design = load_design(SHIPPED_DESIGN)
    makers = [default_observer, lambda: augmented_observer(design), trivial_observer]
    total = 0.0
    print(f"{len(rows)} steps at {RATE_HZ:g} Hz ({seconds:g} s of etc), inputs recorded "
          f"beforehand, best of {repeat} on CPU time; {load_line()}")
    for make in makers:
        def run(make=make) -> None:
            block = make()
            for k, row in enumerate(rows):
                block.step(k / RATE_HZ, row, ticking)
        name = make().name
        elapsed, cpu = best_of(repeat, run)
        what = (f"{1e6 * cpu / len(rows):7.1f} us/step CPU = {seconds / cpu:6.1f} x real time "
                f"(wall clock {seconds / elapsed:6.1f} x)")
        if name == "platform-floor":
            print(f"  {name:<20} {what} (a trivial model: the platform alone)")
            continue
        total += cpu
        print(f"  {name:<20} {what} (goal >= 100 on CPU time: {verdict(seconds / cpu, 100)})")
    print(f"  both side by side    {1e6 * total / len(rows):7.1f} us/step CPU = "
          f"{seconds / total:6.1f} x real time")


if __name__ == "__main__":
    _a = parse("Step cost of the diesel air-path observers (default and augmented EKF, "
               "through the observer contract) at 100 Hz against real time on one core.",
               60.0, "the etc cycle")
    main(_a.seconds, _a.repeat)
