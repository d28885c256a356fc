"""Cost per cycle of the paper's PUMA Kalman script against hand-written Python and filterpy.

Run: ``.venv/bin/python benchmarks/bench_scripts.py [CYCLES]``

All are measured in one process on the same samples (seed 004, Figures 5-6: two banks):

* ``kalman.fdv`` as shipped, stepped as the runtime steps it;
* the same filter hand written in Python (a class with a ``step`` method like a block);
* filterpy's ``KalmanFilter`` (one per bank, ``predict`` + ``update``), if installed;
* the CyFlex-style set ``kalman.labels`` + ``kalman.ravg`` (Figures 2-3), for reference.

Goals from the issue: within 3x of the hand-written step, at least 10x faster than filterpy.
"""

from __future__ import annotations

import random
import time

from cell.scripts.dialects import load_script, shipped_scripts


class HandKalman:
    """Figures 5-6 for both banks, written directly in Python (the reference)."""

    def __init__(self) -> None:
        self.s = {b: [0.0, 1.0, 1.0] for b in ("L", "R")}  # x_prev, P, P_prev
        self.Q, self.R = 4e-6, 1e-4

    def step(self, t, inputs, ticking=None):
        out = {}
        Q, R = self.Q, self.R
        for b in ("L", "R"):
            s = self.s[b]
            x_prev, P, P_prev = s
            K = P * (P + R) ** -1
            x = x_prev + K * (inputs["EXH_BP_" + b] - x_prev)
            P = (1 - K) * P_prev * (1 - K) + K * R * K
            s[0], s[1], s[2] = x, P, P + Q
            out["EXH_BP_" + b + "_Kalman"] = x
        return out


def _time(fn, samples, repeat=5) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for k, inputs in enumerate(samples):
            fn(k * 0.1, inputs)
        best = min(best, time.perf_counter() - t0)
    return best / len(samples) * 1e6


def main(cycles: int = 20_000) -> dict[str, float]:
    rng = random.Random(0)
    samples = [{"EXH_BP_L": 680 + rng.gauss(0, 3), "EXH_BP_R": 650 + rng.gauss(0, 3)}
               for _ in range(cycles)]
    shipped = {n: (t, r) for n, t, r in shipped_scripts()}
    fdv = load_script("kalman.fdv", *shipped["kalman.fdv"])
    cyf = load_script("kalman.labels", *shipped["kalman.labels"])
    hand = HandKalman()
    med = frozenset({"MED"})
    results = {
        "kalman.fdv (script block)": _time(lambda t, i: fdv.step(t, i, med), samples),
        "hand-written Python": _time(hand.step, samples),
        "kalman.labels+ravg (script block)": _time(lambda t, i: cyf.step(t, i, med), samples),
    }
    try:
        import numpy as np
        from filterpy.kalman import KalmanFilter
    except ImportError:
        print("filterpy not installed: skipping its reference")
    else:
        kfs = {}
        for b in ("L", "R"):
            kf = KalmanFilter(dim_x=1, dim_z=1)
            kf.x = np.array([[0.0]])
            kf.F = kf.H = np.array([[1.0]])
            kf.P, kf.Q, kf.R = np.array([[1.0]]), np.array([[4e-6]]), np.array([[1e-4]])
            kfs[b] = kf

        def fp_step(t, inputs):
            for b, kf in kfs.items():
                kf.predict()
                kf.update(inputs["EXH_BP_" + b])

        results["filterpy KalmanFilter"] = _time(fp_step, samples[: max(1, cycles // 10)], 3)
    ref = results["hand-written Python"]
    print(f"cost per cycle, both banks, {cycles} cycles (best of 5):")
    for name, us in results.items():
        print(f"  {name:36s} {us:8.2f} us   {us / ref:6.2f} x hand-written")
    if "filterpy KalmanFilter" in results:
        print(f"  filterpy / kalman.fdv = "
              f"{results['filterpy KalmanFilter'] / results['kalman.fdv (script block)']:.1f} x")
    return results


if __name__ == "__main__":
    import argparse

    _p = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    _p.add_argument("cycles", nargs="?", type=int, default=20_000,
                    help="script cycles timed (default 20000)")
    main(_p.parse_args().cycles)
