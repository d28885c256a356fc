"""Numerics under abuse: the Kalman filters' covariances stay symmetric positive
semi-definite with extreme Q/R (1e-12..1e6) and extreme inputs, and no NaN or inf ever
reaches the bus (such an output is withheld and flagged).

The scalar filter (the native block the runtime runs) goes 10^6 steps per extreme pair. The
n-dimensional core (KF and EKF) costs ~50 µs a step in Python, so CI runs
``TESTCELL_NUMERICS_STEPS`` (default 20,000) steps per case; ``scripts/soak.sh`` and
``scripts/bench.sh`` run this file with 10^6.
"""

import math
import os
from array import array

import numpy as np
import pytest

from cell.runtime.blocks import Block
from cell.estimators.core import Diverged, KalmanCore
from cell.estimators.backpressure import ScalarKalman
from cell.runtime.scheduler import Runtime

SCALAR_STEPS = 1_000_000
CORE_STEPS = int(os.environ.get("TESTCELL_NUMERICS_STEPS", "20000"))
EXTREME = (1e-12, 1e6)


def extreme_inputs(n, seed):
    """Mostly noisy values, with bursts of huge ones, sign flips and values near the float limit."""
    rng = np.random.default_rng(seed)
    y = rng.normal(0.0, 1.0, n) * 10.0 ** rng.integers(-6, 16, n)
    y[rng.random(n) < 1e-4] = 1.7e308 * rng.choice([-1.0, 1.0])
    y[rng.random(n) < 1e-3] = 0.0
    return y


@pytest.mark.parametrize("Q", EXTREME)
@pytest.mark.parametrize("R", EXTREME)
def test_scalar_filter_covariance_stays_psd_over_a_million_steps(Q, R):
    kf = ScalarKalman("k", "y", Q=Q, R=R)
    ys = extreme_inputs(SCALAR_STEPS, seed=int(math.log10(Q) * 7 + math.log10(R)) % 2**31).tolist()
    Ps, Ks = array("d"), array("d")
    invalid = 0
    step = kf._step
    inputs = {"y": 0.0}
    for y in ys:
        inputs["y"] = y
        try:
            out = step(0.0, inputs)["k"]
        except ArithmeticError:
            invalid += 1
        else:
            if not math.isfinite(out):
                invalid += 100_000_000  # a non-finite output that was not flagged
        Ps.append(kf.P)
        Ks.append(kf.K)
    P, K = np.frombuffer(Ps), np.frombuffer(Ks)
    assert np.isfinite(P).all() and (P >= 0).all(), (P.min(), P.max())
    assert ((K >= 0) & (K <= 1)).all()
    assert invalid < 100_000_000
    assert kf.resets == invalid  # every flagged step was a reset, no silent NaN state
    # after the abuse the filter still filters: it converges on a constant input
    for _ in range(200):
        kf._step(0.0, {"y": 5.0})
    assert kf.x == pytest.approx(5.0, rel=1e-3) or kf.K < 1e-3


def _check_psd(P):
    assert np.isfinite(P).all()
    assert np.array_equal(P, P.T)
    assert np.linalg.eigvalsh(P)[0] >= 0.0


CORE_CASES = {
    "kf-tiny-Q-huge-R": dict(Q=1e-12, R=[1e6, 1e6]),
    "kf-huge-Q-tiny-R": dict(Q=1e6, R=[1e-12, 1e-12]),
    "kf-mixed-scales": dict(Q=[1e-12, 1e6, 1.0], R=[1e6, 1e-12]),
    "ekf-tiny-Q-huge-R": dict(Q=1e-12, R=[1e6, 1e6], ekf=True),
    "ekf-huge-Q-tiny-R": dict(Q=1e6, R=[1e-12, 1e-12], ekf=True),
    "ekf-mixed-scales": dict(Q=[1e6, 1e-12, 1e-12], R=[1e-12, 1e6], ekf=True),
}


