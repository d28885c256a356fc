"""Seed 002's design tool, ``testcell design bias LOG`` (:mod:`cell.design.diesel_airpath`):
the design file from a log, the approaches agree, bad logs and options are refused and
nothing is written. The design log and file are shared (``tests/cell/conftest.py``)."""

import json

import can
import numpy as np
import pytest

from cell.core.errors import ConfigError
from cell.design import diesel_airpath as D
from cell.estimators.augmentation import largest_angle_deg
from cell.estimators.diesel_airpath import load_design
from cell.sim import write_log
from tests.cell.conftest import design_args


def test_design_file_has_aq_and_singular_values(design):
    d, path = design
    assert d["approach"] == 2 and d["design_sensors"] == ["P_IM", "P_EM", "N_T"]
    assert len(d["segments"]) >= 3  # the etc holds in the first 300 s
    s = d["singular_values"]
    assert s == sorted(s, reverse=True) and d["n_q"] == 1 and s[1] < 0.1 * s[0]
    Aq = load_design(path)
    assert Aq.shape == (3, 1)
    # the dominant bias raises the exhaust manifold pressure with the intake pressure
    assert Aq[1, 0] > 0.3 and Aq[0, 0] > 0.1


def test_design_without_pem_sensor_gives_zero_pem_row(design_log, tmp_path):
    """§4.4: with no sensor on P_EM, its row of A_q comes out zero."""
    out = tmp_path / "d.json"
    D.main(design_args(design_log, out, states="P_IM,N_T"))
    Aq = load_design(out)
    assert Aq[1, 0] == 0.0 and np.abs(Aq[[0, 2], 0]).max() > 0.1


@pytest.mark.parametrize("approach", [1, 3])
def test_approaches_1_and_3_agree_with_approach2(design_log, design, tmp_path, approach):
    """§4.1 (measured states, no observer) and §4.3 (maximally augmented observer) find the
    direction Approach 2 finds."""
    out = tmp_path / "d.json"
    D.main(design_args(design_log, out, approach=approach))
    assert json.loads(out.read_text())["approach"] == approach
    assert largest_angle_deg(load_design(out), np.array(design[0]["Aq"])) < 5.0


def test_approach1_needs_every_state_measured(design_log, tmp_path):
    with pytest.raises(ConfigError, match="approach 1 needs every state"):
        D.main(design_args(design_log, tmp_path / "d.json", approach=1, states="P_IM,N_T"))


# -- bad input --------------------------------------------------------------------------------
def test_log_without_stationary_segment_is_refused(tmp_path):
    log = tmp_path / "short.log"
    write_log(log, "etc", seed=0, duration=40.0, progress=False)
    out = tmp_path / "d.json"
    with pytest.raises(ConfigError, match="no stationary segment"):
        D.main(design_args(log, out))
    assert not out.exists()


def test_log_without_air_path_signals_is_refused(design_log, tmp_path):
    log = tmp_path / "no_airpath.log"
    with can.Logger(str(log)) as w:
        for i, msg in enumerate(can.LogReader(str(design_log))):
            if msg.arbitration_id not in (960, 961) :
                w.on_message_received(msg)
            if i > 20000:
                break
    out = tmp_path / "d.json"
    with pytest.raises(ConfigError, match="no values of .*VGT_POS"):
        D.main(design_args(log, out))
    assert not out.exists()


@pytest.mark.parametrize("kw, match", [({"states": "P_IM,BOOST"}, "BOOST is not an air-path state"),
                                       ({"dim": 3}, "--dim must be 1..2")])
def test_bad_design_options_are_refused(design_log, tmp_path, kw, match):
    out = tmp_path / "d.json"
    with pytest.raises(ConfigError, match=match):
        D.main(design_args(design_log, out, **kw))
    assert not out.exists()


def test_malformed_log_line_is_refused_with_its_line(tmp_path):
    log = tmp_path / "bad.log"
    log.write_text("(0.000000) vcan0 3C0#0102030405060708\nthis is not a frame\n")
    out = tmp_path / "d.json"
    with pytest.raises(ConfigError, match=r"bad.log:2"):
        D.main(design_args(log, out))
    assert not out.exists()


def test_missing_log_and_bad_design_file(tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        D.main(design_args(tmp_path / "nope.log", tmp_path / "d.json"))
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"Aq": [[1.0, 2.0]]}))
    with pytest.raises(ConfigError, match="3 x n_q"):
        load_design(bad)
    bad.write_text("{")
    with pytest.raises(ConfigError, match="not a readable JSON"):
        load_design(bad)
