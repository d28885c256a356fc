"""One spelling per unit: the DBC's, else the declared one respelled, else the one input's."""

import pytest

from cell.estimators.backpressure import native_filters
from cell.scripts.fdv import FdvBlock
from cell.runtime.scheduler import Runtime
from cell.scripts.manager import ScriptManager
from cell.runtime.units import key, spell, spellings


@pytest.fixture(scope="module")
def known(db):
    return spellings(s.unit for s in db.signals.values())


@pytest.mark.parametrize("text, want", [
    ("MM_H2O", "mmH2O"), ("mmh2o", "mmH2O"), ("mmH2O", "mmH2O"), ("none", ""), ("NONE", ""),
    ("hz", "Hz"), ("rpm", "rpm"), ("RPM", "rpm"), ("kw", "kW"), ("percent", "%"),
    ("mmh2o*s", "mmH2O*s"), ("mmh2o^2", "mmH2O^2"), ("mmh2o*s^-1", "mmH2O/s"), ("bar", "bar"), ("m/s", "m/s"),
])
def test_spellings_follow_the_dbc(known, text, want):
    assert spell(text, known) == want


def test_key_ignores_case_underscores_and_spaces():
    assert key("MM_H2O") == key("mm h2o") == key("mmH2O") == "mmh2o"


def test_every_channel_of_the_shipped_cell_has_one_spelling_per_unit(db):
    rt = Runtime(db, native_filters())
    assert ScriptManager(rt, None).load_defaults() == []
    units = {name: ch.unit for name, ch in rt.channels.items()}
    # the script outputs say what their inputs are measured in, as the DBC spells it
    for name in ("EXH_BP_R_MAF_CYF", "EXH_BP_R_Kalman_CYF",  # declared MM_H2O
                 "EXH_BP_R_MAF_FDV", "EXH_BP_R_Kalman_FDV",  # .fdv: computed from EXH_BP_R alone
                 "a_EXH_BP_R_maf.AV", "a_EXH_BP_R_maf.MX"):  # statistics of EXH_BP_R
        assert units[name] == db.signals["EXH_BP_R"].unit == "mmH2O", name
    assert units["a_EXH_BP_R_maf.IN"] == "mmH2O*s"  # an integral over time
    assert units["a_EXH_BP_R_maf.ST"] == "s" and units["a_EXH_BP_R_maf.RA"] == "Hz"
    assert units["K_EXH_BP_R"] == ""  # declared none: dimensionless
    # no two channels spell one unit two ways
    by_key: dict[str, set[str]] = {}
    for u in units.values():
        by_key.setdefault(key(u), set()).add(u)
    assert all(len(s) == 1 for s in by_key.values()), by_key


TWO_INPUTS = """[init]
dim acc
[formulas]
public ONE_INPUT_OUT
public TWO_INPUT_OUT
acc = 0.9 * acc + 0.1 * EXH_BP_L
ONE_INPUT_OUT = acc * 2
TWO_INPUT_OUT = EXH_BP_L - ENGINE_SPEED
"""


def test_an_fdv_output_takes_the_unit_of_its_one_input_and_no_unit_from_two(db):
    rt = Runtime(db)
    rt.add_block(FdvBlock("units.fdv", TWO_INPUTS))
    assert rt.channel("ONE_INPUT_OUT").unit == "mmH2O"  # through the local acc
    assert rt.channel("TWO_INPUT_OUT").unit == ""  # mmH2O and rpm: no one unit


def test_a_dbc_signal_keeps_the_dbc_unit_whatever_the_block_declares(db):
    rt = Runtime(db)
    block = FdvBlock("demand.fdv", "[formulas]\npublic VALVE_DEMAND_L\nVALVE_DEMAND_L = EXH_BP_L\n")
    block.units["VALVE_DEMAND_L"] = "mmH2O"
    rt.add_block(block)
    assert rt.channel("VALVE_DEMAND_L").unit == db.signals["VALVE_DEMAND_L"].unit == "%"
