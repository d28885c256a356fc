"""``testcell design imbalance``: the exhaust phase per speed and the UEGO lags from a run with
a known offset that starts part-way through, against the plant variant's own constants;
the refusal of a log without the offset."""

from __future__ import annotations

import json

import can
import numpy as np
import pytest

from cell.app.cli import main as cli
from cell.core.errors import ConfigError
from cell.design.cylinders import design_logs, parse_known_offset, read_cycles
from cell.estimators.cylinders import UegoInversion
from cell.experiments.robustness import (DESIGN_OFFSET, DESIGN_SPEEDS, SHORT, Variant,
                                         record_design_frames)
from cell.plant.cylinders import CylinderParams
from cell.plant.si_engine import steady_cycle
from cell.plant.si_turbo import si_turbo
from cell.sim.lockstep import Lockstep
from cell.sim.simulator import Simulator

#: a plant the observer was not written against; little mixing, so the window's start is
#: where the plant puts it: EVO + the extra phase + the transport delay + the mixing lag
PLANT = {"exhaust_phase": 40.0, "uego_lags": "0.030,0.015", "mixing": 0.0005}


def true_phase(rpm: float) -> float:
    p = CylinderParams()
    return p.evo_deg + PLANT["exhaust_phase"] + 6.0 * rpm * (p.delay + PLANT["mixing"])


def _write(path, frames):
    with can.Logger(str(path)) as w:
        for f in frames:
            w.on_message_received(f)
    return path


@pytest.fixture(scope="module")
def logs(tmp_path_factory, db):
    folder = tmp_path_factory.mktemp("imbalance-design")
    frames = record_design_frames(Variant("test", PLANT), 3, SHORT, db)
    sim = Simulator(si_turbo(steady_cycle(1500.0, 0.45, 1.6), 4), db)
    balanced = [f for _, got in Lockstep(sim).steps(160, frames=True) for f in got]
    return _write(folder / "offset.log", frames), _write(folder / "balanced.log", balanced)


@pytest.fixture(scope="module")
def designed(logs, tmp_path_factory):
    out = tmp_path_factory.mktemp("design-out") / "imbalance.json"
    rc = cli(["design", "imbalance", str(logs[0]), "--known-offset", "2:+0.15", "--out", str(out),
              "--quiet"])
    assert rc == 0
    return json.loads(out.read_text())


def test_the_design_finds_the_step_part_way_through(designed):
    step = designed["steps"][0]
    # the scenario frame went at SHORT.design_on; the first whole cycle after it is found
    assert SHORT.design_on <= step["t"] <= SHORT.design_on + 2 * 120.0 / DESIGN_SPEEDS[0]


def test_the_design_identifies_the_phase_per_speed_and_the_lags(designed):
    assert designed["observer"] == "afr_inversion"
    assert designed["known_offset"] == {"cylinder": 2, "offset": 0.15}
    pts = designed["identified"]["points"]
    assert [p["rpm"] for p in pts] == pytest.approx(list(DESIGN_SPEEDS), rel=0.02)
    for p in pts:
        # within 15 deg of where the plant puts it (the 180 deg window)
        assert abs(p["phase_deg"] - true_phase(p["rpm"])) < 15.0, p
    t1, t2 = designed["identified"]["tau1"], designed["identified"]["tau2"]
    # the lags' sum is the sensor's delay at low frequency: within 10 % of the plant's
    assert t1 >= t2 and t1 + t2 == pytest.approx(0.030 + 0.015, rel=0.10)
    fit = designed["fit"]
    assert fit["explained_held_out"] >= 0.9
    assert all(f["held_out_cycles"] >= 3 for f in fit["per_speed"])


def test_the_observer_loads_the_design_file(designed):
    u = UegoInversion()
    u.load_design(designed, "imbalance.json")
    ident = designed["identified"]
    assert (u.tau1, u.tau2) == (ident["tau1"], ident["tau2"])
    for p in ident["points"]:
        assert u.window_start(p["rpm"]) == pytest.approx(p["phase_deg"])


def test_a_log_without_the_offset_is_refused_and_nothing_written(logs, tmp_path, capsys):
    out = tmp_path / "d.json"
    rc = cli(["design", "imbalance", str(logs[1]), "--known-offset", "2:+0.15", "--out", str(out),
              "--quiet"])
    assert rc == 2 and not out.exists()
    err = capsys.readouterr().err
    assert "does not carry the known offset on cylinder 2" in err and "balanced.log" in err


def test_the_cycles_of_a_log_carry_its_speed(logs):
    c = read_cycles(logs[1])
    assert len(c.t) >= 15 and np.all(np.abs(c.rpm - 1500.0) < 30.0)
    assert np.all(np.diff(c.t) > 0)


@pytest.mark.parametrize("text, needle", [
    ("2", "not CYL:OFFSET"), ("5:+0.1", "1..4"), ("2:x", "not CYL:OFFSET"),
    ("2:+0.01", "0.03..0.5"), ("2:nan", "0.03..0.5"),
])
def test_bad_known_offsets_are_refused(text, needle):
    with pytest.raises(ConfigError, match=needle):
        parse_known_offset(text)


def test_a_design_needs_cycles_at_a_held_speed(db):
    sim = Simulator(si_turbo(steady_cycle(1500.0, 0.45, 0.5), 4), db)
    few = [f for _, got in Lockstep(sim).steps(50, frames=True) for f in got]
    with pytest.raises(ConfigError, match="whole engine cycles"):
        design_logs([few], DESIGN_OFFSET, db=db)
