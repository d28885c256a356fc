"""Safety over HTTP (issue 20, points 2 and 7; issue 24): absurd parameters get 422 naming the
parameter, bound and value; a feedback channel there is not gets 422 naming the channels; a
controller is switched off even when the tuning file cannot be written."""

import json

import can
import pytest
from tests.helpers.client import local_client

from cell.app.cell import Cell
from cell.app.tuning import TuningStore
from cell.control.backpressure import controllers
from cell.core import registry
from cell.core.settings import Settings
from cell.estimators.backpressure import native_filters
from cell.runtime.scheduler import Runtime
from service.main import create_app

RUNNING = 1


def make(db, state, blocks):
    rt = Runtime(db, blocks)
    store = TuningStore(state)
    store.load()
    cell = Cell(runtime=rt, bus="virtual:test", tuning=store)
    return rt, cell, local_client(create_app(cell))


@pytest.fixture
def observers(db, tmp_path):
    blocks = registry.BLOCK_SETS["seed002-airpath"].build(Settings.build({}, environ={}))
    return make(db, tmp_path / "tuning.json", blocks)


@pytest.mark.parametrize("Q, words", [
    ([1e300, 1e300, 1e300], ["diagonal element [0] must be <= 1e+06", "1e+300"]),
    ([0.05, 5e-324, 1e-4], ["diagonal element [1] must be >= 1e-12", "5e-324"]),
])
def test_an_absurd_observer_q_is_422_naming_the_bound_and_keeps_the_old_one(observers, Q, words):
    rt, cell, c = observers
    before = c.get("/observers/airpath-default").json()["params"]
    r = c.patch("/observers/airpath-default", json={"Q": Q})
    assert r.status_code == 422, r.text
    (err,) = r.json()["detail"]
    assert err["loc"] == ["body", "Q"] and all(w in err["msg"] for w in words), err
    assert c.get("/observers/airpath-default").json()["params"] == before


@pytest.mark.parametrize("body, field", [({"Q": 1e300}, "Q"), ({"R": 5e-324}, "R"),
                                         ({"Q": 1e7, "R": 1e-4}, "Q")])
def test_an_absurd_kalman_q_or_r_is_422(db, tmp_path, body, field):
    rt, cell, c = make(db, tmp_path / "t.json", native_filters())
    r = c.patch("/filters/EXH_BP_R_Kalman", json=body)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", field], r.text
    assert rt.blocks["EXH_BP_R_Kalman"].Q == 1e-6


def test_a_feedback_that_is_no_channel_is_422_naming_the_channels(db, tmp_path):
    rt, cell, c = make(db, tmp_path / "t.json", [*native_filters(), *controllers("kalman")])
    before = c.get("/controllers/PI_R").json()["params"]
    r = c.patch("/controllers/PI_R", json={"feedback": "NOPE"})
    assert r.status_code == 422, r.text
    (err,) = r.json()["detail"]
    assert err["loc"] == ["body", "feedback"] and "'NOPE' is not a channel" in err["msg"]
    assert "EXH_BP_R_Kalman" in err["msg"] and "VALVE_POS_R" not in err["msg"]  # mmH2O only
    assert c.get("/controllers/PI_R").json()["params"] == before


def drive(rt, db, t0, t1):
    t = t0
    while t < t1 - 1e-9:
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 500.0, "EXH_BP_R": 500.0}, t))
        rt.ingest(db.encode("VALVE_POS", {"VALVE_POS_L": 100.0, "VALVE_POS_R": 100.0}, t))
        rt.ingest(db.encode("ENGINE_STATUS", {"ENGINE_STATE": RUNNING, "TRIP_REASON": 0,
                                              "EXH_BP_LIMIT": 1200, "ENGINE_LOAD": 100}, t))
        t = round(t + 0.01, 6)
    rt.advance(t1 - 0.01)
    return [db.decode(f)[1] for f in rt.take_outbox()
            if f.arbitration_id == db.message("VALVE_DEMAND").frame_id]


