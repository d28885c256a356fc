"""Defects found when the cell was tried as a new user would: each one stays fixed.

- a script reading an input that no channel provides is accepted with the input named;
- a deleted script's errors leave ``/health`` with it;
- ``/health`` turns ``degraded`` (with the reason) when the bus falls silent;
- a trip shows in ``/health`` with its reason, and the two steps ``POST /engine/reset`` then
  ``POST /engine/reset/confirm`` (or the same two steps as scenario frames) reset it, in a
  simulator fed through the bus frames; a single frame does not.
"""


from tests.helpers.client import local_client

from cell.bus.scenario import scenario_frames
from cell.core import registry
from cell.app.cell import Cell
from cell.estimators.backpressure import native_filters
from cell.plant import TRIPPED
from cell.runtime.scheduler import Runtime
from cell.scripts.manager import ScriptManager
from cell.core.settings import Settings
from cell.sim import build as build_sim
from cell.app.tuning import TuningStore
from service.main import create_app
from tests.helpers.frames import feed as bp_feed
from tests.helpers.frames import steady, wavy


def feed(rt, db, t0, t1):
    bp_feed(rt, db, t0, t1, left=steady(600.0), right=wavy(600.0))


def make(db, tmp_path):
    rt = Runtime(db, native_filters())
    store = TuningStore(tmp_path / "tuning.json")
    mgr = ScriptManager(rt, store)
    return rt, mgr, local_client(create_app(Cell(runtime=rt, tuning=store, scripts=mgr)))


def test_script_reading_an_unknown_input_is_accepted_with_the_input_named(db, tmp_path):
    rt, mgr, c = make(db, tmp_path)
    r = c.put("/scripts/typo.fdv", content="[formulas]\npublic Y\nY = EXH_BP_RR * 2 + EXH_BP_R\n")
    assert r.status_code == 201
    warnings = r.json()["warnings"]
    assert len(warnings) == 1 and "EXH_BP_RR" in warnings[0], warnings
    ok = c.put("/scripts/fine.fdv", content="[formulas]\npublic Z\nZ = EXH_BP_R_Kalman + 1\n")
    assert ok.status_code == 201 and ok.json()["warnings"] == []


def test_block_errors_leave_health_with_the_deleted_script(db, tmp_path):
    rt, mgr, c = make(db, tmp_path)
    assert c.put("/scripts/div.fdv", content="[formulas]\npublic D\nD = 1 / (EXH_BP_L - 600)\n"
                 ).status_code == 201
    feed(rt, db, 0.0, 2.0)
    assert c.get("/health").json()["block_errors"].get("div.fdv", 0) > 0
    assert c.delete("/scripts/div.fdv").status_code == 204
    assert "div.fdv" not in c.get("/health").json()["block_errors"]
    feed(rt, db, 2.0, 3.0)
    assert "div.fdv" not in c.get("/health").json()["block_errors"]


def test_health_is_degraded_with_the_reason_when_the_bus_falls_silent(db, tmp_path):
    rt, mgr, c = make(db, tmp_path)
    h = c.get("/health").json()
    assert h["status"] == "waiting"
    feed(rt, db, 0.0, 5.0)
    h = c.get("/health").json()
    assert h["status"] == "ok" and h["reasons"] == [] and h["frames_per_s"] > 0
    rt.advance(8.0)  # a live cell advances bus time on a silent bus
    h = c.get("/health").json()
    assert h["frames_per_s"] == 0.0 and h["status"] == "degraded"
    assert any("bus silent" in r for r in h["reasons"]), h["reasons"]
    feed(rt, db, 8.0, 10.0)
    assert c.get("/health").json()["status"] == "ok"


def test_trip_is_shown_and_reset_over_http_and_by_scenario_frame(db, tmp_path):
    """The simulator and runtime exchange frames only (as on the bus); the valve is shut so
    the back-pressure trips the engine; /health shows it; the two-step reset clears it."""
    settings = Settings.build({"engine": "large-diesel", "duty": "rated", "valve": 5.0,
                               "bp_limit": 250.0},
                              environ={}).for_simulator()
    sim = build_sim(settings, db)
    rt = Runtime(db, native_filters())
    c = local_client(create_app(Cell(runtime=rt)))

    def run(seconds):
        for _ in range(round(seconds / sim.dt)):
            for msg in sim.frames():
                rt.ingest(msg)
            for msg in rt.take_outbox():
                sim.receive(msg)
            sim.step()

    run(5.0)
    h = c.get("/health").json()
    assert h["trip"] == {"state": "TRIPPED", "reason": "EXH_BP_LIMIT", "since": h["trip"]["since"]}
    assert h["status"] == "degraded" and any("engine tripped: EXH_BP_LIMIT" in r for r in h["reasons"])
    exhaust = sim.plant.plant("exhaust")
    assert exhaust.state == TRIPPED
    run(10.0)  # the engine runs down, so the trip's cause clears
    assert c.get("/health").json()["trip"] is not None  # a trip holds until reset
    # one frame never resets: a lone confirm (any value) is refused
    rt.send([db.encode("ENGINE_CMD", {"ENGINE_RESET_REQ": 0, "ENGINE_RESET_CONFIRM": 77}, rt.now)])
    run(1.0)
    assert exhaust.state == TRIPPED and rt.channels["RESET_STATE"].value == 4  # no request
    r = c.post("/engine/reset", json={})
    assert r.status_code == 200
    challenge = r.json()["challenge"]
    assert r.json()["sent"] == {"ENGINE_RESET_REQ": challenge} and r.json()["window_s"] == 2.0
    run(1.0)
    assert exhaust.state == TRIPPED and rt.channels["RESET_STATE"].value == 1  # pending
    wrong = c.post("/engine/reset/confirm", json={"challenge": challenge % 65535 + 1})
    assert wrong.status_code == 422 and "challenge" in wrong.text
    r = c.post("/engine/reset/confirm", json={"challenge": challenge})
    assert r.status_code == 200 and r.json()["sent"] == {"ENGINE_RESET_CONFIRM": challenge}
    run(2.0)
    h = c.get("/health").json()
    assert h["trip"] is None and h["status"] == "ok", h
    assert exhaust.state != TRIPPED and rt.channels["ENGINE_STATE"].value == 1
    assert rt.channels["RESET_STATE"].value == 2
    # trip again, then reset with the same two steps as scenario frames (what `testcell
    # scenario engine_reset_req=N`, then `engine_reset_confirm=N`, send)
    run(20.0)
    assert c.get("/health").json()["trip"] is not None
    run(10.0)
    for key in ("engine_reset_req", "engine_reset_confirm"):
        rt.send(scenario_frames(db, {key: 4321}, rt.now))
        run(0.5)
    # reset (the shut valve trips the engine again within seconds of its restart)
    assert rt.channels["RESET_STATE"].value == 2 and rt.channels["ENGINE_STATE"].value == 1
    assert c.get("/health").json()["trip"] is None
    assert registry  # the engine profile came from the registry
