"""Scores of estimates against truth and of innovations, against closed forms."""

import numpy as np
import pytest

from cell.analysis import scores
from cell.analysis.series import Series
from cell.estimators.backpressure import kalman_bank


def test_nis_and_whiteness_of_a_consistent_filter():
    rng = np.random.default_rng(7)
    n, Q, R = 20_000, 4.0, 100.0
    y = np.cumsum(rng.normal(0, 2.0, n)) + rng.normal(0, 10.0, n)
    # true Q, R (P0 = R: the exact prior after x0 = y0), and a badly tuned Q either side
    _, e, S = kalman_bank(y, [Q, Q * 100, Q / 100], R, P0=R)
    s = scores.innovation_scores(e, S)
    assert s["nis"][0] == pytest.approx(1.0, abs=0.04)
    assert s["whiteness"][0] < 4 / np.sqrt(n)
    assert s["ljung_box"][0] < 30  # chi2(10) 99.9 % = 29.6
    assert s["whiteness"][1] > 0.3 and s["whiteness"][2] > 0.3
    assert s["nis"][2] > 2


def test_truth_scores_of_known_signals():
    rate = 10.0
    truth = np.r_[np.full(200, 100.0), np.full(200, 400.0), np.full(200, 250.0)]
    series = Series.from_arrays(truth + 1.0, truth, rate)
    delayed = np.r_[np.full(7, 100.0), truth[:-7]]  # truth 0.7 s late
    sc = scores.score_estimates(series, np.column_stack([truth + 5.0, delayed]))
    assert sc["rmse"][0] == pytest.approx(5.0) and sc["max_err"][0] == pytest.approx(5.0)
    assert sc["ss_std"][0] == pytest.approx(0.0, abs=1e-12)
    assert sc["lag_s"][0] == pytest.approx(0.0, abs=1e-9)
    assert sc["lag_s"][1] == pytest.approx(0.7)
    assert sc["max_err"][1] == pytest.approx(300.0)
    assert sc["rmse"][1] == pytest.approx(np.sqrt((7 * 300**2 + 7 * 150**2) / 600))
    steps = scores.find_steps(series.t, truth, scores.steady_mask(truth, rate))
    assert [(s.before, s.after) for s in steps] == [(100.0, 400.0), (400.0, 250.0)]


def test_truth_scores_take_plain_arrays_in_any_units():
    """Any estimate against its truth, e.g. an observer's state in its own units, with
    thresholds to match; the back-pressure defaults (mmH2O) see no step in it."""
    rate = 10.0
    truth = np.r_[np.full(200, 0.1), np.full(200, 0.4), np.full(200, 0.25)]
    delayed = np.r_[np.full(7, 0.1), truth[:-7]]  # truth 0.7 s late
    sc = scores.truth_scores(delayed, truth, rate, steady_tol=2e-3, step_min=0.05)
    assert sc["lag_s"][0] == pytest.approx(0.7)
    assert sc["max_err"][0] == pytest.approx(0.3)
    assert sc["ss_std"][0] == pytest.approx(0.0, abs=1e-12)
    assert np.isnan(scores.truth_scores(delayed, truth, rate)["lag_s"][0])
    # plain arrays and a Series give the same numbers (times from the rate)
    plain = scores.truth_scores(delayed * 1000, truth * 1000, rate)
    series = Series.from_arrays(truth * 1000, truth * 1000, rate)
    via_series = scores.score_estimates(series, delayed * 1000)
    for key in scores.TRUTH_KEYS:
        np.testing.assert_array_equal(plain[key], via_series[key])
    assert plain["lag_s"][0] == pytest.approx(0.7)
