"""The SI air-path plant (cell/plant/si_airpath.py): balances, sensors, the model's errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cell.core.errors import ConfigError
from cell.plant.composition import Composition
from cell.plant.si_airpath import MODEL_PARAMS, PLANT_PARAMS, SIAirPath, airpath_rhs, flows, steady_state
from cell.plant.si_engine import SIEngine, SICycle


def _plant(speed=1800.0, load=0.4, seed=0):
    p = SIAirPath(seed=seed)
    p.start({"ENGINE_SPEED": speed, "SI_LOAD_DEMAND": load, "LAMBDA_ENGINE_TRUE": 1.0})
    return p


def test_started_plant_is_stationary_with_its_flows_balanced():
    p = _plant(1800.0, 0.4)
    f = flows(p.x, p._u, PLANT_PARAMS)
    # mass balance of every volume at rest: compressor = throttle = engine, turbine + wastegate
    # = engine out (1e-3 relative: the ECU's loops have had their settling time)
    assert f.w_c == pytest.approx(f.w_th, rel=2e-3)
    assert f.w_th == pytest.approx(f.w_ac, rel=2e-3)
    assert f.w_t + f.w_wg == pytest.approx(f.w_eo, rel=2e-3)
    out = p.output()
    assert out["EXH_MASS_FLOW_TRUE"] == pytest.approx(f.w_ac * (1 + 1 / 14.7))
    # fuel for lambda 1, in L/h of gasoline
    assert out["FUEL_RATE"] == pytest.approx(f.w_ac / 14.7 * 3600 / 0.745)
    assert out["ENGINE_POWER"] == pytest.approx(out["ENGINE_TORQUE"] * 1800 * math.pi / 30 / 1000)
    assert out["CAC_TRUE"] == pytest.approx(f.cac * 1e6)
    # the catalyst-inlet temperature: issue 8's map over the relative charge (air over the
    # swept volume at ambient density and η_vol 0.9), below the manifold's
    charge = f.w_ac / (0.9 * 101300 / (287 * 298) * 2.3e-3 * 1800 / 120)
    assert out["T_EXH_TRUE"] == pytest.approx(min(280 + 0.045 * 1800 + 230 * charge, 950), rel=1e-9)
    assert out["T_EXH_TRUE"] < f.T_em - 273.15


def test_steady_state_is_a_rest_point_of_the_model():
    u = (30.0, 0.2, 2500.0, 1.0)
    x = steady_state(MODEL_PARAMS, u)
    d = np.array(airpath_rhs(0.0, x, u, MODEL_PARAMS)) / np.array([1e5, 1e5, 300, 1e5, 1e4])
    assert np.max(np.abs(d)) < 1e-6


def test_sensors_have_their_documented_noise_ripple_and_lag():
    p = _plant(1800.0, 0.4)
    n = 3000
    rows = []
    for k in range(n):
        p.step((k + 1) * 0.01, {"ENGINE_SPEED": 1800.0, "SI_LOAD_DEMAND": 0.4, "LAMBDA_ENGINE_TRUE": 1.0})
        rows.append(p.output())
    pic = np.array([r["P_IC"] - r["P_IC_TRUE"] for r in rows])
    pim = np.array([r["P_IM"] - r["P_IM_TRUE"] for r in rows])
    prm = PLANT_PARAMS
    assert np.std(pic) == pytest.approx(prm.noise_p_ic / 1000, rel=0.1)
    # white noise plus the sampled pumping ripple: variance sigma^2 + (a p_im)^2 / 2
    p_im = np.mean([r["P_IM_TRUE"] for r in rows])
    expect = math.sqrt((prm.noise_p_im / 1000) ** 2 + (prm.ripple_p_im * p_im) ** 2 / 2)
    assert np.std(pim) == pytest.approx(expect, rel=0.1)
    # a step in the true T_im reaches the thermocouple with its time constant
    T_true0 = p.x[2]
    p.x[2] = T_true0 + 10.0
    p.T_sensor = T_true0
    a = p._a_T
    p._update()
    sensor = [p.T_sensor]
    for _ in range(round(prm.tau_T_im_sensor / 0.01)):
        p.x[2] = T_true0 + 10.0
        p.T_sensor += a * (p.x[2] - p.T_sensor)
        sensor.append(p.T_sensor)
    assert sensor[-1] - T_true0 == pytest.approx(10.0 * (1 - math.exp(-1)), rel=0.02)


def test_the_default_model_is_wrong_about_the_engine_as_documented():
    p = _plant(1800.0, 0.3)
    x_model = steady_state(MODEL_PARAMS, p._u, p.x)
    # η_vol 5 % low: the model's manifold pressure is higher at the same throttle
    assert x_model[1] - p.x[1] > 500.0
    assert MODEL_PARAMS.c_eta_vol < PLANT_PARAMS.c_eta_vol
    assert MODEL_PARAMS.comp_flow_offset != PLANT_PARAMS.comp_flow_offset


def test_throttle_step_moves_p_im_fast_and_the_thermocouple_slowly():
    cycle = SICycle("step", np.array([0.0, 2.0, 2.02, 6.0]), np.full(4, 1800.0),
                    np.array([0.3, 0.3, 0.7, 0.7]), 6.0)
    comp = Composition("t", [SIEngine(cycle), SIAirPath(seed=1)])
    rows = []
    for _ in range(600):
        comp.step()
        rows.append((comp.t, comp["P_IM_TRUE"], comp["T_IM_TRUE"], comp["T_IM"]))
    a = np.array(rows)
    after = a[:, 0] > 2.5
    before = a[:, 0] < 2.0
    assert a[after, 1].min() > a[before, 1].max() + 20.0  # kPa, within half a second
    # the true manifold temperature jumps with the step (fast dynamics, seed 003 Figure 1);
    # the thermocouple shows a fraction of that jump in the half second after it
    win = (a[:, 0] > 2.0) & (a[:, 0] < 2.5)
    jump_true = np.max(np.abs(a[win, 2] - a[before, 2].mean()))
    jump_sensor = np.max(np.abs(a[win, 3] - a[before, 3].mean()))
    assert jump_true > 3.0
    assert jump_sensor < 0.35 * jump_true


def test_bad_substeps_are_refused():
    from dataclasses import replace

    with pytest.raises(ConfigError, match="substeps"):
        SIAirPath(replace(PLANT_PARAMS, substeps=0))


def test_throttle_steps_and_operating_points_cycles():
    from cell.plant.si_engine import OPERATING_LOADS, OPERATING_SPEEDS, SI_CYCLES, THROTTLE_STEP_LOADS

    ts = SI_CYCLES["throttle-steps"]()
    assert np.all(ts.speed == 1800.0)
    levels = [ts.setpoint(8.0 * i + 4.0)[1] for i in range(len(THROTTLE_STEP_LOADS))]
    assert levels == pytest.approx(list(THROTTLE_STEP_LOADS))
    assert len(THROTTLE_STEP_LOADS) - 1 >= 10  # at least ten step cases (seed 003: twenty)
    ops = SI_CYCLES["operating-points"]()
    pts = {ops.setpoint(10.0 * i + 5.0) for i in range(len(OPERATING_SPEEDS) * len(OPERATING_LOADS))}
    assert pts == {(s, ld) for s in OPERATING_SPEEDS for ld in OPERATING_LOADS}
    assert ops.duration == 10.0 * len(pts)
