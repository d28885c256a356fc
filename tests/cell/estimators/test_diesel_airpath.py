"""The large diesel's air-path observers on the runtime (seed 002)."""

import json

import numpy as np
import pytest

from cell import app
from cell.core import registry
from cell.bus.dbc import load
from cell.core.errors import ConfigError
from cell.estimators.diesel_airpath import (
    SHIPPED_DESIGN,
    airpath_observers,
    augmented_observer,
    default_observer,
    load_design,
)
from cell.sim.lockstep import Lockstep
from cell.plant.diesel import DutyCycle
from cell.plant.diesel_airpath import NO_BIAS
from cell.plant.large_diesel import large_diesel
from cell.runtime.scheduler import Runtime
from cell.core.settings import Settings
from cell.sim.simulator import Simulator


def test_block_set_of_large_diesel_has_both_observers_on_the_dbc():
    app.load()
    bs = registry.BLOCK_SETS["seed002-airpath"]
    assert bs.applies_to("large-diesel") and not bs.applies_to("toy")
    blocks = bs.build(Settings.build({}, environ={}))
    assert [b.name for b in blocks] == ["airpath-default", "airpath-augmented"]
    db = load()
    outs = set(blocks[0].outputs) | set(blocks[1].outputs)
    for name in ("DSL_P_EM_EST_DEFAULT", "DSL_P_EM_EST", "DSL_P_IM_EST", "N_T_EST", "Q_BIAS_1"):
        assert name in outs and name in db.signals
    assert "DSL_P_EM" not in blocks[1].inputs  # not measured at run time
    assert {"DSL_P_IM", "N_T"} <= set(blocks[1].inputs)
    Runtime(db, blocks)  # the runtime accepts them (outputs are RUNTIME signals)


def test_design_setting_is_loaded_and_a_refused_design_names_its_column(tmp_path):
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"Aq": [[0.6, 0.0], [0.8, 0.5], [0.0, 0.5]]}))
    blocks = airpath_observers(good)
    assert "Q_BIAS_2" in blocks[1].outputs
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"Aq": [[0.0], [1.0], [0.0]]}))
    with pytest.raises(ConfigError, match=r"bad.json.*column 1.*P_EM"):
        airpath_observers(bad)
    with pytest.raises(ConfigError, match="no such file"):
        airpath_observers(tmp_path / "missing.json")
    assert load_design(SHIPPED_DESIGN).shape[0] == 3


def test_observers_are_tunable():
    obs = augmented_observer(load_design(SHIPPED_DESIGN))
    n = len(obs.model.states)
    obs.set_params({"Q": [0.1] * n})
    assert obs.params()["Q"] == [0.1] * n
    with pytest.raises(Exception, match="Q"):
        obs.set_params({"Q": [0.1] * (n + 1)})


def test_default_observer_tracks_an_unbiased_engine():
    """When the engine equals the default model the default observer has no bias: its
    P_EM (not measured) settles within a few kPa of the truth."""
    db = load()
    hold = DutyCycle("hold", [(0.0, 1500.0, 0.75)], 40.0)
    sim = Simulator(large_diesel(hold, 0, biases=NO_BIAS, pem_sensor=False), db)
    rt = Runtime(db, [default_observer()])
    rows = []
    Lockstep(sim, rt, stride=2, on_tick=lambda t: rows.append(
        (t, rt.channels["DSL_P_EM_EST_DEFAULT"].value, rt.channels["DSL_P_EM_TRUE"].value))).run(40.0)
    a = np.array([r for r in rows if r[0] > 20.0 and r[1] is not None], dtype=float)
    assert len(a) > 150
    assert abs(np.mean(a[:, 1] - a[:, 2])) < 3.0
