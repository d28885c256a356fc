"""afr_inversion's confirmed diagnosis (issue 18): the sequential test on the per-cylinder
departures, its state and confidence channels, and loading an imbalance design. The
departures are fed as the exhaust windows would close, from patterns written here."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from cell.estimators.contract import DesignError
from cell.estimators.cylinders import CONFIRMED, NONE, SETTLING, SUSPECT, UegoInversion


def _feed(u: UegoInversion, patterns, rng, noise=0.03):
    """Close one exhaust window per pattern (AFR of the four cylinders); the diagnosis and
    state after each."""
    u.cycles_since_reset = u.settle_cycles
    u._fresh = {1, 2, 3, 4}
    out = []
    for p in patterns:
        u._t_samples += 0.02  # a window at 1500 rpm
        u.cyl_est = 14.7 + np.asarray(p, dtype=float) + rng.normal(0.0, noise, 4)
        u._diagnose()
        out.append((u.diagnosis, u.diag_state, u.confidence))
    return out


def _one_off(cyl, x):
    """Cylinder ``cyl`` departs by -3x, the other three by +x (the λ control keeps the mean)."""
    d = np.full(4, x)
    d[cyl - 1] = -3 * x
    return d


def test_a_balanced_engine_never_names_a_cylinder_and_says_none():
    u, rng = UegoInversion(), np.random.default_rng(0)
    got = _feed(u, [np.zeros(4)] * 2000, rng)
    assert {d for d, _, _ in got} == {0.0}
    assert got[-1][1] == NONE and got[-1][2] == 0.0


@pytest.mark.parametrize("cyl", [1, 2, 3, 4])
def test_one_cylinder_off_is_confirmed_after_a_cycle_of_evidence(cyl):
    u, rng = UegoInversion(), np.random.default_rng(cyl)
    got = _feed(u, [np.zeros(4)] * 40 + [_one_off(cyl, 0.5)] * 40, rng)
    names = [d for d, _, _ in got]
    first = names.index(float(cyl))
    # not on the first window of the new pattern: it must hold for `persist` windows
    assert 40 + u.persist - 1 <= first <= 40 + 12
    assert set(names[:first]) == {0.0} and set(names[first:]) == {float(cyl)}
    assert got[-1][1] == CONFIRMED and got[-1][2] == 1.0
    # evidence builds up before the name: suspect, with a rising confidence
    states = [s for _, s, _ in got[40:first]]
    assert SUSPECT in states and all(s in (NONE, SUSPECT) for s in states)


def test_two_opposite_cylinders_are_suspect_but_never_named():
    # two rich cylinders 360 deg apart: all four depart equally, no single cylinder stands out
    u, rng = UegoInversion(), np.random.default_rng(5)
    got = _feed(u, [np.array([-1.0, 1.0, 1.0, -1.0])] * 200, rng)
    assert {d for d, _, _ in got} == {0.0}
    assert got[-1][1] == SUSPECT


def test_a_departure_still_moving_is_not_evidence():
    # the estimate sweeps from one cylinder to another (a transient): no name while it moves
    u, rng = UegoInversion(), np.random.default_rng(7)
    sweep = [_one_off(2, 0.8) * np.sin(k / 3.0) + _one_off(4, 0.8) * np.cos(k / 3.0)
             for k in range(60)]
    got = _feed(u, [np.zeros(4)] * 40 + sweep, rng)
    assert {d for d, _, _ in got} == {0.0}
    # the same pattern held still is confirmed
    held = _feed(u, [_one_off(4, 0.8)] * 30, rng)
    assert held[-1][0] == 4.0


def test_a_named_cylinder_is_dropped_when_its_evidence_goes():
    u, rng = UegoInversion(), np.random.default_rng(9)
    got = _feed(u, [_one_off(3, 0.6)] * 40 + [np.zeros(4)] * 200, rng)
    names = [d for d, _, _ in got]
    assert names[39] == 3.0 and names[-1] == 0.0 and set(names) == {0.0, 3.0}
    assert got[-1][1] == NONE


def test_the_state_channels_say_settling_until_the_diagnosis_is_known():
    u = UegoInversion()
    out = u.step(0.1, {"ENGINE_SPEED": 1500.0})
    assert out["IMBALANCE_STATE"] == SETTLING and out["IMBALANCE_CONF"] == 0.0
    assert "IMBALANCE_CYL" not in out


DESIGN = {"observer": "afr_inversion",
          "identified": {"points": [{"rpm": 1500.0, "phase_deg": 230.0},
                                    {"rpm": 2500.0, "phase_deg": 290.0}],
                         "tau1": 0.03, "tau2": 0.015}}


def test_a_design_sets_the_windows_phase_per_speed_and_the_lags():
    u = UegoInversion()
    assert u.window_start(2000.0) == pytest.approx(140.0 + 6 * 2000.0 * 0.007)
    u.load_design(copy.deepcopy(DESIGN))
    assert (u.tau1, u.tau2) == (0.03, 0.015)
    assert u.window_start(2000.0) == pytest.approx(260.0)  # between the design's speeds
    assert u.window_start(1000.0) == pytest.approx(230.0)  # held at the ends
    assert u.window_start(4000.0) == pytest.approx(290.0)


@pytest.mark.parametrize("change, needle", [
    ({"observer": "twc"}, "not 'afr_inversion'"),
    ({"identified": {"tau1": 0.03, "tau2": 0.01}}, "no identified.points"),
    ({"identified": {"points": [{"rpm": 1500.0}], "tau1": 0.03, "tau2": 0.01}}, "incomplete"),
    ({"identified": {**DESIGN["identified"], "tau1": float("nan")}}, "finite"),
    ({"identified": {**DESIGN["identified"], "tau2": 5.0}}, "lags must be in"),
])
def test_a_bad_design_is_refused_by_name_and_nothing_changes(change, needle):
    u = UegoInversion()
    u.load_design(copy.deepcopy(DESIGN))
    bad = {**copy.deepcopy(DESIGN), **change}
    with pytest.raises(DesignError, match=needle):
        u.load_design(bad)
    assert (u.tau1, u.tau2) == (0.03, 0.015) and u.window_start(1500.0) == pytest.approx(230.0)


def test_a_design_round_trips_through_the_contract():
    u = UegoInversion()
    u.load_design(copy.deepcopy(DESIGN))
    again = UegoInversion()
    again.load_design(u.design())  # what the contract writes for it
    assert (again.tau1, again.tau2) == (0.03, 0.015)
    assert again.window_start(2000.0) == pytest.approx(260.0)
    # a design of the parameters alone puts the windows back on the model's delay
    again.load_design({"observer": "afr_inversion", "params": {"delay": 0.006}})
    assert again.window_start(2000.0) == pytest.approx(140.0 + 6 * 2000.0 * 0.006)
