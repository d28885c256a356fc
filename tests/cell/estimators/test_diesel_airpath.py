"""The large diesel's air-path observers on the runtime (seed 002)."""

import json

import can

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


def test_unplugged_sensors_and_a_raw_minimum_are_refused_with_a_reason_and_recovered():
    """Issue 20, point 1: 0.5 s of an all-zero AIRPATH_SENS frame (every value inside its DBC
    range), then EXH_BP_R at its raw minimum: the observers do not step on them (no
    TypeError, no estimate at 1e10), their outputs are invalid with the reason, and they
    recover on the simulator's truth once the frames are good again."""
    db = load()
    sens, bp = db.message("AIRPATH_SENS").frame_id, db.message("EXH_BP").frame_id
    raw_min = (-(2 ** 31)).to_bytes(4, "little", signed=True)

    def wire(frames):
        out = []
        for m in frames:
            if m.arbitration_id == sens and 6.0 <= m.timestamp < 6.5:
                m = can.Message(arbitration_id=sens, data=bytes(8), timestamp=m.timestamp,
                                is_extended_id=m.is_extended_id)
            elif m.arbitration_id == bp and 8.0 <= m.timestamp < 8.5:
                m = can.Message(arbitration_id=bp, data=bytes(m.data[:4]) + raw_min,
                                timestamp=m.timestamp, is_extended_id=m.is_extended_id)
            out.append(m)
        return out

    hold = DutyCycle("hold", [(0.0, 1500.0, 0.75)], 12.0)
    sim = Simulator(large_diesel(hold, 0, biases=NO_BIAS, pem_sensor=False), db)
    blocks = airpath_observers()
    rt = Runtime(db, blocks)
    names = ("DSL_P_IM_EST_DEFAULT", "DSL_P_IM_EST")
    rows = []
    Lockstep(sim, rt, stride=2, wire=wire, on_tick=lambda t: rows.append(
        (t, rt.channels["DSL_P_IM_TRUE"].value,
         *[(rt.channels[n].status, rt.channels[n].reason, rt.channels[n].value) for n in names]))
             ).run(12.0)
    for t, truth, *chans in rows:
        for status, reason, value in chans:
            if 6.05 <= t < 6.5:
                assert status == "invalid" and "DSL_P_IM = 0 outside its plausible range" in reason
            if 8.05 <= t < 8.5:
                assert status == "invalid" and "EXH_BP_R" in reason and "plausible" in reason
            if value is not None and status == "ok":
                assert 5.0 < value < 1500.0  # never a diverged estimate on the bus
            if t > 10.0 or 5.0 < t < 6.0:
                assert status == "ok" and abs(value - truth) < 0.05 * truth, (t, value, truth)
    for b in blocks:
        c = b.state()["contract"]
        assert c["refused"]["DSL_P_IM"] >= 20 and c["refused"]["EXH_BP_R"] >= 20
        assert c["status"] == "ok" and c["gaps"] >= 1  # stale for 0.5 s, then restarted
        assert "resumed after a gap" in c["last_reset_reason"]


def test_the_models_domain_guard_keeps_powers_real_on_negative_pressures():
    """The observer's model never hands a negative base to a power: a state at -1e10 kPa or a
    back-pressure at its raw minimum gives finite real derivatives (the plant's own model
    raises TypeError there)."""
    from cell.estimators.diesel_airpath import default_model
    from cell.plant.diesel_airpath import AirPathParams, airpath_rhs

    u = np.array([200.0, 1500.0, 50.0, 20.0, 600.0, -21474836.48])
    with pytest.raises(TypeError):
        airpath_rhs(0.0, np.array([150.0, 200.0, 40.0]), u, AirPathParams())
    model = default_model()
    for x in ([150.0, 200.0, 40.0], [-1e10, -1e10, 1e10], [0.0, 0.0, 0.0]):
        f = model.f(0.0, np.array(x), u, model.params)
        assert f.dtype == float and np.isfinite(f).all()
