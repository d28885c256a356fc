"""The air-path observer (cell/estimators/si_airpath.py): its gains, schedule, tuning and runtime."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cell.core.errors import ConfigError, ParamError
from cell.estimators.si_airpath import (
    DEFAULT_TABLE,
    MEASUREMENTS,
    OUTPUTS,
    AirPathObserver,
    GainTable,
    discrete_gain,
)


@pytest.fixture(scope="module")
def table():
    return GainTable.load()


def _riccati_by_iteration(F, H, Q, R, n=20000):
    """The a-priori covariance by iterating the Riccati recursion: an independent reference."""
    P = np.eye(F.shape[0])
    for _ in range(n):
        S = H @ P @ H.T + R
        P_new = F @ P @ F.T - F @ P @ H.T @ np.linalg.solve(S, H @ P @ F.T) + Q
        if np.allclose(P_new, P, rtol=1e-12, atol=1e-15):
            break
        P = P_new
    return P, P @ H.T @ np.linalg.inv(H @ P @ H.T + R)


def test_discrete_gain_matches_the_iterated_riccati_recursion():
    A = np.array([[-3.0, 1.0], [0.5, -0.2]])
    Q, R, dt = np.array([4e6, 1e4]), np.array([2e6]), 0.01
    K, P = discrete_gain(A, Q, R, [0], dt)
    n = 2
    F = np.eye(n) + np.linalg.solve(np.eye(n) - dt * A, dt * A)
    H = np.array([[1.0, 0.0]])
    P_ref, K_ref = _riccati_by_iteration(F, H, np.diag(Q), np.diag(R))
    np.testing.assert_allclose(P, P_ref, rtol=1e-6)
    np.testing.assert_allclose(K, K_ref, rtol=1e-6)


def test_shipped_table_gains_are_the_riccati_gains_of_its_points(table):
    pt = table.points[7]
    K, _ = discrete_gain(np.array(pt.A), np.array(pt.Q) * table.dt,
                         np.array([pt.R[m] for m in table.feedback]),
                         [MEASUREMENTS[m][0] for m in table.feedback], table.dt)
    np.testing.assert_allclose(np.array(pt.K["augmented"]), K, rtol=1e-8)
    assert len(table.points) == 35 and table.feedback == ("P_IC", "P_IM")


def test_nearest_point_by_speed_and_p_im(table):
    for i in (0, 12, 34):
        pt = table.points[i]
        assert table.nearest(pt.speed + 50.0, pt.p_im + 1000.0) == i


def test_table_files_refuse_bad_content(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ConfigError, match="not a JSON gain table"):
        GainTable.load(bad)
    bad.write_text(json.dumps({"format": "other"}))
    with pytest.raises(ConfigError, match="not a gain table"):
        GainTable.load(bad)
    with pytest.raises(ConfigError, match="not found"):
        GainTable.load(tmp_path / "missing.json")
    assert DEFAULT_TABLE.exists()


def _inputs(pt, **over):
    z = {"THROTTLE": pt.u[0], "WASTEGATE": 100 * pt.u[1], "ENGINE_SPEED": pt.u[2],
         "P_IC": pt.x[0] / 1000, "P_IM": pt.x[1] / 1000, "T_IM": pt.x[2] - 273.15,
         "N_TC": pt.x[4] * 30 / np.pi}
    return z | over


def test_at_a_table_point_with_its_own_measurements_the_observer_stays_put(table):
    pt = table.points[17]
    obs = AirPathObserver(table=table)
    for k in range(200):
        out = obs.step(k * 0.01, _inputs(pt))
    assert set(out) == set(OUTPUTS) | {"AIRPATH_CONF"}  # the contract adds the confidence
    assert out["P_IM_EST"] == pytest.approx(pt.x[1] / 1000, abs=0.01)
    assert out["N_TC_EST"] == pytest.approx(pt.x[4] * 30 / np.pi, rel=1e-3)
    assert out["DC_ETA_VOL_EST"] == pytest.approx(0.0, abs=1e-4)
    assert out["AIRPATH_POINT"] == 17


def test_augmented_state_removes_a_p_im_offset_the_plain_one_keeps(table):
    pt = table.points[17]
    z = _inputs(pt, P_IM=pt.x[1] / 1000 - 2.0)  # the engine pumps more than the model says
    ends = {}
    for aug in (0, 1):
        obs = AirPathObserver(table=table, augmentation=bool(aug))
        for k in range(1500):
            out = obs.step(k * 0.01, z)
        ends[aug] = out
    assert abs(ends[0]["P_IM_EST"] - z["P_IM"]) > 0.5
    assert ends[1]["P_IM_EST"] == pytest.approx(z["P_IM"], abs=0.1)
    assert ends[1]["DC_ETA_VOL_EST"] > 0.005  # more pumping: a positive ΔC_ηvol
    assert ends[0]["DC_ETA_VOL_EST"] == 0.0


def test_tuning_feedback_and_augmentation(table):
    obs = AirPathObserver(table=table)
    assert obs.params() == {"augmentation": 1, "feedback": ["P_IC", "P_IM"]}
    obs.set_params({"feedback": ["P_IM", "N_TC"], "augmentation": 0})
    assert obs.params() == {"augmentation": 0, "feedback": ["P_IM", "N_TC"]}
    pt = table.points[3]
    out = obs.step(0.0, _inputs(pt))
    assert out["DC_ETA_VOL_EST"] == 0.0
    for bad, match in (({"feedback": ["P_EM"]}, "P_EM is not a measurement"),
                       ({"feedback": []}, "non-empty list"),
                       ({"feedback": ["P_IM", "P_IM"]}, "twice"),
                       ({"augmentation": 2}, "<= 1"),
                       ({"gain": 1}, "not a parameter")):
        with pytest.raises(ParamError, match=match):
            obs.set_params({"augmentation": 1} | bad)  # all or nothing
        assert obs.params() == {"augmentation": 0, "feedback": ["P_IM", "N_TC"]}  # unchanged


def test_another_tick_period_gets_gains_solved_for_it(table):
    obs = AirPathObserver(table=table)
    pt = table.points[5]
    # 50 Hz (the runtime's default FAS) is stored in the table; 25 Hz is solved when asked
    for dt in (0.02, 0.04):
        M, K = obs._matrices(dt, True, ("P_IC", "P_IM"))
        K_ref, _ = table.solve(pt, ("P_IC", "P_IM"), True, dt)
        np.testing.assert_allclose(K[5], K_ref, rtol=1e-8)
        assert not np.allclose(K[5], np.array(pt.K["augmented"]))
    assert "augmented@0.02" in pt.K and "augmented@0.04" not in pt.K


def test_observer_runs_in_the_runtime_and_puts_its_estimates_on_the_bus():
    from cell.bus.dbc import load
    from cell.sim.lockstep import Lockstep
    from cell.plant.si_turbo import si_turbo
    from cell.runtime.scheduler import Rates, Runtime
    from cell.sim.simulator import Simulator

    db = load()
    sim = Simulator(si_turbo("steady", 0, crank=False), db)
    rt = Runtime(db, [AirPathObserver()], rates=Rates(FAS=100.0, MED=10.0))
    sent = []
    receive = sim.receive

    def tap(msg):  # the frames the runtime puts on the bus reach the simulator's side
        sent.append(msg)
        return receive(msg)
    sim.receive = tap
    Lockstep(sim, rt).run(3.0)
    names = {db.decode(m)[0].name for m in sent}
    assert {"AIRPATH_EST_1", "AIRPATH_EST_2"} <= names
    ch = rt.channels
    assert ch["P_IM_EST"].value == pytest.approx(ch["P_IM_TRUE"].value, abs=1.5)
    assert ch["N_TC_EST"].value == pytest.approx(ch["N_TC_TRUE"].value, rel=0.05)
    assert ch["AIRPATH_POINT"].value >= 0
    assert rt.block("airpath").state()["point"] is not None
