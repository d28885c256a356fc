"""Seed 002 on the cell: the §6.1 study, the design tool and the augmented observer on the
diesel (acceptance tests of issue 11). One design log and one evaluation run are shared."""

import argparse
import json

import can
import numpy as np
import pytest

from cell.core.errors import ConfigError
from cell.estimators.augmentation import largest_angle_deg
from cell.estimators.diesel_airpath import load_design
from cell.experiments import diesel_airpath as B
from cell.plant.diesel import DutyCycle
from cell.sim import write_log

#: Short runs that still hold three stationary segments of the etc cycle.
DESIGN_S, EVAL_S = 300.0, 300.0


@pytest.fixture(scope="module")
def study():
    return B.simulation_study(seed=0, duration=400.0)  # the experiment runs 600 s


def test_simulation_study_two_dominant_singular_values_and_small_angle(study):
    s = np.array(study["S_r"])
    assert study["n_q"] == 2
    assert s[1] >= 0.1 * s[0] and s[2] < 0.1 * s[0]
    assert study["largest_angle_deg"] < 10.0
    # independent of the module: the angle recomputed from the matrices with plain SVD
    Q1 = np.linalg.qr(np.array(study["Aq_hat"]))[0]
    Q2 = np.linalg.qr(np.array(study["Aq_true"]))[0]
    cos_min = np.linalg.svd(Q1.T @ Q2, compute_uv=False).min()
    assert np.degrees(np.arccos(min(cos_min, 1.0))) == pytest.approx(study["largest_angle_deg"], abs=1e-6)
    # §4.4: the third row (x_3 has no bias) is small
    assert np.abs(study["Aq_hat"][2]).max() < 0.1


def test_simulation_study_augmented_observer_is_better_on_x2(study):
    assert study["mean_abs_error_augmented"][1] < 0.5 * study["mean_abs_error_default"][1]


@pytest.fixture(scope="module")
def design_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("bias") / "etc.log"
    write_log(path, "etc", seed=0, duration=DESIGN_S, progress=False)
    return path


def _design_args(log, out, **kw):
    return argparse.Namespace(log=str(log), states=kw.get("states"), approach=kw.get("approach", 2),
                              out=str(out), dim=kw.get("dim"))


@pytest.fixture(scope="module")
def design(design_log, tmp_path_factory):
    out = tmp_path_factory.mktemp("design") / "bias_design.json"
    assert B.design_main(_design_args(design_log, out)) == 0
    return json.loads(out.read_text()), out


def test_design_file_has_aq_and_singular_values(design):
    d, path = design
    assert d["approach"] == 2 and d["design_sensors"] == ["P_IM", "P_EM", "N_T"]
    assert len(d["segments"]) >= 3  # the etc holds in the first 300 s
    s = d["singular_values"]
    assert s == sorted(s, reverse=True) and d["n_q"] == 1 and s[1] < 0.1 * s[0]
    Aq = load_design(path)
    assert Aq.shape == (3, 1)
    # the dominant bias raises the exhaust manifold pressure with the intake pressure
    assert Aq[1, 0] > 0.3 and Aq[0, 0] > 0.1


def test_design_without_pem_sensor_gives_zero_pem_row(design_log, tmp_path):
    """§4.4: with no sensor on P_EM, its row of A_q comes out zero."""
    out = tmp_path / "d.json"
    B.design_main(_design_args(design_log, out, states="P_IM,N_T"))
    Aq = load_design(out)
    assert Aq[1, 0] == 0.0 and np.abs(Aq[[0, 2], 0]).max() > 0.1


@pytest.mark.parametrize("approach", [1, 3])
def test_approaches_1_and_3_agree_with_approach2(design_log, design, tmp_path, approach):
    """§4.1 (measured states, no observer) and §4.3 (maximally augmented observer) find the
    direction Approach 2 finds."""
    out = tmp_path / "d.json"
    B.design_main(_design_args(design_log, out, approach=approach))
    assert json.loads(out.read_text())["approach"] == approach
    assert largest_angle_deg(load_design(out), np.array(design[0]["Aq"])) < 5.0


def test_approach1_needs_every_state_measured(design_log, tmp_path):
    with pytest.raises(ConfigError, match="approach 1 needs every state"):
        B.design_main(_design_args(design_log, tmp_path / "d.json", approach=1, states="P_IM,N_T"))


def test_experiment_refuses_a_run_too_short(tmp_path):
    args = argparse.Namespace(out=str(tmp_path), json=True, seconds=50.0, seed=0, no_progress=True)
    with pytest.raises(ConfigError, match="--seconds must be >= 100"):
        B.main(args)


