"""The large diesel's air path (seed 002, Appendix A), its components and its coupling."""

import math

import numpy as np
import pytest

from cell.bus.dbc import load
from cell.plant import airpath_parts as parts
from cell.plant.composition import Composition
from cell.plant.diesel import ETC_HOLD, ETC_HOLDS, DieselEngine, DutyCycle, duty_cycle
from cell.plant.diesel_airpath import (
    NO_BIAS,
    AirPathParams,
    DieselAirPath,
    airpath_jacobian,
    airpath_rhs,
)
from cell.plant.backpressure import ExhaustBanks
from cell.plant.large_diesel import large_diesel
from cell.core.settings import Settings
from cell.sim import build
from cell.sim.simulator import Simulator


# -- components ----------------------------------------------------------------------------
def test_orifice_is_choked_below_the_critical_ratio_and_continuous():
    g = 1.3
    crit = (2 / (g + 1)) ** (g / (g - 1))
    choked = math.sqrt(g * (2 / (g + 1)) ** ((g + 1) / (g - 1)))  # textbook choked Psi
    assert parts.flow_function(0.2, g) == pytest.approx(choked, rel=1e-9)
    assert parts.flow_function(crit * 0.999, g) == pytest.approx(choked, rel=1e-9)
    a, b = parts.flow_function(0.99 - 1e-9, g), parts.flow_function(0.99 + 1e-9, g)
    assert a == pytest.approx(b, rel=1e-5)
    assert parts.flow_function(1.0, g) == 0.0


def test_closed_forms():
    assert parts.cylinder_flow(1.0, 1e5, 300.0, 1200.0, 0.012) == pytest.approx(
        1e5 * 1200 * 0.012 / (120 * 287 * 300))
    assert parts.turbine_power(2.0, 900.0, 1.0, 0.7, parts.CP_EXH, parts.GAMMA_EXH) == 0.0
    # the compressor map: zero head at pressure ratio 1 gives the map's largest flow, a head
    # at the surge line none
    r, w = 0.1, 3000.0
    rho_area_u = 1e5 / (287.0 * 300.0) * math.pi * r * r * r * w
    assert parts.compressor_map_flow(1.0, w, r, 1.1, 0.2, 1e5, 300.0) == pytest.approx(0.2 * rho_area_u)
    pr_surge = (1.1 * (r * w) ** 2 / (2 * parts.CP_AIR * 300.0) + 1.0) ** (1.4 / 0.4)
    assert parts.compressor_map_flow(pr_surge * 1.01, w, r, 1.1, 0.2, 1e5, 300.0) == 0.0
    # turbine flow falls as the outlet pressure rises (the back-pressure coupling)
    w = [parts.turbine_flow(3e5, 800.0, p, 1e-3, 1.5, parts.R_EXH) for p in (1.0e5, 1.1e5, 1.2e5)]
    assert w[0] > w[1] > w[2] > 0


# -- the model --------------------------------------------------------------------------------
def _settled(biases, speed=1500.0, load_=0.75, valve=100.0, seconds=60.0):
    eng = DieselEngine(DutyCycle("hold", [(0.0, speed, load_)], seconds))
    banks = ExhaustBanks(seed=0, initial_valve=valve)
    air = DieselAirPath(biases=biases, seed=0)
    c = Composition("t", [eng, banks, air])
    c.run(seconds)
    return c, air


def test_unbiased_plant_is_a_steady_state_of_the_default_model():
    """With no bias the plant's settled state makes the default model's f vanish."""
    c, air = _settled(NO_BIAS)
    u = air._inputs(c.signals)
    f = airpath_rhs(0.0, air.x, u, AirPathParams())
    scale = np.array([1 / 0.1, 1 / 1.0, 1 / 0.05])  # kPa/s, kPa/s, krpm/s: slow against the states
    assert np.abs(f / scale).max() < 1.0


def test_biased_plant_is_not_a_steady_state_of_the_default_model():
    c, air = _settled(None)
    u = air._inputs(c.signals)
    f = airpath_rhs(0.0, air.x, u, AirPathParams())
    assert abs(f[1]) > 100.0  # kPa/s: the default model's exhaust pressure is far from here


