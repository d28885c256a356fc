"""Seed 003's acceptance on the emulated engine (cell/experiments/si_airpath.py), against truth.

One throttle-steps run (twelve step cases at 1800 rpm, 104 s) is shared by the tests.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from cell.app.cli import main as cli
from cell.experiments.si_airpath import lowpass, run_experiment


@pytest.fixture(scope="module")
def result():
    run, est, res = run_experiment(seed=3)
    return run, est, res


def test_p_im_estimate_is_quieter_than_the_sensor_without_lag(result):
    _, _, r = result
    assert r.noise_ratio < 0.3  # less noisy than the measured P_IM
    # lags the truth by no more than one observer sample at every step
    assert max(r.lags_est_s) <= r.dt + 1e-9
    # a causal low-pass with the same noise reduction lags far more, at every step
    assert min(r.lags_lpf_s) >= 5 * r.dt
    assert r.lag_lpf_s > 5 * max(r.lag_est_s, r.dt)


def test_lowpass_is_the_textbook_first_order_filter():
    y = np.r_[np.zeros(5), np.ones(200)]
    f = lowpass(y, 0.1)
    # step response 1 - (1 - a)^(k + 1) after the step
    k = np.arange(200)
    np.testing.assert_allclose(f[5:], 1 - 0.9 ** (k + 1), rtol=1e-12)


def test_without_augmentation_a_stationary_error_remains_with_it_p_im_converges(result):
    _, _, r = result
    assert len(r.cases) >= 10
    plain = np.array([c.plain_vs_meas for c in r.cases])
    aug = np.array([c.augmented_vs_meas for c in r.cases])
    # the non-augmented observer keeps a stationary error at some operating point ...
    assert np.max(np.abs(plain)) > 0.5  # kPa
    # ... the augmented one converges to the measured pressure in every step case (the
    # 2 s means of the measurement carry about 0.1 kPa of noise)
    assert np.all(np.abs(aug) < 0.3)
    # and to the truth too
    assert np.all(np.abs([c.augmented_vs_true for c in r.cases]) < 0.3)


def test_turbo_speed_within_three_percent_from_the_two_pressures(result):
    _, _, r = result
    assert all(abs(c.n_tc_err_pct) < 3.0 for c in r.cases)


def test_cac_error_is_reported_and_the_augmentation_reduces_it(result):
    run, est, r = result
    plain = np.array([abs(c.cac_err_plain_pct) for c in r.cases])
    aug = np.array([abs(c.cac_err_augmented_pct) for c in r.cases])
    assert np.all(np.isfinite(plain)) and np.all(np.isfinite(aug))
    assert aug.mean() < plain.mean()
    assert r.cac_rms_augmented_pct < r.cac_rms_plain_pct
    # the report's CAC is the truth's channel: check one case by hand
    c = r.cases[0]
    t = run["t"]
    sel = (t >= r.cases[1].t_step - 2.0) & (t <= r.cases[1].t_step)
    true = run["CAC_TRUE"][sel].mean()
    assert c.cac_err_augmented_pct == pytest.approx(
        100 * (est["augmented"]["CAC_EST"][sel].mean() - true) / true, abs=1e-6)


def test_experiment_command_writes_figures_and_json(tmp_path, capsys, monkeypatch, result):
    import cell.experiments.si_airpath as mod

    monkeypatch.setattr(mod, "run_experiment", lambda *a, **k: result)
    assert cli(["experiment", "airpath", "--out", str(tmp_path), "--json", "--quiet"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["cases"]) == 12 and out["noise_ratio"] < 1
    for name in ("figure1_model", "figure3_gains", "figure5_observer", "figure6_augmented"):
        png = tmp_path / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_experiment_refuses_a_short_hold(capsys):
    assert cli(["experiment", "airpath", "--hold", "3"]) == 2
    assert "--hold must be at least 6" in capsys.readouterr().err