@pytest.mark.parametrize("case", list(CORE_CASES))
def test_core_covariance_stays_symmetric_psd_with_extreme_q_r_and_inputs(case):
    spec = dict(CORE_CASES[case])
    ekf = spec.pop("ekf", False)
    dt = 0.01
    F = np.array([[1.0, dt, 0.0], [0.0, 1.0, dt], [0.0, 0.0, 0.99]])
    H = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    kf = KalmanCore(np.zeros(3), np.eye(3), spec["Q"], np.diag(spec["R"]), F=F, H=H, name=case)

    def f(x, u):  # a damped pendulum with a drifting bias: the EKF's model
        return np.array([x[0] + dt * x[1], x[1] - dt * math.sin(x[0]) - dt * 0.1 * x[1], 0.99 * x[2]])

    def h(x):
        return np.array([math.atan(x[0]) * 10.0, x[2] + 0.01 * x[1] ** 2])

    z = extreme_inputs(2 * CORE_STEPS, seed=len(case)).reshape(-1, 2)
    diverged = 0
    for k in range(CORE_STEPS):
        try:
            if ekf:
                kf.predict(f=f)
                _check_psd(kf.P)
                kf.update(z[k], h=h)
            else:
                kf.predict()
                _check_psd(kf.P)
                kf.update(z[k])
        except Diverged:
            diverged += 1
        _check_psd(kf.P)
        assert np.isfinite(kf.x).all()
    assert diverged == kf.resets


class Wild(Block):
    """Writes NaN, inf, -inf, a huge and a plain value, in turn, to a DBC output."""

    kind = "test"
    family = "filter"

    def __init__(self):
        super().__init__("wild", ["EXH_BP_L"], ["EXH_BP_L_MAF", "EXH_BP_L_Kalman"])
        self.k = 0

    def _step(self, t, inputs):
        v = (math.nan, math.inf, -math.inf, 1e308, 650.0)[self.k % 5]
        self.k += 1
        return {"EXH_BP_L_MAF": v, "EXH_BP_L_Kalman": 600.0}


def test_no_nan_or_inf_reaches_the_bus_it_is_withheld_and_flagged(db):
    rt = Runtime(db, [Wild()])
    for i in range(1000):  # 10 s at 100 Hz, 100 MED ticks
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 600.0, "EXH_BP_R": 600.0}, i * 0.01))
    rt.advance(9.99)
    frames = rt.take_outbox()
    assert len(frames) == 40  # only the ticks with finite values: 1e308 (clamped) and 650
    for msg in frames:
        _, values = db.decode(msg)
        assert all(math.isfinite(v) for v in values.values()), values
        assert values["EXH_BP_L_MAF"] in (20000.0, 650.0)  # 1e308 clamped to the DBC maximum
    h = rt.health()
    assert h["withheld"] == {"EXH_BP_L_MAF": 60}
    assert h["block_errors"] == {"wild": 60}
    ch = rt.channels["EXH_BP_L_MAF"]
    rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 600.0, "EXH_BP_R": 600.0}, 10.0))
    rt.advance(10.0)
    assert rt.channels["EXH_BP_L_MAF"].status == "invalid" and "nan" in ch.reason.lower()


def test_a_runtime_filter_fed_a_value_beyond_float_range_resets_and_flags(db):
    from cell.estimators.backpressure import native_filters

    rt = Runtime(db, native_filters())
    for i in range(300):
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 600.0, "EXH_BP_R": 600.0}, i * 0.01))
    rt.advance(2.99)
    k = rt.blocks["EXH_BP_R_Kalman"]
    k.x = math.inf  # a state gone beyond the float range (e.g. a huge float input of a user DBC)
    rt.take_outbox()
    for i in range(300, 400):
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 600.0, "EXH_BP_R": 600.0}, i * 0.01))
    rt.advance(3.99)
    assert rt.health()["block_errors"].get("EXH_BP_R_Kalman", 0) >= 1 and k.resets >= 1
    assert rt.channels["EXH_BP_R_Kalman"].status == "ok"  # restarted on the next sample
    for msg in rt.take_outbox():
        assert all(math.isfinite(v) for v in db.decode(msg)[1].values())
