"""Native filters against independent references: a textbook loop, filterpy and numpy; the
batch versions (the vectorised Kalman bank, the batch moving average) against the online blocks."""

import math

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from cell.analysis.sweep import table2
from cell.core.errors import ConfigError, ParamError
from cell.estimators.backpressure import (
    MAX_SAMPLES,
    MovingAverage,
    ScalarKalman,
    gain_sequence,
    kalman_bank,
    moving_average,
    steady_state_gain,
)


def textbook_kalman(ys, Q, R, P0=1.0):
    """Seed 004 eqs. (2)-(4) with A = C = 1, written out plainly."""
    x, P = ys[0], P0
    out = [x]
    for y in ys[1:]:
        P_prior = P + Q
        K = P_prior / (P_prior + R)
        x = x + K * (y - x)
        P = (1 - K) * P_prior
        out.append(x)
    return np.array(out)


def run_block(block, ys, source="EXH_BP_R"):
    return np.array([block.step(i * 0.1, {source: y})[block.name] for i, y in enumerate(ys)])


@pytest.fixture
def samples():
    rng = np.random.default_rng(7)
    truth = np.concatenate([np.full(300, 420.0), np.full(300, 680.0), np.linspace(680, 300, 200)])
    return truth + rng.standard_t(4, truth.size) * 60.0


@pytest.mark.parametrize("Q,R", [(1e-6, 1e-4), (4e-6, 1e-4), (1e-5, 1e-3), (1e-3, 1e-4)])
def test_kalman_matches_textbook_and_filterpy(samples, Q, R):
    ours = run_block(ScalarKalman("EXH_BP_R_Kalman", "EXH_BP_R", Q=Q, R=R), samples)
    np.testing.assert_allclose(ours, textbook_kalman(samples, Q, R), rtol=0, atol=1e-9)

    kf = KalmanFilter(dim_x=1, dim_z=1)
    kf.x = np.array([[samples[0]]])
    kf.P = np.array([[1.0]])
    kf.F = np.array([[1.0]])
    kf.H = np.array([[1.0]])
    kf.Q = np.array([[Q]])
    kf.R = np.array([[R]])
    ref = [samples[0]]
    for y in samples[1:]:
        kf.predict()
        kf.update(np.array([[y]]))
        ref.append(kf.x[0, 0])
    np.testing.assert_allclose(ours, np.array(ref), rtol=0, atol=1e-9)


def test_kalman_gain_converges_to_riccati_fixed_point(samples):
    kf = ScalarKalman("k", "EXH_BP_R", Q=1e-6, R=1e-4)
    run_block(kf, samples, source="EXH_BP_R")
    # closed form: P- solves P-^2 - Q P- - Q R = 0
    P_prior = (1e-6 + math.sqrt(1e-12 + 4e-10)) / 2
    assert kf.K == pytest.approx(P_prior / (P_prior + 1e-4), rel=1e-6)
    assert kf.steady_state_gain() == pytest.approx(P_prior / (P_prior + 1e-4), rel=1e-12)


@pytest.mark.parametrize("M", [1, 2, 3, 30])
def test_moving_average_is_exact(samples, M):
    ours = run_block(MovingAverage("m", "EXH_BP_R", samples=M), samples)
    ref = np.array([samples[max(0, i - M + 1): i + 1].mean() for i in range(samples.size)])
    np.testing.assert_allclose(ours, ref, rtol=1e-13, atol=1e-10)


def test_retuning_keeps_the_estimate(samples):
    kf = ScalarKalman("k", "EXH_BP_R")
    run_block(kf, samples[:100])
    x, P = kf.x, kf.P
    kf.set_params({"Q": 1e-3})
    assert (kf.x, kf.P) == (x, P)
    y = samples[100]
    kf.step(10.0, {"EXH_BP_R": y})
    K = (P + 1e-3) / (P + 1e-3 + kf.R)
    assert kf.x == pytest.approx(x + K * (y - x), abs=1e-12)

    ma = MovingAverage("m", "EXH_BP_R", samples=30)
    run_block(ma, samples[:100])
    ma.set_params({"samples": 10})
    assert ma.step(10.0, {"EXH_BP_R": samples[100]})["m"] == pytest.approx(samples[91:101].mean())
    ma.set_params({"samples": 40})  # grows as samples arrive; the kept 10 are not thrown away
    assert ma.step(10.1, {"EXH_BP_R": samples[101]})["m"] == pytest.approx(samples[91:102].mean())