@pytest.fixture(scope="module")
def evaluation(design):
    rec = B.evaluate(load_design(design[1]), EVAL_S, seed=1)
    return rec, B.error_table(rec)


def test_evaluation_runs_without_pem_sensor(evaluation):
    rec, _ = evaluation
    assert "DSL_P_EM" not in rec.cols or np.isnan(rec["DSL_P_EM"]).all()


def test_augmented_observer_halves_the_pem_mean_error(evaluation):
    """Acceptance: mean error on P_EM (not measured) >= 50 % below the default observer's,
    max-abs error no worse by more than 10 %; scored against simulator truth."""
    rec, table = evaluation
    row = table["P_EM"]
    truth = rec["DSL_P_EM_TRUE"][rec.t >= B.SCORE_FROM]
    est = rec["DSL_P_EM_EST"][rec.t >= B.SCORE_FROM]
    assert np.mean(est - truth) == pytest.approx(row["mean_augmented"])
    assert abs(row["mean_default"]) > 2.0  # the default model is biased
    assert B.mean_error_reduction(table) >= 0.5
    assert row["max_abs_augmented"] <= 1.1 * row["max_abs_default"]


def test_back_pressure_raises_pem_and_augmented_observer_follows(design):
    hold = DutyCycle("hold", [(0.0, 1500.0, 0.75)], 80.0)
    rec = B.evaluate(load_design(design[1]), 80.0, seed=2, duty=hold, valve_steps=[(40.0, 25.0)],
                     initial_valve=100.0)
    before, after = (rec.t > 25) & (rec.t < 40), rec.t > 70
    bp = rec["EXH_BP_L_TRUE"]
    assert bp[after].mean() > bp[before].mean() + 500.0
    rise = rec["DSL_P_EM_TRUE"][after].mean() - rec["DSL_P_EM_TRUE"][before].mean()
    assert rise > 10.0
    est_rise = rec["DSL_P_EM_EST"][after].mean() - rec["DSL_P_EM_EST"][before].mean()
    assert est_rise == pytest.approx(rise, rel=0.3)
    assert abs(rec["DSL_P_EM_EST"][after].mean() - rec["DSL_P_EM_TRUE"][after].mean()) < 15.0


# -- bad input --------------------------------------------------------------------------------
def test_log_without_stationary_segment_is_refused(tmp_path):
    log = tmp_path / "short.log"
    write_log(log, "etc", seed=0, duration=40.0, progress=False)
    out = tmp_path / "d.json"
    with pytest.raises(ConfigError, match="no stationary segment"):
        B.design_main(_design_args(log, out))
    assert not out.exists()


def test_log_without_air_path_signals_is_refused(design_log, tmp_path):
    log = tmp_path / "no_airpath.log"
    with can.Logger(str(log)) as w:
        for i, msg in enumerate(can.LogReader(str(design_log))):
            if msg.arbitration_id not in (960, 961) :
                w.on_message_received(msg)
            if i > 20000:
                break
    out = tmp_path / "d.json"
    with pytest.raises(ConfigError, match="no values of .*VGT_POS"):
        B.design_main(_design_args(log, out))
    assert not out.exists()


@pytest.mark.parametrize("kw, match", [({"states": "P_IM,BOOST"}, "BOOST is not an air-path state"),
                                       ({"dim": 3}, "--dim must be 1..2")])
def test_bad_design_options_are_refused(design_log, tmp_path, kw, match):
    out = tmp_path / "d.json"
    with pytest.raises(ConfigError, match=match):
        B.design_main(_design_args(design_log, out, **kw))
    assert not out.exists()


def test_malformed_log_line_is_refused_with_its_line(tmp_path):
    log = tmp_path / "bad.log"
    log.write_text("(0.000000) vcan0 3C0#0102030405060708\nthis is not a frame\n")
    out = tmp_path / "d.json"
    with pytest.raises(ConfigError, match=r"bad.log:2"):
        B.design_main(_design_args(log, out))
    assert not out.exists()


def test_missing_log_and_bad_design_file(tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        B.design_main(_design_args(tmp_path / "nope.log", tmp_path / "d.json"))
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"Aq": [[1.0, 2.0]]}))
    with pytest.raises(ConfigError, match="3 x n_q"):
        load_design(bad)
    bad.write_text("{")
    with pytest.raises(ConfigError, match="not a readable JSON"):
        load_design(bad)
