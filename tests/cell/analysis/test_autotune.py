"""Auto-tuning Q and R from data alone (issue 4, part 4; seed 004's future work).

The acceptance test: on simulator logs of the ``transient`` duty cycle, the filter tuned with
no truth scores an RMSE against ``EXH_BP_R_TRUE`` within 10 % of the best pair of a fine
grid scored *with* the truth.
"""

import argparse
import json
import math

import numpy as np
import pytest

from cell.analysis import autotune as at
from cell.analysis import sweep as sw
from cell.analysis.scores import score_estimates
from cell.analysis.series import channel_series
from cell.core.errors import ConfigError
from cell.estimators.backpressure import kalman_bank
from cell.sim import write_log

#: A fine grid: Q/R from 1e-4 to 1e2 at 40 points per decade (P0 = 1, as the runtime).
FINE = [(q, 1e-4) for q in np.geomspace(1e-8, 1e-2, 241)]


@pytest.fixture(scope="module", params=[0, 1])
def transient(request, tmp_path_factory):
    path = tmp_path_factory.mktemp("tune") / f"transient{request.param}.log"
    write_log(path, "transient", seed=request.param, progress=False)
    return channel_series(path, "EXH_BP_R", progress=False)


def test_autotuned_rmse_is_within_10_percent_of_the_best_grid_pair(transient):
    res = at.autotune(transient.y, transient.rate_hz)
    x, _, _ = kalman_bank(transient.y, res.Q, res.R)
    rmse_tuned = score_estimates(transient, x)["rmse"][0]
    best = sw.sweep(transient, FINE)[0]
    paper = sw.sweep(transient, [(1e-6, 1e-4)])[0]
    print(f"\n{transient.source}: autotune Q={res.Q:.4g} R={res.R:.4g} (Q/R {res.ratio:.4g}, "
          f"gain {res.gain:.3f}) RMSE {rmse_tuned:.2f}; best grid Q/R "
          f"{best['Q'] / best['R']:.4g} RMSE {best['rmse']:.2f}; "
          f"paper pair RMSE {paper['rmse']:.2f}")
    assert rmse_tuned <= 1.10 * best["rmse"]
    assert res.ratio_ci[0] <= best["Q"] / best["R"] <= res.ratio_ci[1]


def test_estimated_r_is_the_simulated_noise_variance(transient):
    res = at.autotune(transient.y, transient.rate_hz)
    noise_var = float(np.nanvar(transient.y - transient.truth))
    print(f"\nR = {res.R:.0f} (95 % {res.R_ci[0]:.0f}..{res.R_ci[1]:.0f}), "
          f"var(raw - truth) = {noise_var:.0f}, kurtosis {res.kurtosis:.1f}")
    assert res.R == pytest.approx(noise_var, rel=0.15)
    assert res.kurtosis > 4  # the plant's noise is heavy tailed; the intervals widen for it


# -- synthetic random walk: closed-form truth -----------------------------------------------
def random_walk(seed, n=2000, Q=4.0, R=100.0):
    rng = np.random.default_rng(seed)
    return 300.0 + np.cumsum(rng.normal(0, math.sqrt(Q), n)) + rng.normal(0, math.sqrt(R), n)


def test_ml_recovers_q_and_r_inside_its_intervals():
    hits = 0
    for seed in range(10):
        res = at.autotune(random_walk(seed), 10.0)
        hits += res.Q_ci[0] <= 4.0 <= res.Q_ci[1] and res.R_ci[0] <= 100.0 <= res.R_ci[1]
        assert res.Q == pytest.approx(4.0, rel=0.6) and res.R == pytest.approx(100.0, rel=0.15)
    assert hits >= 7  # 95 % intervals, two of them, ten draws


def test_ml_is_the_likelihood_maximum_and_agrees_with_pykalman_em():
    pytest.importorskip("pykalman")
    y = random_walk(11, n=600)
    res = at.autotune(y, 10.0)
    q_em, r_em = at.em_reference(y, n_iter=25)
    print(f"\nML Q={res.Q:.3f} R={res.R:.2f}; pykalman EM Q={q_em:.3f} R={r_em:.2f}")
    ll = at.loglik(y, [res.Q, q_em, res.Q * 1.3, res.Q], [res.R, r_em, res.R, res.R * 1.1])
    assert ll[0] == pytest.approx(res.loglik, rel=1e-9)
    assert ll[0] >= ll.max() - 1e-6  # no other point is more likely
    assert res.Q_ci[0] <= q_em <= res.Q_ci[1]
    assert res.R_ci[0] <= r_em <= res.R_ci[1]
    # EM moves slowly from its start (25 iterations are not converged) but a maximum of the
    # likelihood is a fixed point of EM: started at the ML estimate it stays there
    q_fix, r_fix = at.em_reference(y, n_iter=8, Q0=res.Q, R0=res.R)
    assert q_fix == pytest.approx(res.Q, rel=0.02) and r_fix == pytest.approx(res.R, rel=0.005)


def test_als_on_a_random_walk():
    res = at.autotune(random_walk(3, n=20_000, Q=100.0), 10.0, method="als")
    assert res.method == "als" and math.isnan(res.loglik)
    assert res.Q == pytest.approx(100.0, rel=0.25) and res.R == pytest.approx(100.0, rel=0.1)
    assert res.Q_ci[0] <= 100.0 <= res.Q_ci[1]


def test_stale_samples_and_none_are_held_over():
    y = list(random_walk(5, n=1500))
    y[:3] = [None, None, None]
    y[500:520] = [None] * 20
    res = at.autotune(y, 10.0)
    assert res.n == 1477 and res.R == pytest.approx(100.0, rel=0.2)
    json.dumps(res.to_dict(), allow_nan=False)


@pytest.mark.parametrize(
    "y, kw, words",
    [
        ([1.0] * 10, {}, "at least 50"),
        ([5.0] * 100, {}, "constant"),
        ([float(i % 7) for i in range(100)], {"method": "em"}, "method 'em'"),
        ([float(i % 7) for i in range(100)], {"rate_hz": 0}, "rate_hz"),
    ],
)
def test_bad_input(y, kw, words):
    with pytest.raises(ConfigError, match=words):
        at.autotune(y, **kw)


def test_cli_prints_the_estimate_and_applies_nothing(tmp_path, capsys):
    log = tmp_path / "t.log"
    write_log(log, "transient", seed=2, duration=80.0, progress=False)
    parser = argparse.ArgumentParser()
    at.add_arguments(parser)
    assert at.main(parser.parse_args([str(log), "--channel", "EXH_BP_R", "--quiet"])) == 0
    out = capsys.readouterr()
    assert "Q = " in out.out and "95 %" in out.out and "RMSE vs EXH_BP_R_TRUE" in out.out
    assert "not applied" in out.err
    assert at.main(parser.parse_args([str(log), "--quiet", "--json"])) == 0
    obj = json.loads(capsys.readouterr().out)
    assert {"Q", "R", "Q_ci", "R_ci", "loglik", "method", "n", "rmse_vs_truth"} <= set(obj)
    with pytest.raises(ConfigError, match="EXH_BP_Z"):
        at.main(parser.parse_args([str(log), "--channel", "EXH_BP_Z", "--quiet"]))
