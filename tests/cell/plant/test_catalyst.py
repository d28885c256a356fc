"""The three-way catalyst plant (cell/plant/catalyst.py, seed 000 section III) against
closed-form answers: the thermal steady state, the oxygen balance, capacity and sensors."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from cell.bus.dbc import load
from cell.core.errors import ConfigError
from cell.plant.catalyst import Catalyst, CatalystParams, SensorParams
from cell.plant.composition import Composition
from cell.plant.si_turbo import si_turbo
from cell.plant.catalyst_model import TWCKinetics, TWCThermal
from cell.bus.scenario import scenario_frames
from cell.sim.simulator import Simulator


def catalyst(**params):
    """A catalyst alone in a composition, its inputs set by hand."""
    cat = Catalyst(CatalystParams(**params))
    return Composition("cat", [cat]), cat


def drive(comp, seconds, mdot, T_exh, lam, names=()):
    comp.set_input("EXH_MASS_FLOW_TRUE", mdot)
    comp.set_input("T_EXH_TRUE", T_exh)
    comp.set_input("LAMBDA_ENGINE_TRUE", lam)
    out = {n: [] for n in names}
    for _ in range(round(seconds / comp.dt)):
        comp.step()
        for n in names:
            out[n].append(comp[n])
    return {n: np.array(v) for n, v in out.items()}


def test_thermal_steady_state_solves_eqs_13_and_14():
    th = replace(TWCThermal(), K_reac=0.0)  # no exotherm: a linear steady state
    comp, cat = catalyst(thermal=th, T_cat0=400.0)
    mdot, T_exh = 0.02, 500.0
    drive(comp, 600.0, mdot, T_exh, 1.0)
    # reference: eq. 13 for the gas, eq. 14 = 0 for the solid, cell by cell
    k = TWCKinetics()
    solid = th.rho_s * (1 - th.epsilon) * th.c_s
    kc, ko = th.h * th.A_geo / solid, 4 * th.h_out / (math.sqrt(4 * k.area / math.pi) * solid)
    beta = th.h * th.A_geo * k.area * (k.length / th.cells) / (mdot * th.c_pg)
    T_g, ref = T_exh, []
    for _ in range(th.cells):
        # 0 = -kc (Tc - Tg) - ko (Tc - Tamb), Tg = (Tg_prev + beta Tc) / (1 + beta)
        a = kc * (1 - beta / (1 + beta)) + ko
        Tc = (kc * T_g / (1 + beta) + ko * th.T_amb) / a
        T_g = (T_g + beta * Tc) / (1 + beta)
        ref.append(Tc)
    np.testing.assert_allclose(cat.T_cat, ref, rtol=1e-4)
    assert ref[0] > ref[-1] > th.T_amb  # the brick cools towards its back


def test_the_exotherm_heats_a_lit_catalyst_only():
    comp, cat = catalyst(T_cat0=100.0)
    drive(comp, 900.0, 0.02, 500.0, 1.0)
    lit = max(cat.T_cat)
    assert lit > 500.0 + 20.0  # reaction heat above the gas (eq. 4)
    comp2, cat2 = catalyst(T_cat0=100.0)
    drive(comp2, 900.0, 0.02, 150.0, 1.0)  # below light-off: no exotherm
    assert max(cat2.T_cat) < 151.0


def test_oxygen_balance_closes():
    """Stored oxygen equals what went in minus what came out (eqs. 12, 15-17):
    d(Σφ)/dt = 2 y_C ṁ (λ_in - λ_out) / (M_exh A_cs Δz OSC) for lean gas at λ < 1 + ...,
    integrated over a lean fill from empty."""
    comp, cat = catalyst(T_cat0=450.0, phi0=0.0)
    k = TWCKinetics()
    mdot, lam = 0.01, 1.02
    r = drive(comp, 20.0, mdot, 450.0, lam, ["LAMBDA_MID_TRUE", "SOX_TRUE"])
    y_c = k.y_c / (1 + k.y_c / k.y_o2_air * (lam - 1))  # feed gas carbon fraction
    osc = k.osc_fresh
    rate = 2 * y_c * mdot * (lam - r["LAMBDA_MID_TRUE"]) / (k.M_exh * k.area * k.dz * osc)
    stored = 3 * r["SOX_TRUE"][-1]
    assert stored == pytest.approx(np.sum(rate) * comp.dt, rel=0.02)
    assert r["SOX_TRUE"][-1] > 0.95 and r["LAMBDA_MID_TRUE"][-1] == pytest.approx(lam, abs=2e-3)


@pytest.mark.parametrize("osc", [1.0, 0.5])
def test_breakthrough_time_is_capacity_over_oxygen_flow(osc):
    comp, cat = catalyst(T_cat0=450.0, phi0=0.0, osc=osc)
    k = TWCKinetics()
    mdot, lam = 0.01, 1.02
    r = drive(comp, 25.0, mdot, 450.0, lam, ["LAMBDA_MID_TRUE"])
    t_break = (np.argmax(r["LAMBDA_MID_TRUE"] > 1.01) + 1) * comp.dt
    # O2 capacity: one O2 per two sites; O2 flow: (λ - 1) x carbon x molar flow
    y_c = k.y_c / (1 + k.y_c / k.y_o2_air * (lam - 1))
    t_fill = (osc * k.osc_fresh * k.volume / 2) / ((lam - 1) * y_c * mdot / k.M_exh)
    assert t_break == pytest.approx(t_fill, rel=0.15)


def test_a_cold_catalyst_stores_nothing():
    comp, cat = catalyst(phi0=0.5)
    r = drive(comp, 5.0, 0.01, 25.0, 1.05, ["LAMBDA_MID_TRUE", "SOX_TRUE"])
    assert r["LAMBDA_MID_TRUE"][-1] == pytest.approx(1.05, abs=1e-4)
    assert r["SOX_TRUE"][-1] == pytest.approx(0.5, abs=1e-3)


def test_sensors_have_their_documented_noise_and_lag():
    s = SensorParams()
    comp, cat = catalyst(T_cat0=450.0)
    r = drive(comp, 30.0, 0.02, 450.0, 1.0, ["LAMBDA_PRE", "EXH_MASS_FLOW", "T_CAT"])
    assert np.std(r["LAMBDA_PRE"][500:]) == pytest.approx(s.noise_lambda, rel=0.1)
    assert np.std(r["EXH_MASS_FLOW"][500:]) == pytest.approx(0.02 * s.noise_flow_rel, rel=0.1)
    assert np.std(r["T_CAT"][2000:] - cat.T_cat[s.t_cat_cell]) < 3 * s.noise_temp
    # a step of λ: the sensor reaches 63 % after its time constant
    comp.set_input("LAMBDA_ENGINE_TRUE", 1.2)
    pre = []
    for _ in range(50):
        comp.step()
        pre.append(cat.s_lam_pre)
    k63 = int(np.argmax(np.array(pre) >= 1.0 + 0.2 * (1 - math.exp(-1))))
    assert (k63 + 1) * comp.dt == pytest.approx(s.tau_lambda, abs=0.011)


def test_osc_option_drift_and_bad_values():
    comp = si_turbo("steady", osc=0.6, osc_drift=-3.6)  # -0.001 per second
    cat = comp.plant("catalyst")
    comp.run(100.0)
    assert cat.osc == pytest.approx(0.6 - 0.1, abs=1e-6)
    assert comp["OSC_TRUE"] == pytest.approx(0.5, abs=1e-6)
    for bad in ({"osc": 0.0}, {"osc": 3.0}, {"osc_drift": 50.0}):
        with pytest.raises(ConfigError, match="--osc"):
            Catalyst(CatalystParams(**bad))


def test_a_scenario_frame_steps_osc_in_the_simulator():
    db = load()
    sim = Simulator(si_turbo("steady"), db)
    sim.step()
    assert sim.plant["OSC_TRUE"] == 1.0
    (frame,) = scenario_frames(db, {"osc": 0.45})
    assert sim.receive(frame) is True
    sim.step()
    assert sim.plant["OSC_TRUE"] == pytest.approx(0.45)
    sim.step()
    assert sim.plant["OSC_TRUE"] == pytest.approx(0.45)  # holds until the next command


def test_osc_options_on_the_command_line(tmp_path, capsys):
    from cell.app import cli

    log = tmp_path / "aged.log"
    assert cli.main(["sim", "--engine", "si-turbo", "--osc", "0.6", "--duration", "1",
                     "--out", str(log)]) == 0
    import can

    db = load()
    osc = [db.decode(m)[1]["OSC_TRUE"] for m in can.LogReader(str(log))
           if db.decode(m)[0].name == "TRUTH_TWC"]
    assert osc and all(v == pytest.approx(0.6) for v in osc)
    capsys.readouterr()
    assert cli.main(["sim", "--engine", "si-turbo", "--osc", "3", "--out", str(log)]) == 2
    assert "--osc must be in [0.05, 2]" in capsys.readouterr().err
    assert cli.main(["sim", "--osc", "0.6", "--out", str(log)]) == 2
    assert "--osc is an option of si-turbo, not of large-diesel" in capsys.readouterr().err