def test_jacobian_against_central_differences():
    x = np.array([250.0, 330.0, 37.0])
    u = (250.0, 1500.0, 40.0, 25.0, 200.0, 200.0)
    p = AirPathParams()
    J = airpath_jacobian(0.0, x, u, p)
    for j, h in enumerate((1e-3, 1e-3, 1e-4)):
        e = np.zeros(3)
        e[j] = h
        num = (airpath_rhs(0, x + e, u, p) - airpath_rhs(0, x - e, u, p)) / (2 * h)
        np.testing.assert_allclose(J[:, j], num, rtol=2e-2, atol=1e-3 * np.abs(num).max())


def test_operating_points_are_physical():
    for speed, load_ in ((600.0, 0.0), (1200.0, 0.5), (1800.0, 1.0)):
        c, air = _settled(None, speed, load_, valve=40.0, seconds=40.0)
        s = c.signals
        assert 95.0 < s["DSL_P_IM_TRUE"] < 360.0
        assert s["DSL_P_EM_TRUE"] > s["DSL_P_IM_TRUE"] - 5.0  # a VGT diesel drives its EGR
        assert s["DSL_P_EM_TRUE"] > 101.325 + s["EXH_BP_L_TRUE"] * 9.80665e-3
        assert 0.0 <= s["VGT_POS"] <= 100.0 and 0.0 <= s["EGR_POS"] <= 100.0
    assert s["DSL_P_IM_TRUE"] == pytest.approx(334.4, abs=3.0)  # boost ratio 3.3 at rated


# -- the profile -----------------------------------------------------------------------------
def test_seed004_plants_behave_as_without_the_air_path():
    """The air path feeds nothing back: the back-pressure plant's outputs are unchanged."""
    full = large_diesel("transient", 3)
    bare = Composition("bare", [full.plants[0].__class__("transient", full.plants[0].params),
                                ExhaustBanks(full.plants[1].params, seed=3,
                                             initial_valve=full.plants[1].valves["L"].position)])
    for _ in range(1500):
        full.step()
        bare.step()
    for name in bare.signals:
        assert full.signals[name] == bare.signals[name], name


def test_no_pem_sensor_option_leaves_p_em_off_the_bus():
    db = load()
    on = Simulator(large_diesel("etc", 0), db)
    off = build(Settings.build({"no_pem_sensor": True}, environ={}), db)
    names_on = {m.name for m, _, _ in on.schedule}
    names_off = {m.name for m, _, _ in off.schedule}
    assert {"AIRPATH_SENS", "AIRPATH_PEM", "TRUTH_AIRPATH"} <= names_on
    assert names_on - names_off == {"AIRPATH_PEM"}
    assert "DSL_P_EM" not in off.plant.signals and "DSL_P_EM_TRUE" in off.plant.signals
    s = Settings.build({"no_pem_sensor": True}, environ={})
    assert "--no-pem-sensor" in s.sim_argv("virtual")
    assert "--no-pem-sensor" not in Settings.build({}, environ={}).sim_argv("virtual")
    env = Settings.build({}, environ={"TESTCELL_NO_PEM_SENSOR": "yes"})
    assert env.plant["no_pem_sensor"] is True


def test_truth_and_sensors_in_frames():
    db = load()
    sim = Simulator(large_diesel("etc", 0), db)
    for _ in range(200):
        sim.step()
    truth = {}
    for msg in sim.frames():
        if msg.arbitration_id in (960, 1872):
            truth.update(db.decode(msg)[1])
    assert truth["DSL_P_IM_TRUE"] == pytest.approx(sim.plant["DSL_P_IM_TRUE"], abs=0.02)
    assert truth["N_T"] == pytest.approx(sim.plant["N_T"], abs=1.0)


def test_etc_cycle_has_its_holds():
    c = duty_cycle("etc")
    assert c.duration == 1800.0
    assert duty_cycle("etc").knots == c.knots  # deterministic
    windows = c.steady_windows(settle=8.0)
    assert len(windows) == len(ETC_HOLDS)
    assert sum(1 for a, _ in windows if a < 300.0) == 3
    for a, b in windows:
        assert b - a == pytest.approx(ETC_HOLD - 8.0)
    speeds = [k[1] for k in c.knots]
    assert min(speeds) == 600.0 and max(speeds) <= 1800.0
