"""The si-turbo engine's plants (cell/plant/si_engine.py): duty cycles, λ control, breathing."""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np
import pytest

from cell.bus.dbc import load
from cell.plant.composition import Composition
from cell.plant.si_engine import (
    LAMBDA_FUEL_CUT,
    SI_CYCLES,
    BreathingParams,
    SIBreathing,
    SICycle,
    SIEngine,
    SIEngineParams,
    ftp_cycle,
)
from cell.plant.si_turbo import si_turbo
from cell.sim import write_log


def run(plant, seconds, names):
    out = defaultdict(list)
    for _ in range(round(seconds / plant.dt)):
        plant.step()
        out["t"].append(plant.t)
        for n in names:
            out[n].append(plant[n])
    return {k: np.array(v) for k, v in out.items()}


def cycle(points, duration):
    """An SICycle through (t, speed, load) points, on a 0.1 s grid."""
    t = np.arange(0.0, duration, 0.1)
    tp, sp, lp = zip(*points)
    return SICycle("test", t, np.interp(t, tp, sp), np.interp(t, tp, lp), duration)


def test_ftp_cycle_has_the_ftp75_shape():
    c = ftp_cycle()
    v = c.vehicle_speed
    assert c.duration == 1874.0 and c.t[-1] == pytest.approx(1873.9)
    i505, i1369 = 5050, 13690
    assert 88.0 <= v.max() <= 95.0 and np.argmax(v) < i505  # the "hill" of phase 1
    assert v[i505:i1369].max() <= 56.0  # phase 2: stop-and-go
    np.testing.assert_array_equal(v[i1369:], v[:i505])  # hot start repeats the cold start
    km = v.sum() * 0.1 / 3600.0
    assert 15.0 <= km <= 19.0  # the FTP-75: 17.8 km
    stops = int(np.sum((v[1:] == 0) & (v[:-1] > 0)))
    assert 20 <= stops <= 35
    assert c.speed.min() >= 750.0 and c.speed.max() < 3000.0
    assert c.load.min() == 0.0 and 0.9 <= c.load.max() <= 1.0  # overrun, and the hill's climb
    assert list(SI_CYCLES)[:2] == ["ftp", "steady"]  # issue 10 adds throttle-steps, operating-points


def test_lambda_limit_cycles_about_one_at_steady_state():
    plant = si_turbo("steady")
    r = run(plant, 60.0, ["LAMBDA_ENGINE_TRUE", "FUEL_CUT_TRUE"])
    lam = r["LAMBDA_ENGINE_TRUE"][r["t"] > 10.0]
    assert abs(lam.mean() - 1.0) < 0.005
    amplitude = (lam.max() - lam.min()) / 2
    assert 0.01 < amplitude < 0.05
    crossings = np.flatnonzero(np.diff(np.sign(lam - 1.0)) != 0)
    period = 2.0 * np.mean(np.diff(crossings)) * plant.dt
    assert 0.3 < period < 3.0
    assert r["FUEL_CUT_TRUE"].max() == 0.0


def test_tip_in_goes_rich_and_tip_out_lean():
    c = cycle([(0, 2000, 0.2), (10, 2000, 0.2), (10.5, 2000, 0.8), (20, 2000, 0.8),
               (20.5, 2000, 0.2), (40, 2000, 0.2)], 40.0)
    plant = si_turbo(c)
    r = run(plant, 30.0, ["LAMBDA_ENGINE_TRUE"])
    t, lam = r["t"], r["LAMBDA_ENGINE_TRUE"]
    quiet = lam[(t > 5) & (t < 10)]
    tip_in = lam[(t > 10) & (t < 12)]
    tip_out = lam[(t > 20) & (t < 22)]
    assert tip_in.min() < quiet.min() - 0.04
    assert tip_out.max() > quiet.max() + 0.04


