"""``testcell design airpath`` (cell/design/si_airpath.py): the gain table from a log,
and the refusal of logs that lack what the design needs."""

from __future__ import annotations

import math

import can
import numpy as np
import pytest

from cell.app.cli import main as cli
from cell.bus.dbc import load
from cell.core.errors import ConfigError
from cell.estimators.si_airpath import MEASUREMENTS, GainTable, discrete_gain
from cell.design.si_airpath import Q_FLOOR, R_FLOOR, design_log, read_channels
from cell.sim.lockstep import Lockstep
from cell.plant.si_airpath import MODEL_PARAMS, steady_state
from cell.plant.si_engine import _holds
from cell.plant.si_turbo import si_turbo
from cell.sim.simulator import Simulator

POINTS = [(1500.0, 0.3), (1500.0, 0.7), (2500.0, 0.3), (2500.0, 0.7)]


def _write(path, points, hold):
    cycle = _holds("design-test", points, hold, "four stationary points")
    sim = Simulator(si_turbo(cycle, seed=2, crank=False), load())
    with can.Logger(str(path)) as log:
        for msg in Lockstep(sim).frames(round(cycle.duration / sim.dt)):
            log.on_message_received(msg)
    return path


@pytest.fixture(scope="module")
def ops_log(tmp_path_factory):
    return _write(tmp_path_factory.mktemp("design") / "ops.log", POINTS, 10.0)


def test_design_gives_riccati_gains_from_the_stationary_data(ops_log, tmp_path):
    out = tmp_path / "gains.json"
    table = design_log(ops_log, out, speeds=(1500.0, 2500.0), progress=False)
    assert [(p.speed, round(p.load, 2)) for p in table.points] == POINTS
    loaded = GainTable.load(out)
    assert len(loaded.points) == 4
    data = read_channels(ops_log, progress=False)
    for i, pt in enumerate(table.points):
        t0, t1 = pt.window  # from --settle 6 s after the step to the next one
        assert t0 == pytest.approx(10.0 * i + 6.0, abs=0.1) and t1 == pytest.approx(10.0 * (i + 1), abs=0.1)
        # R_i: the stationary variance of each measured signal (§3.3.1), SI units, floored
        for name, (_, scale, _) in MEASUREMENTS.items():
            t, v = data[name]
            sel = (t >= t0) & (t <= t1)
            assert pt.R[name] == pytest.approx(max(np.var(v[sel]) * scale**2, R_FLOOR[name]), rel=1e-9)
        # x_stat: the default model at rest at the measured input; Q_i = (x_meas - x_stat)^2
        x = steady_state(MODEL_PARAMS, pt.u, pt.x[:5])
        np.testing.assert_allclose(pt.x[:5], x, rtol=1e-6)
        p_im_meas = data["P_IM"][1][(data["P_IM"][0] >= t0) & (data["P_IM"][0] <= t1)].mean() * 1000
        assert pt.Q[1] == pytest.approx(max((p_im_meas - x[1]) ** 2, Q_FLOOR[1]), rel=1e-9)
        assert pt.Q[3] == Q_FLOOR[3]  # p_em has no sensor: its floor
        # the gain solves the Riccati equation of the point
        K, _ = discrete_gain(np.array(pt.A)[:5, :5], np.array(pt.Q[:5]) * 0.01,
                             np.array([pt.R["P_IC"], pt.R["P_IM"]]), [0, 1], 0.01)
        np.testing.assert_allclose(np.array(pt.K["plain"]), K, rtol=1e-8)
    # the speed sets its table point's Jacobian: different points, different models
    assert not np.allclose(table.points[0].A, table.points[2].A)


def test_design_refuses_a_log_without_a_requested_speed_and_writes_nothing(ops_log, tmp_path):
    out = tmp_path / "gains.json"
    with pytest.raises(ConfigError, match="no stationary segment at 2000 rpm"):
        design_log(ops_log, out, speeds=(1500.0, 2000.0), progress=False)
    assert not out.exists()


def test_design_refuses_a_too_short_log(tmp_path):
    short = _write(tmp_path / "short.log", [(1500.0, 0.3)], 3.0)
    with pytest.raises(ConfigError, match="no stationary segment"):
        design_log(short, tmp_path / "g.json", progress=False)


def test_design_refuses_a_log_without_the_air_path_signals(tmp_path):
    from cell.sim import write_log

    diesel = tmp_path / "diesel.log"
    write_log(diesel, "rated", duration=1.0, progress=False)
    with pytest.raises(ConfigError, match="the log has no SI_LOAD_DEMAND, THROTTLE, WASTEGATE, "
                                          "P_IC, P_IM, T_IM, N_TC"):
        design_log(diesel, tmp_path / "g.json", progress=False)


def test_design_command_line(ops_log, tmp_path, capsys):
    out = tmp_path / "cli.json"
    assert cli(["design", "airpath", str(ops_log), "--out", str(out), "--speeds", "1500,2500",
                "--quiet"]) == 0
    assert "4 operating points" in capsys.readouterr().out
    assert GainTable.load(out).dt == 0.01
    # errors: one line naming what was wrong, exit code 2, nothing written
    bad = tmp_path / "bad.json"
    assert cli(["design", "airpath", str(ops_log), "--out", str(bad), "--speeds", "3000"]) == 2
    assert "no stationary segment at 3000 rpm" in capsys.readouterr().err
    assert cli(["design", "airpath", str(tmp_path / "none.log"), "--out", str(bad)]) == 2
    assert "log file not found" in capsys.readouterr().err
    assert cli(["design", "airpath", str(ops_log), "--out", str(bad), "--dt", "0"]) == 2
    assert "--dt must be in (0, 1]" in capsys.readouterr().err
    assert cli(["design", "airpath", str(ops_log), "--out", str(tmp_path / "g.npz")]) == 2
    assert "written as JSON" in capsys.readouterr().err
    assert not bad.exists() and not math.isnan(0.0)