def test_disabling_a_controller_works_with_the_state_folder_unwritable(db, tmp_path, caplog):
    """The issue: 500 and the loop kept driving the valve. The state folder here lies under a
    regular file, so no one (root included) can create the tuning file."""
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    rt, cell, c = make(db, blocker / "state" / "tuning.json",
                       [*native_filters(), *controllers("kalman", enable=True)])
    assert drive(rt, db, 0.0, 2.0), "the enabled loop drives the valve"
    # another change cannot be saved: refused, undone, as before
    r = c.patch("/controllers/PI_R", json={"kp": 0.02})
    assert r.status_code == 500 and "cannot save tuning" in r.json()["detail"]
    assert rt.blocks["PI_R"].kp == 0.005
    r = c.patch("/controllers/PI_R", json={"enable": False})
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["params"]["enable"] is False
    (warning,) = out["warnings"]
    assert "PI_R" in warning and "applied but not saved" in warning and "not-a-folder" in warning
    assert warning in caplog.text  # logged
    h = c.get("/health").json()
    assert h["status"] == "degraded" and warning in h["reasons"] and h["unsaved"] == [warning]
    assert c.patch("/controllers/PI_L", json={"enable": False}).status_code == 200
    assert len(c.get("/health").json()["unsaved"]) == 2
    assert drive(rt, db, 2.0, 4.0) == []  # the loops stopped driving the valves: they hold
    # the disk is back: the next save succeeds and the warning is gone
    blocker.unlink()
    cell.tuning.path = tmp_path / "ok" / "tuning.json"
    assert c.patch("/controllers/PI_R", json={"kp": 0.004}).status_code == 200
    h = c.get("/health").json()
    saved = json.loads(cell.tuning.path.read_text())
    assert h["unsaved"] == [] and saved["controllers"]["PI_R"]["kp"] == 0.004


def test_health_counts_implausible_values_by_signal(db, tmp_path):
    rt, cell, c = make(db, tmp_path / "t.json", native_filters())
    drive(rt, db, 0.0, 1.0)
    m = db.message("EXH_BP")
    forged = can.Message(timestamp=1.0, arbitration_id=m.frame_id, is_extended_id=False,
                         data=m.encode({"EXH_BP_L": 70000, "EXH_BP_R": 2**31 - 1}, scaling=False,
                                       strict=False))
    rt.ingest(forged)
    rt.advance(1.1)
    assert c.get("/health").json()["implausible"] == {"EXH_BP_R": 1}
    ch = c.get("/channels/EXH_BP_R").json()
    assert ch["status"] == "invalid"
    assert "EXH_BP_R = 2.14748e+07 is outside its range -500..20000" in ch["reason"]


@pytest.mark.parametrize("field, value, words", [
    ("feedback", "VALVE_POS_R", ["VALVE_POS_R is in %", "PI_R needs mmH2O", "EXH_BP_R_Kalman"]),
    ("feedback", "ENGINE_STATE", ["ENGINE_STATE is of no known unit", "needs mmH2O"]),
    ("track", "EXH_BP_R", ["EXH_BP_R is in mmH2O", "needs %", "VALVE_POS_R"]),
    ("track", "NOPE", ["'NOPE' is not a channel", "channels in %: "]),
])
def test_a_channel_of_the_wrong_unit_is_422_naming_the_ones_that_would_do(db, tmp_path, field,
                                                                          value, words):
    rt, cell, c = make(db, tmp_path / "t.json", [*native_filters(), *controllers("kalman")])
    before = c.get("/controllers/PI_R").json()["params"]
    r = c.patch("/controllers/PI_R", json={field: value})
    assert r.status_code == 422, r.text
    (err,) = r.json()["detail"]
    assert err["loc"] == ["body", field] and all(w in err["msg"] for w in words), err["msg"]
    assert "VALVE_DEMAND_R" not in err["msg"]  # never the controller's own output
    assert c.get("/controllers/PI_R").json()["params"] == before


def test_a_mapped_channel_is_a_feedback_the_controller_takes(tmp_path):
    """A user's kPa signal mapped onto a cell channel is that channel, in mmH2O (--map)."""
    from pathlib import Path

    from cell.bus.dbc import load
    from cell.runtime import mapping

    daq = load([Path(__file__).resolve().parents[1] / "data" / "dbc" / "daq_kpa.dbc"])
    rt, cell, c = make(daq, tmp_path / "t.json", [*native_filters(), *controllers("kalman")])
    mapping.install(rt, ["EXH_BP_R=DAQ_BP_R"])
    r = c.patch("/controllers/PI_R", json={"feedback": "DAQ_BP_R"})  # kPa: refused
    assert r.status_code == 422 and "DAQ_BP_R is in kPa" in r.text, r.text
    r = c.patch("/controllers/PI_R", json={"feedback": "EXH_BP_R"})  # the mapped one: taken
    assert r.status_code == 200, r.text
    assert rt.blocks["PI_R"].feedback == "EXH_BP_R"
