"""What the page and ``replay --plot`` label their axes with: the channels' own units.

The air-path observers' predicted turbo speed (``AIRPATH_*_N_T_HAT``) is in rpm, as its
sensor ``N_T`` (the DBC's unit), while their state ``N_T_EST`` is in krpm; ``replay --plot``
draws one panel per unit, each y axis labelled with it.
"""

from __future__ import annotations

import can
import numpy as np
import pytest

from cell.analysis import figures
from cell.app.cli import main
from cell.estimators import diesel_airpath


@pytest.mark.parametrize("which", [0, 1])  # the default and the augmented observer (shipped design)
def test_the_air_path_observers_predicted_turbo_speed_is_in_the_sensors_unit(db, which):
    block = diesel_airpath.airpath_observers()[which]
    hats = [n for n in block.outputs if n.endswith("_N_T_HAT")]
    assert len(hats) == 1
    assert block.units[hats[0]] == db.signals["N_T"].unit == "rpm"
    state = next(n for n in block.outputs if n.startswith("N_T_EST") and not n.endswith("_SD"))
    assert block.units[state] == db.signals[state].unit == "krpm"
    # the prediction is the state in the sensor's unit: h(x) = 1000 x for the turbo speed
    x = np.array([150.0, 180.0, 42.0])
    assert diesel_airpath._h(0.0, x, None, None)[2] == pytest.approx(1000 * x[2])


def test_replay_plot_labels_each_axis_with_its_channels_unit(db, tmp_path, monkeypatch):
    log = tmp_path / "cell.log"
    with can.Logger(str(log)) as w:
        for i in range(300):  # 3 s at 100 Hz
            t = 1000.0 + i * 0.01
            w.on_message_received(db.encode("EXH_BP", {"EXH_BP_L": 600.0, "EXH_BP_R": 610.0 + i % 7}, t))
            w.on_message_received(db.encode("ENGINE_1", {"ENGINE_SPEED": 1500.0 + i, "ENGINE_POWER": 500.0,
                                                         "FUEL_RATE": 100.0, "ENGINE_TORQUE": 2000.0}, t))
    drawn = []
    real_save = figures.save
    monkeypatch.setattr(figures, "save", lambda fig, path, **kw: (drawn.append(
        [(ax.get_ylabel(), [ln.get_label() for ln in ax.get_lines()]) for ax in fig.axes]),
        real_save(fig, path, **kw))[1])
    png = tmp_path / "plot.png"
    assert main(["replay", str(log), "--out", str(tmp_path / "o.csv"), "--plot", str(png), "--quiet",
                 "--channels", "EXH_BP_R,ENGINE_SPEED,EXH_BP_R_Kalman"]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert drawn == [[("mmH2O", ["EXH_BP_R", "EXH_BP_R_Kalman"]), ("rpm", ["ENGINE_SPEED"])]]