@pytest.mark.parametrize(
    "body,field",
    [
        ({"Q": 0}, "Q"),
        ({"Q": -1e-6}, "Q"),
        ({"R": float("nan")}, "R"),
        ({"R": float("inf")}, "R"),
        ({"Q": "1e-6"}, "Q"),
        ({"Q": True}, "Q"),
        ({"Q": None}, "Q"),
        ({"samples": 30}, "samples"),
        ({"Q": 1e-5, "R": -1.0}, "R"),
        ({}, "body"),
    ],
)
def test_bad_kalman_params_change_nothing(body, field):
    kf = ScalarKalman("EXH_BP_R_Kalman", "EXH_BP_R")
    before = kf.params()
    with pytest.raises(ParamError) as err:
        kf.set_params(body)
    assert err.value.field == field
    assert field in str(err.value)
    assert kf.params() == before


@pytest.mark.parametrize("value", [0, -3, 2.5, MAX_SAMPLES + 1, 10**12, "30", float("nan")])
def test_bad_window_changes_nothing(value):
    ma = MovingAverage("EXH_BP_R_MAF", "EXH_BP_R")
    with pytest.raises(ParamError, match="samples"):
        ma.set_params({"samples": value})
    assert ma.samples == 30


# -- batch versions against the online blocks and filterpy ---------------------------------
def scalar_reference(y, Q, R, P0=1.0):
    """ScalarKalman stepped by hand; a NaN sample is skipped (state held), as the runtime does."""
    kf = ScalarKalman("k", "y", Q=Q, R=R, P0=P0)
    out = []
    for v in y:
        out.append(kf.step(0.0, {"y": v})["k"] if np.isfinite(v) else np.nan)
    return np.array(out)


@pytest.fixture(scope="module")
def noisy_walk():
    rng = np.random.default_rng(4)
    y = 500.0 + np.cumsum(rng.normal(0, 3, 3000)) + rng.standard_t(5, 3000) * 40
    y[[0, 1, 700, 701, 702, 2999]] = np.nan  # stale ticks, including the first ones
    return y


def test_bank_equals_scalar_kalman_for_all_table2_pairs(noisy_walk):
    pairs = table2()
    Q, R = np.array(pairs).T
    x, e, S = kalman_bank(noisy_walk, Q, R)
    assert x.shape == e.shape == S.shape == (noisy_walk.size, 72)
    for i in range(72):
        ref = scalar_reference(noisy_walk, Q[i], R[i])
        np.testing.assert_array_equal(np.isnan(x[:, i]), np.isnan(ref))
        np.testing.assert_allclose(x[:, i], ref, rtol=0, atol=1e-9, equal_nan=True)
    # innovation of a tick: sample minus the previous estimate; none at the first sample
    j = np.flatnonzero(np.isfinite(noisy_walk))
    assert np.isnan(e[j[0]]).all()
    np.testing.assert_allclose(e[j[1:], 3], noisy_walk[j[1:]] - x[j[:-1], 3])


def test_bank_matches_filterpy(noisy_walk):
    from filterpy.kalman import KalmanFilter

    y = noisy_walk[2:700]  # no gaps: filterpy has no notion of a stale sample
    pairs = [(1e-6, 1e-4), (4e-6, 1e-3), (9e-5, 1e-4), (10.0, 1600.0)]
    x, e, S = kalman_bank(y, *np.array(pairs).T)
    for i, (q, r) in enumerate(pairs):
        kf = KalmanFilter(dim_x=1, dim_z=1)
        kf.F[:] = kf.H[:] = 1.0
        kf.Q[:], kf.R[:], kf.x[:], kf.P[:] = q, r, y[0], 1.0
        for k in range(1, y.size):
            kf.predict()
            kf.update(y[k])
            assert x[k, i] == pytest.approx(kf.x[0, 0], abs=1e-9, rel=1e-12)
            assert S[k, i] == pytest.approx(kf.S[0, 0], rel=1e-9)
            assert e[k, i] == pytest.approx(kf.y[0, 0], abs=1e-9, rel=1e-12)


def test_gain_sequence_converges_to_the_riccati_fixed_point():
    K, _ = gain_sequence([1e-6, 1e-2, 5.0], [1e-4, 1e-4, 100.0], 1.0, steps=100_000)
    assert K.shape[0] < 100_000  # stopped once converged
    np.testing.assert_allclose(K[-1], steady_state_gain([1e-6, 1e-2, 5.0], [1e-4, 1e-4, 100.0]),
                               rtol=1e-12)
    kf = ScalarKalman("k", "y", Q=1e-6, R=1e-4)
    assert K[-1, 0] == pytest.approx(kf.steady_state_gain(), rel=1e-12)


def test_bank_rejects_bad_covariances():
    with pytest.raises(ConfigError, match="R must be finite and > 0"):
        kalman_bank([1.0, 2.0], 1e-6, [1e-4, -1.0])


def test_moving_average_equals_the_runtime_block(noisy_walk):
    block = MovingAverage("m", "y", samples=30)
    ref = [block.step(0.0, {"y": v})["m"] if np.isfinite(v) else np.nan for v in noisy_walk]
    np.testing.assert_allclose(moving_average(noisy_walk), ref, rtol=1e-12, equal_nan=True)