def test_fuel_cut_on_overrun_then_a_rich_purge():
    p = SIEngineParams()
    c = cycle([(0, 2000, 0.3), (5, 2000, 0.3), (5.1, 2000, 0.0), (10, 2000, 0.0),
               (10.1, 2000, 0.3), (20, 2000, 0.3)], 20.0)
    plant = si_turbo(c)
    names = ["LAMBDA_ENGINE_TRUE", "FUEL_CUT_TRUE", "FUEL_RATE", "ENGINE_TORQUE",
             "EXH_MASS_FLOW_TRUE"]
    r = run(plant, 20.0, names)
    t = r["t"]
    cut = r["FUEL_CUT_TRUE"] == 1.0
    assert t[cut].min() == pytest.approx(5.1 + p.fuel_cut_delay, abs=0.05)
    assert t[cut].max() == pytest.approx(10.0, abs=0.05)  # load returns after 10 s
    assert np.all(r["LAMBDA_ENGINE_TRUE"][cut] == LAMBDA_FUEL_CUT)
    assert np.all(r["FUEL_RATE"][cut] == 0.0) and np.all(r["ENGINE_TORQUE"][cut] == 0.0)
    # the purge: rich until the exhaust mass times the λ deficit reaches purge_mass
    lam = r["LAMBDA_ENGINE_TRUE"]
    purge = (t > 10.0) & (lam == p.purge_lambda)
    start, end = t[purge].min(), t[purge].max()
    assert start == pytest.approx(10.0, abs=0.05)
    assert np.all(purge[(t >= start) & (t <= end)])  # one unbroken purge
    deficit = np.sum(r["EXH_MASS_FLOW_TRUE"][purge] * (1 - p.purge_lambda)) * plant.dt
    assert deficit == pytest.approx(p.purge_mass, rel=0.02)
    assert 1.0 < end - start < p.purge_time_max


def test_breathing_gives_the_hand_computed_flow_and_temperature():
    # SIBreathing left the si-turbo profile for the mean-value air path (issue 10): test it
    # in a composition of its own
    plant = Composition("breathing", [SIEngine("steady"), SIBreathing()])  # 2000 rpm, 0.4
    r = run(plant, 30.0, ["EXH_MASS_FLOW_TRUE", "T_EXH_TRUE", "FUEL_RATE", "ENGINE_TORQUE",
                          "ENGINE_POWER", "LAMBDA_ENGINE_TRUE"])
    b = BreathingParams()
    charge = b.charge_idle + (b.charge_full - b.charge_idle) * 0.4
    air = 0.9 * 1.184 * 0.002 * 2000 / 120 * charge  # kg/s, four-stroke swept rate
    late = r["t"] > 25.0
    flow = r["EXH_MASS_FLOW_TRUE"][late].mean()
    assert flow == pytest.approx(air * (1 + 1 / 14.7), rel=0.01)
    assert r["T_EXH_TRUE"][-1] == pytest.approx(280 + 0.045 * 2000 + 230 * charge, abs=2.0)
    fuel_lph = r["FUEL_RATE"][late].mean()
    assert fuel_lph == pytest.approx(air / 14.7 * 3600 / 0.745, rel=0.02)
    power = r["ENGINE_POWER"][late].mean()
    torque = r["ENGINE_TORQUE"][late].mean()
    assert power == pytest.approx(torque * 2000 * math.pi / 30 / 1000, rel=1e-3)


def test_sim_writes_the_si_turbo_frames_at_their_cycle_times(tmp_path):
    import can

    db = load()
    n = write_log(tmp_path / "si.log", "ftp", seed=0, duration=2.0, engine="si-turbo",
                  crank="off", progress=False, db=db)  # the crank frames: test_cylinders.py
    frames = list(can.LogReader(str(tmp_path / "si.log")))
    assert len(frames) == n
    names = defaultdict(int)
    for msg in frames:
        names[db.decode(msg)[0].name] += 1
    expected = {"ENGINE_1": 100, "SI_ENGINE_2": 100, "TRUTH_SI_ENGINE": 200, "TWC_LAMBDA": 200,
                "TWC_FLOW": 200, "TWC_TEMP": 20, "TRUTH_TWC_SOX": 20, "TRUTH_TWC": 20,
                # the air path of issue 10 (dbc/si_airpath.dbc)
                "AIRPATH_SENSORS": 200, "AIRPATH_ACTUATORS": 200, "AIRPATH_TRUTH_1": 200,
                "AIRPATH_TRUTH_2": 200,
                # the simulator's own status (dbc/cell_commands.dbc)
                "SIM_STATUS": 20, "SIM_E2E": 20}
    assert dict(names) == expected
    assert SIEngine("steady").speed == 2000.0
