"""Seed 000's acceptance on the emulated cell: the dual EKF against the simulator's truth.

One FTP-like drive per catalyst is recorded through the simulator, the DBC frames and the
runtime (:func:`cell.experiments.catalyst.record`), module-scoped, and every observer case runs
over it offline, as the runtime would step it (a test checks that equivalence).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from cell.app import cli
from cell.estimators.catalyst import Q4_DEFAULT, TWCObserver
from cell.experiments.catalyst import convergence_time, naive_sox, observe, reach_time, record, rmse


@pytest.fixture(scope="module")
def fresh():
    """A fresh catalyst (OSC 1) over the first 1000 s of the cycle."""
    return record(1.0, 1000.0)


@pytest.fixture(scope="module")
def aged():
    """An aged catalyst (``--osc 0.6``) over 1800 s."""
    return record(0.6, 1800.0)


@pytest.fixture(scope="module")
def fresh_estimates(fresh):
    return {g: observe(fresh, osc_init=g) for g in (0.5, 1.0, 1.5)}


@pytest.mark.parametrize("guess,within", [(0.5, 700.0), (1.0, 700.0), (1.5, 1000.0)])
def test_osc_converges_from_each_initial_guess(fresh, fresh_estimates, guess, within):
    est = fresh_estimates[guess]
    truth = fresh.truth["OSC_TRUE"]
    assert np.all(truth == 1.0)
    t_conv = convergence_time(fresh.t, est.osc, truth)
    assert t_conv is not None and t_conv <= within  # Figure 5
    assert abs(est.osc[-1] - 1.0) <= 0.1
    assert est.errors == 0 and est.block.core.resets == 0


def test_a_guess_above_fresh_takes_longer(fresh, fresh_estimates):
    truth = fresh.truth["OSC_TRUE"]
    t = {g: convergence_time(fresh.t, e.osc, truth) for g, e in fresh_estimates.items()}
    assert t[1.5] > t[0.5]  # Figure 5: OSC_normalised > 1 is the slow case


def test_ten_times_q4_converges_sooner_and_ripples_more(fresh, fresh_estimates):
    slow = fresh_estimates[0.5]
    fast = observe(fresh, osc_init=0.5, Q=(1e-4, 1e-4, 1e-4, 10 * Q4_DEFAULT))
    truth = fresh.truth["OSC_TRUE"]
    assert reach_time(fresh.t, fast.osc, truth) < reach_time(fresh.t, slow.osc, truth)
    late = fresh.t >= 500.0  # both inside the band by then: the ripple about the truth
    ripple = {k: np.std(np.diff(e.osc[late])) for k, e in (("slow", slow), ("fast", fast))}
    assert ripple["fast"] > 1.5 * ripple["slow"]  # Figure 6


def test_an_aged_catalyst_is_estimated_from_the_fresh_guess(aged):
    est = observe(aged, osc_init=1.0)
    assert np.all(aged.truth["OSC_TRUE"] == 0.6)
    assert abs(est.osc[-1] / 0.6 - 1.0) <= 0.10
    last_minute = aged.t >= aged.t[-1] - 60.0
    assert abs(np.mean(est.osc[last_minute]) / 0.6 - 1.0) <= 0.10


def test_a_step_of_osc_mid_run_is_followed():
    rec = record(1.0, 1100.0, osc_step=(500.0, 0.6))  # the scenario frame, through the sim
    t, truth = rec.t, rec.truth["OSC_TRUE"]
    assert truth[t < 499.9].max() == 1.0 and np.all(truth[t > 500.2] == pytest.approx(0.6))
    est = observe(rec, osc_init=1.0)
    before = (t > 400.0) & (t < 500.0)
    assert np.all(np.abs(est.osc[before] - 1.0) <= 0.1)
    after = t > 500.0
    t_follow = reach_time(t[after], est.osc[after], truth[after])
    assert t_follow is not None and t_follow - 500.0 <= 300.0
    assert abs(np.mean(est.osc[t > 1000.0]) / 0.6 - 1.0) <= 0.1


@pytest.mark.parametrize("which", ["fresh", "aged"])
def test_sox_tracks_truth_better_than_the_naive_lambda_pre_integrator(which, request,
                                                                      fresh_estimates):
    rec = request.getfixturevalue(which)
    est = fresh_estimates[1.0] if which == "fresh" else observe(rec, osc_init=1.0)
    warm = rec.inputs["T_CAT"] >= 350.0
    late = rec.t >= 300.0  # the observer has had its time to converge
    ours = rmse(est.sox, rec.truth["SOX_TRUE"], warm & late)
    naive = rmse(naive_sox(rec), rec.truth["SOX_TRUE"], warm & late)
    assert ours < 0.8 * naive
    assert ours < 0.08


def test_offline_observation_is_what_the_runtime_block_computes():
    block = TWCObserver("twc", osc_init=0.7)
    rec = record(1.0, 120.0, runtime_blocks=[block])
    offline = observe(rec, osc_init=0.7)
    ran = ~np.isnan(rec.truth["OSC_EST"])
    assert ran.sum() > 1000
    np.testing.assert_allclose(offline.osc[ran], rec.truth["OSC_EST"][ran], rtol=0, atol=1e-12)
    np.testing.assert_allclose(offline.sox[ran], rec.truth["SOX_EST"][ran], rtol=0, atol=1e-12)


def test_the_model_mismatch_is_configurable(fresh):
    from cell.experiments.catalyst import parse_mismatch
    from cell.plant.catalyst_model import TWCKinetics

    k = parse_mismatch("A1=0.5,y_c=1.1")
    assert k.A1 == 0.5 * TWCKinetics().A1 and k.y_c == pytest.approx(1.1 * TWCKinetics().y_c)
    exact = observe(fresh, osc_init=1.0, kinetics=parse_mismatch("A1=1"))
    assert exact.block.kinetics == TWCKinetics()
    wrong = observe(fresh, osc_init=1.0, kinetics=parse_mismatch("y_c=1.3"))
    # 30 % too much carbon in the model's feed gas: it sees storage fill and empty faster,
    # so it needs a larger capacity to explain the same breakthroughs
    late = fresh.t >= 500.0
    assert np.mean(wrong.osc[late]) > np.mean(exact.osc[late]) + 0.1


def test_experiment_command_writes_figures_table_and_json(tmp_path, capsys):
    out = tmp_path / "twc"
    code = cli.main(["experiment", "twc", "--duration", "60", "--osc-init", "1.0,1.5",
                     "--q4", "2e-5,2e-4", "--out", str(out), "--json", "--quiet",
                     "--mismatch", "A1=0.8,A2=1.2"])
    assert code == 0
    captured = capsys.readouterr()
    lines = [json.loads(x) for x in captured.out.splitlines()]
    assert [r["case"] for r in lines] == ["osc_init=1", "osc_init=1.5", "q4=2e-05", "q4=0.0002"]
    assert {"convergence_s", "ripple", "sox_rmse", "sox_rmse_naive"} <= set(lines[0])
    assert "conv. s" in captured.err
    for name in ("figure4_twc.png", "figure5_osc_init.png", "figure6_q4.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len((out / "twc_cases.json").read_text().splitlines()) == 4


@pytest.mark.parametrize("argv,needle", [
    (["--osc-init", "0.5,abc"], "--osc-init '0.5,abc': 'abc' is not a number"),
    (["--q4", "-1"], "--q4 '-1': each value must be in (0, 1]"),
    (["--osc-true", "3"], "--osc-true must be in [0.05, 2]"),
    (["--duration", "1"], "--duration must be >= 10 s"),
    (["--mismatch", "A3=2"], "'A3=2' is not NAME=FACTOR with NAME one of A1, E1"),
    (["--mismatch", "A1=0"], "a factor must be in [0.1, 10], got 0"),
])
def test_experiment_refuses_bad_options(argv, needle, capsys, tmp_path):
    assert cli.main(["experiment", "twc", *argv, "--out", str(tmp_path), "--quiet"]) == 2
    assert needle in capsys.readouterr().err
    assert not (tmp_path / "figure4_twc.png").exists()
