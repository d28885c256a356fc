"""The catalyst plant's variants (issue 18): the λ sensors' lag on λ or on composition,
their dead time and time constant, the kinetics and the cells, against answers written
plainly here; the defaults are the plant as it was."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cell.core.errors import ConfigError
from cell.core.settings import Settings
from cell.plant.catalyst import Catalyst, CatalystParams, catalyst_params
from cell.plant.catalyst_model import TWCKinetics
from cell.plant.composition import Composition


def sensor_step(variant, lam0=10.0, lam1=0.93, steps=40):
    """λ_pre of a cold catalyst's sensor (no storage) after λ steps from lam0 to lam1."""
    cat = Catalyst(catalyst_params(variant))
    comp = Composition("cat", [cat])
    comp.set_input("EXH_MASS_FLOW_TRUE", 0.01)
    comp.set_input("T_EXH_TRUE", 25.0)
    comp.set_input("LAMBDA_ENGINE_TRUE", lam0)
    for _ in range(400):  # settled: the start's state is gone to 1e-17
        comp.step()
    comp.set_input("LAMBDA_ENGINE_TRUE", lam1)
    out = []
    for _ in range(steps):
        comp.step()
        out.append(cat.s_lam_pre)
    return np.array(out), cat


def fractions(lam, k=TWCKinetics()):
    """O₂, CO, CO₂ mole fractions of feed gas of λ, written plainly."""
    if lam >= 1.0:
        c = k.y_c / (1.0 + k.y_c / k.y_o2_air * (lam - 1.0))
        return (lam - 1.0) * c, 0.0, c
    co = 2.0 * (1.0 - lam) * k.y_c
    return 0.0, co, k.y_c - co


def test_no_options_is_the_cell_own_plant():
    assert catalyst_params({}) == CatalystParams()
    assert catalyst_params({"osc": 0.6, "crank": "on"}) == CatalystParams()  # not the catalyst's


def test_lag_on_composition_lags_each_species_and_reports_their_lambda():
    got, cat = sensor_step({"lambda_sensor": "composition"})
    a = 1.0 - math.exp(-0.01 / 0.1)
    gas = np.array(fractions(10.0))
    want = []
    for _ in range(40):
        gas = gas + a * (np.array(fractions(0.93)) - gas)
        o2, co, co2 = gas
        want.append((2.0 * (o2 + co2) + co) / (2.0 * (co + co2)))  # eq. 12
    np.testing.assert_allclose(got, want, rtol=1e-9)
    plain, _ = sensor_step({})
    assert got[5] < plain[5] - 2.0  # leaving fuel cut, composition falls far faster


def test_dead_time_delays_and_tau_scale_slows_the_sensor():
    plain, _ = sensor_step({})
    late, _ = sensor_step({"lambda_dead_time": 0.05})
    np.testing.assert_allclose(late[5:], plain[:-5], rtol=1e-12)
    assert np.all(late[:5] == pytest.approx(10.0))
    slow, _ = sensor_step({"lambda_tau_scale": 2.0}, 1.0, 1.2, 30)
    k63 = int(np.argmax(slow >= 1.0 + 0.2 * (1 - math.exp(-1))))
    assert (k63 + 1) * 0.01 == pytest.approx(0.2, abs=0.011)


def test_kinetics_and_cells():
    p = catalyst_params({"kinetics_scale": 0.3, "storage_cells": 12, "thermal_cells": 1})
    k = TWCKinetics()
    assert p.kinetics.A1 == pytest.approx(0.3 * k.A1) and p.kinetics.A2 == pytest.approx(0.3 * k.A2)
    assert p.kinetics.cells == 12 and p.thermal.cells == 1 and p.sensors.t_cat_cell == 0
    cat = Catalyst(p)
    comp = Composition("cat", [cat])
    comp.set_input("EXH_MASS_FLOW_TRUE", 0.01)
    comp.set_input("T_EXH_TRUE", 500.0)
    comp.set_input("LAMBDA_ENGINE_TRUE", 0.97)
    for _ in range(300):
        comp.step()
    out = cat.output()
    phi = cat.phi
    assert out["SOX_1_TRUE"] == pytest.approx(np.mean(phi[0:4]))
    assert out["SOX_3_TRUE"] == pytest.approx(np.mean(phi[8:12]))
    assert out["SOX_TRUE"] == pytest.approx(np.mean(phi))
    one = Catalyst(catalyst_params({"storage_cells": 1}))
    assert one._thirds == [[0], [0], [0]]


@pytest.mark.parametrize("variant,needle", [
    ({"storage_cells": 0}, "--storage-cells must be 1..12"),
    ({"lambda_sensor": "voltage"}, "--lambda-sensor must be one of lambda, composition"),
    ({"kinetics_scale": 5.0}, "--kinetics-scale must be in [0.3, 3]"),
    ({"lambda_dead_time": -0.1}, "--lambda-dead-time must be in [0, 0.5]"),
])
def test_bad_variants_are_refused_by_flag(variant, needle):
    with pytest.raises(ConfigError, match=needle.replace("[", r"\[").replace("]", r"\]")):
        catalyst_params(variant)
    with pytest.raises(ConfigError, match=needle.split(" must")[0]):
        Settings.build({"engine": "si-turbo", **variant}, environ={})


def test_variants_are_engine_options_of_si_turbo():
    s = Settings.build({}, environ={"TESTCELL_LAMBDA_SENSOR": "composition",
                                    "TESTCELL_STORAGE_CELLS": "6", "TESTCELL_ENGINE": "si-turbo"})
    assert s.plant == {"lambda_sensor": "composition", "storage_cells": 6}
    argv = s.sim_argv("virtual")
    assert "--lambda-sensor" in argv and "--storage-cells" in argv
