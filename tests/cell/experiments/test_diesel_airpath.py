"""Seed 002 on the cell, ``testcell experiment bias``: the §6.1 study and the augmented
observer on the diesel (acceptance tests of issue 11). One evaluation run is shared; its
design comes from the design tool (``tests/cell/conftest.py``)."""

import argparse

import numpy as np
import pytest

from cell.core.errors import ConfigError
from cell.estimators.diesel_airpath import load_design
from cell.experiments import diesel_airpath as B
from cell.plant.diesel import DutyCycle

#: A short evaluation run that still holds three stationary segments of the etc cycle.
EVAL_S = 300.0


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
