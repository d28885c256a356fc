"""``testcell design twc`` (issue 18) against the simulator's own sensor model: it finds
whether the λ sensors' lag acts on λ or on composition, and their time constant, from logs of
plant variants; it refuses a log without fuel cuts, writing nothing."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cell.app import cli
from cell.design.catalyst import SIGNALS, design
from cell.plant.catalyst import catalyst_params
from cell.plant.si_turbo import si_turbo

pytestmark = pytest.mark.slow


def plant_signals(variant, seconds=600.0, seed=1):
    """The observer's four sensor signals every 10 ms from the si-turbo plant (FTP-like)."""
    comp = si_turbo("ftp", seed, crank=False, catalyst=catalyst_params(variant))
    n = round(seconds / comp.dt)
    a = np.empty((n, 4))
    for i in range(n):
        comp.step()
        a[i] = [comp[s] for s in SIGNALS]
    t = np.arange(n) * comp.dt
    return {s: (t, a[:, j]) for j, s in enumerate(SIGNALS)}


@pytest.fixture(scope="module", params=[{}, {"lambda_sensor": "composition",
                                             "lambda_tau_scale": 1.5}],
                ids=["lambda", "composition-x1.5"])
def designed(request):
    return request.param, design(plant_signals(request.param), 1.0)


def test_the_sensor_lag_and_time_constant_are_identified(designed):
    variant, d = designed
    got = d["identified"]
    assert got["lambda_lag"] == variant.get("lambda_sensor", "lambda")
    assert got["tau_lambda"] == pytest.approx(0.1 * variant.get("lambda_tau_scale", 1.0), rel=0.1)
    fit = d["fit"]
    assert fit["windows"] >= 3 and fit["windows_held_out"] >= 1
    # the held-out transients are predicted to about the sensor noise (0.002)
    assert fit["rmse_held_out"] < 0.005
    other = [f for lag, f in fit["by_lag"].items() if lag != got["lambda_lag"]][0]
    assert other["cost"] > 10 * fit["by_lag"][got["lambda_lag"]]["cost"]


def test_a_log_without_fuel_cuts_is_refused_and_nothing_written(tmp_path, capsys):
    log = tmp_path / "steady.log"
    assert cli.main(["sim", "--engine", "si-turbo", "--duty", "steady", "--duration", "20",
                     "--crank", "off", "--out", str(log)]) == 0
    out = tmp_path / "twc.json"
    assert cli.main(["design", "twc", str(log), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "0 warm fuel cut(s)" in err and "at least 3 are needed" in err
    assert not out.exists()


def test_the_design_file_names_its_observer_and_loads(designed, tmp_path):
    from cell.estimators.catalyst import TWCObserver
    from cell.estimators.contract import read_design, write_design

    _, d = designed
    path = write_design(d, tmp_path / "twc.json")
    data = read_design(path)
    assert data["observer"] == "twc" and json.loads(path.read_text())["fit"]["rmse_fit"] > 0
    ob = TWCObserver()
    ob.load_design(data, str(path))
    assert ob.sensor_model()["lambda_lag"] == d["identified"]["lambda_lag"]
