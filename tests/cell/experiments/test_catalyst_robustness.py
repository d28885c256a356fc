"""Issue 18's catalyst acceptance on plant variants the observer was not written against:
after ``testcell design twc`` on one log of the variant, OSC on another (other noise seed)
reaches ±10 % of the truth and stays from ≤ 700 s (short cycles; the full matrix is
``testcell experiment robustness``)."""

from __future__ import annotations

import pytest

from cell.experiments.catalyst import robustness_case

pytestmark = pytest.mark.slow

VARIANTS = {
    "composition-lag": {"lambda_sensor": "composition"},
    "slow-sensor-slow-kinetics": {"lambda_tau_scale": 2.0, "kinetics_scale": 0.5},
}


@pytest.mark.parametrize("case,name", [("fresh", "slow-sensor-slow-kinetics")])
def test_osc_converges_on_a_variant_after_design(case, name):
    r = robustness_case(VARIANTS[name], case, 3, True)
    assert set(r) == {"passed", "metrics", "reason"}
    assert r["passed"], r["reason"]
    assert r["metrics"]["convergence_s"] <= 700.0
    # the design found the variant's sensor: twice the cell's 0.1 s, its lag on λ
    assert r["metrics"]["identified"]["lambda_lag"] == "lambda"
    assert r["metrics"]["identified"]["tau_lambda"] == pytest.approx(0.1 * VARIANTS[name].get(
        "lambda_tau_scale", 1.0), rel=0.1)
