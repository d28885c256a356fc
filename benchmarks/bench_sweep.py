"""How fast the vectorised Q/R sweep is, against filterpy in a loop and against simdkalman.

Run: ``.venv/bin/python benchmarks/bench_sweep.py [SUBSET]``

The workload is issue 4's: seed 004's Table 2 (72 listed pairs) over one hour of 10 Hz
samples (36 000) of ``EXH_BP_R``, sampled from the plant running the ``transient`` duty cycle
back to back (the plant is stepped directly, no CAN, to keep the set-up short). Three runs of
the same filter, side by side in this process:

- ``cell.estimators.backpressure.kalman_bank``: all 72 pairs at once (best of 3);
- filterpy's ``KalmanFilter`` (``predict()``/``update()`` per sample) in a Python loop per
  pair: SUBSET pairs (default 4) are timed and the time is scaled to 72;
- simdkalman's ``KalmanFilter.compute`` (filtering only), vectorised over the 72 pairs as 72
  series with per-series Q and R (best of 3).

All three are checked to give the same estimates first. Goals (issue 4, Speed): >= 50x
filterpy, no slower than simdkalman; issue 7 keeps it at >= 400x (what it was before the restructure).
"""

from __future__ import annotations

import time

import numpy as np

from cell.plant import DutyCycle, duty_cycle, large_diesel
from cell.analysis.series import Series
from cell.analysis.sweep import sweep, table2
from cell.estimators.backpressure import kalman_bank

RATE_HZ = 10.0
SECONDS = 3600.0


def hour_of_samples(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """EXH_BP_R and its truth at 10 Hz over one hour of the transient cycle, repeated."""
    base = duty_cycle("transient")
    knots = []
    reps = int(np.ceil(SECONDS / base.duration))
    for i in range(reps):
        off = i * base.duration
        knots += [(t + off, s, ld) for t, s, ld in base.knots]
        knots.append(((i + 1) * base.duration, *base.knots[-1][1:]))
    plant = large_diesel(DutyCycle(f"transient x{reps}", knots, SECONDS), seed)
    per = round(1.0 / (RATE_HZ * plant.dt))
    n = round(SECONDS * RATE_HZ)
    y = np.empty(n)
    truth = np.empty(n)
    for i in range(n):
        y[i] = plant["EXH_BP_R"]
        truth[i] = plant["EXH_BP_R_TRUE"]
        for _ in range(per):
            plant.step()
    return y, truth


def best_of(fn, repeat: int = 3) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def filterpy_run(y: np.ndarray, Q: float, R: float, P0: float = 1.0) -> np.ndarray:
    from filterpy.kalman import KalmanFilter

    kf = KalmanFilter(dim_x=1, dim_z=1)
    kf.F[:] = 1.0
    kf.H[:] = 1.0
    kf.Q[:] = Q
    kf.R[:] = R
    kf.x[:] = y[0]
    kf.P[:] = P0
    out = np.empty(y.size)
    out[0] = y[0]
    for j in range(1, y.size):
        kf.predict()
        kf.update(y[j])
        out[j] = kf.x[0, 0]
    return out


def simdkalman_run(y: np.ndarray, Q: np.ndarray, R: np.ndarray, P0: float = 1.0) -> np.ndarray:
    import simdkalman

    m = Q.size
    kf = simdkalman.KalmanFilter(
        state_transition=1.0,
        process_noise=Q.reshape(m, 1, 1),
        observation_model=1.0,
        observation_noise=R.reshape(m, 1, 1),
    )
    # same start as ScalarKalman: x = y0, P = P0; the prior of the 2nd sample is (y0, P0 + Q)
    data = np.broadcast_to(y[1:], (m, y.size - 1))
    res = kf.compute(
        data, 0,
        initial_value=np.full((m, 1, 1), y[0]),
        initial_covariance=(P0 + Q).reshape(m, 1, 1),
        smoothed=False, filtered=True, covariances=False, observations=False,
    )
    states = res.filtered.states.mean[..., 0]  # (m, n-1)
    return np.concatenate([np.full((m, 1), y[0]), states], axis=1).T


def main(subset: int = 4) -> dict[str, float]:
    t0 = time.perf_counter()
    y, truth = hour_of_samples()
    print(f"workload: {y.size} samples ({SECONDS:.0f} s at {RATE_HZ:g} Hz) of EXH_BP_R on the "
          f"transient cycle, made in {time.perf_counter() - t0:.1f} s")
    pairs = table2()
    Q = np.array([p[0] for p in pairs])
    R = np.array([p[1] for p in pairs])
    m = Q.size
    print(f"grid: seed 004 Table 2, {m} pairs as listed")

    x, _, _ = kalman_bank(y, Q, R)
    pick = np.linspace(0, m - 1, subset).round().astype(int)
    fp = np.column_stack([filterpy_run(y, Q[i], R[i]) for i in pick])
    sk = simdkalman_run(y, Q, R)
    print(f"agreement: max |bank - filterpy| = {np.abs(x[:, pick] - fp).max():.2e}, "
          f"max |bank - simdkalman| = {np.abs(x - sk).max():.2e} mmH2O")

    t_bank = best_of(lambda: kalman_bank(y, Q, R))
    series = Series(np.arange(y.size) / RATE_HZ, y, truth, "EXH_BP_R", "EXH_BP_R_TRUE", RATE_HZ)
    t_sweep = best_of(lambda: sweep(series, pairs))
    t0 = time.perf_counter()
    for i in pick:
        filterpy_run(y, Q[i], R[i])
    t_fp_subset = time.perf_counter() - t0
    t_fp = t_fp_subset * m / pick.size
    t_sk = best_of(lambda: simdkalman_run(y, Q, R))

    print(f"  cell.estimators.backpressure.kalman_bank, {m} pairs:        {t_bank:8.3f} s")
    print(f"  cell.analysis.sweep.sweep (bank + all scores):    {t_sweep:8.3f} s")
    print(f"  filterpy loop, {pick.size} pairs timed:           {t_fp_subset:8.3f} s "
          f"-> {t_fp:.1f} s scaled to {m} pairs")
    print(f"  simdkalman, {m} series vectorised:        {t_sk:8.3f} s")
    print(f"ratios: filterpy / kalman_bank = {t_fp / t_bank:7.1f}x (goal >= 400x); "
          f"filterpy / sweep = {t_fp / t_sweep:.1f}x")
    print(f"        simdkalman / kalman_bank = {t_sk / t_bank:7.1f}x (goal >= 1x); "
          f"simdkalman / sweep = {t_sk / t_sweep:.1f}x")
    return {"pairs": m, "samples": y.size, "bank_s": t_bank, "sweep_s": t_sweep,
            "filterpy_s": t_fp, "simdkalman_s": t_sk}


if __name__ == "__main__":
    import argparse

    _p = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    _p.add_argument("repeats", nargs="?", type=int, default=4,
                    help="repeats of each timing, best taken (default 4)")
    main(_p.parse_args().repeats)
