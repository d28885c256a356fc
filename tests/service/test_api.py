"""The HTTP API over an in-process runtime fed with frames (no bus, no wall clock)."""

import json

import pytest
from fastapi.testclient import TestClient

from cell.app.cell import Cell
from cell.estimators.backpressure import native_filters
from cell.runtime.scheduler import Runtime
from cell.app.tuning import TuningStore
from service.main import create_app
from tests.helpers.frames import feed as bp_feed
from tests.helpers.frames import steady, wavy


def feed(rt, db, t0, t1, value=680.0):
    bp_feed(rt, db, t0, t1, left=steady(value), right=wavy(value))


@pytest.fixture
def cell(db, tmp_path):
    rt = Runtime(db, native_filters())
    store = TuningStore(tmp_path / "tuning.json")
    store.load()
    feed(rt, db, 0.0, 20.0)
    return Cell(runtime=rt, bus="virtual:test", tuning=store)


@pytest.fixture
def client(cell):
    return TestClient(create_app(cell))


def test_health_counts_frames_and_errors(client, cell, db):
    import can

    cell.runtime.ingest(can.Message(timestamp=20.0, arbitration_id=0x5, data=b"", is_extended_id=False))
    h = client.get("/health").json()
    assert h["bus"] == "virtual:test"
    assert h["frames"] == 2001
    assert h["decode_errors"]["unknown_id"] == 1
    assert h["frames_per_s"] == pytest.approx(100, abs=2)
    assert h["last_frame_time"] == pytest.approx(20.0)


def test_channels_list_and_one(client):
    chans = {c["name"]: c for c in client.get("/channels").json()}
    for name in ("EXH_BP_L", "EXH_BP_R", "EXH_BP_L_MAF", "EXH_BP_R_MAF", "EXH_BP_L_Kalman",
                 "EXH_BP_R_Kalman"):
        assert chans[name]["status"] == "ok"
        assert chans[name]["unit"] == "mmH2O"
    one = client.get("/channels/EXH_BP_R_Kalman").json()
    assert one["value"] == pytest.approx(680, abs=15)
    assert one["source"] == "EXH_BP_R_Kalman"
    r = client.get("/channels/NOPE")
    assert r.status_code == 404 and "NOPE" in r.json()["detail"]


def test_history_is_bounded_and_validated(client):
    pts = client.get("/channels/EXH_BP_L/history", params={"seconds": 5}).json()["points"]
    assert len(pts) == 50
    assert all(p["status"] == "ok" for p in pts)
    for bad in ("0", "-1", "nan", "inf", "abc", "1e9"):
        r = client.get("/channels/EXH_BP_L/history", params={"seconds": bad})
        assert r.status_code == 422, bad
        assert "seconds" in json.dumps(r.json())
    assert client.get("/channels/NOPE/history").status_code == 404


def test_patch_kalman_takes_effect_next_tick_and_keeps_estimate(client, cell, db):
    rt = cell.runtime
    kal = rt.blocks["EXH_BP_R_Kalman"]
    x, P = kal.x, kal.P
    r = client.patch("/filters/EXH_BP_R_Kalman", json={"Q": 1e-3, "R": 2e-4})
    assert r.status_code == 200, r.text
    assert r.json()["params"] == {"Q": 1e-3, "R": 2e-4}
    assert (kal.x, kal.P) == (x, P)  # no reset
    rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 700.0, "EXH_BP_R": 700.0}, 20.0))
    rt.advance(20.0)
    K = (P + 1e-3) / (P + 1e-3 + 2e-4)
    assert kal.x == pytest.approx(x + K * (700.0 - x), abs=1e-9)
    assert json.loads(cell.tuning.path.read_text())["filters"]["EXH_BP_R_Kalman"] == {"Q": 1e-3, "R": 2e-4}


def test_patch_moving_average_window(client, cell):
    r = client.patch("/filters/EXH_BP_L_MAF", json={"samples": 10})
    assert r.status_code == 200 and r.json()["params"]["samples"] == 10
    assert r.json()["state"]["filled"] == 10


@pytest.mark.parametrize(
    "name,body,field",
    [
        ("EXH_BP_R_Kalman", {"Q": 0}, "Q"),
        ("EXH_BP_R_Kalman", {"R": -1e-4}, "R"),
        ("EXH_BP_R_Kalman", {"Q": "1e-6"}, "Q"),
        ("EXH_BP_R_Kalman", {"Q": None}, "Q"),
        ("EXH_BP_R_Kalman", {"Q": 1e-6, "gain": 2}, "gain"),
        ("EXH_BP_R_Kalman", {"samples": 30}, "samples"),
        ("EXH_BP_R_MAF", {"Q": 1e-6}, "Q"),
        ("EXH_BP_R_MAF", {"samples": 0}, "samples"),
        ("EXH_BP_R_MAF", {"samples": 12.5}, "samples"),
        ("EXH_BP_R_MAF", {"samples": 10**9}, "samples"),
        ("EXH_BP_R_MAF", {}, "body"),
    ],
)
def test_bad_patch_is_422_naming_field_and_changes_nothing(client, cell, name, body, field):
    before = client.get(f"/filters/{name}").json()
    r = client.patch(f"/filters/{name}", json=body)
    assert r.status_code == 422, r.text
    assert field in json.dumps(r.json()["detail"])
    after = client.get(f"/filters/{name}").json()
    assert after["params"] == before["params"]
    assert not cell.tuning.path.exists()


@pytest.mark.parametrize("raw", ['{"Q": NaN}', '{"R": Infinity}', '{"Q": -Infinity}'])
def test_non_finite_json_numbers_are_refused(client, raw):
    r = client.patch("/filters/EXH_BP_R_Kalman", content=raw, headers={"content-type": "application/json"})
    assert r.status_code == 422
    assert r.json()["detail"][0]["loc"][-1] in ("Q", "R")


@pytest.mark.parametrize("raw", ["[1, 2]", '"Q"', "{not json", ""])
def test_malformed_bodies_are_refused(client, raw):
    r = client.patch("/filters/EXH_BP_R_Kalman", content=raw, headers={"content-type": "application/json"})
    assert r.status_code == 422


def test_unknown_filter_is_404(client):
    r = client.patch("/filters/EXH_BP_X_Kalman", json={"Q": 1e-6})
    assert r.status_code == 404
    assert "EXH_BP_X_Kalman" in r.json()["detail"] and "EXH_BP_R_Kalman" in r.json()["detail"]
    assert client.get("/filters/EXH_BP_X_Kalman").status_code == 404


def test_tuning_survives_a_restart(db, tmp_path):
    path = tmp_path / "state" / "tuning.json"
    rt = Runtime(db, native_filters())
    store = TuningStore(path)
    store.load()
    c = TestClient(create_app(Cell(runtime=rt, tuning=store)))
    assert c.patch("/filters/EXH_BP_L_Kalman", json={"Q": 4e-6}).status_code == 200
    assert c.patch("/filters/EXH_BP_R_MAF", json={"samples": 50}).status_code == 200
    assert [p.name for p in path.parent.iterdir()] == ["tuning.json"]  # no temp files left

    rt2 = Runtime(db, native_filters())
    store2 = TuningStore(path)
    store2.load()
    assert store2.restore(rt2) == []
    assert rt2.blocks["EXH_BP_L_Kalman"].Q == 4e-6
    assert rt2.blocks["EXH_BP_R_MAF"].samples == 50


def test_corrupt_tuning_file_is_kept_aside(db, tmp_path):
    path = tmp_path / "tuning.json"
    path.write_text("{ half a file")
    store = TuningStore(path)
    assert store.load() == {}
    aside = [p for p in tmp_path.iterdir() if ".corrupt-" in p.name]
    assert len(aside) == 1 and aside[0].read_text() == "{ half a file"


def test_saved_tuning_with_bad_values_is_skipped_not_applied(db, tmp_path):
    path = tmp_path / "tuning.json"
    path.write_text(json.dumps({"filters": {"EXH_BP_L_Kalman": {"Q": -1}, "GONE": {"Q": 1e-6},
                                            "EXH_BP_R_Kalman": {"R": 5e-4}}}))
    rt = Runtime(db, native_filters())
    store = TuningStore(path)
    store.load()
    skipped = store.restore(rt)
    assert len(skipped) == 2
    assert rt.blocks["EXH_BP_L_Kalman"].Q == 1e-6
    assert rt.blocks["EXH_BP_R_Kalman"].R == 5e-4


def test_page_and_openapi(client):
    r = client.get("/")
    assert r.status_code == 200 and "text/html" in r.headers["content-type"]
    assert '<script src="/static/dashboard.js">' in r.text
    js = client.get("/static/dashboard.js")
    assert js.status_code == 200 and "javascript" in js.headers["content-type"] and "/channels" in js.text
    assert client.get("/static/nope.js").status_code == 404
    paths = client.get("/openapi.json").json()["paths"]
    for p in ("/health", "/channels", "/channels/{name}", "/channels/{name}/history", "/filters",
              "/filters/{name}"):
        assert p in paths


def test_controllers_are_tunable_and_keep_off_the_bus_until_enabled(db, tmp_path):
    from cell.control.backpressure import controllers

    rt = Runtime(db, [*native_filters(), *controllers("kalman")])
    store = TuningStore(tmp_path / "t.json")
    c = TestClient(create_app(Cell(runtime=rt, tuning=store)))

    def run(t0, t1):
        t = t0
        while t < t1 - 1e-9:
            rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 900.0, "EXH_BP_R": 900.0}, t))
            rt.ingest(db.encode("VALVE_POS", {"VALVE_POS_L": 100.0, "VALVE_POS_R": 100.0}, t))
            rt.ingest(db.encode("ENGINE_STATUS", {"ENGINE_STATE": 1, "TRIP_REASON": 0,
                                                  "EXH_BP_LIMIT": 1200, "ENGINE_LOAD": 100}, t))
            t = round(t + 0.01, 6)
        rt.advance(t1 - 0.01)
        return [f for f in rt.take_outbox() if f.arbitration_id == db.message("VALVE_DEMAND").frame_id]

    names = [b["name"] for b in c.get("/controllers").json()]
    assert names == ["PI_L", "PI_R"]
    assert run(0.0, 3.0) == []  # disabled: no demand on the bus
    for name in names:
        r = c.patch(f"/controllers/{name}", json={"enable": True})
        assert r.status_code == 200, r.text
    demands = run(3.0, 6.0)
    assert demands, "enabled controllers put no VALVE_DEMAND on the bus"
    _, last = db.decode(demands[-1])
    assert last["VALVE_DEMAND_R"] > 100.0 - 5.0 * 3.0 - 0.01  # rate-limited at 5 %/s...
    assert last["VALVE_DEMAND_R"] <= 100.0  # ...and opening further is impossible (900 > 680)

    for body, field in [('{"kp": NaN}', "kp"), ('{"feedback": ""}', "feedback"),
                        ('{"enable": "yes"}', "enable"), ('{"out_min": 90, "out_max": 10}', "out_")]:
        before = c.get("/controllers/PI_R").json()["params"]
        r = c.patch("/controllers/PI_R", content=body, headers={"content-type": "application/json"})
        assert r.status_code == 422 and field in json.dumps(r.json()), (body, r.text)
        assert c.get("/controllers/PI_R").json()["params"] == before
    assert c.patch("/controllers/PI_X", json={"enable": True}).status_code == 404


def test_autotune_estimates_from_history_and_applies_only_on_request(db, tmp_path):
    import numpy as np

    rt = Runtime(db, native_filters(), history_s=600)
    rng = np.random.default_rng(5)
    level = 600.0
    for i in range(30000):  # 300 s at 100 Hz: a random walk (Q = 4 per tick) plus white noise (R = 2500)
        if i % 10 == 0:
            level += rng.normal(0, 2.0)
        y = level + rng.normal(0, 50.0)
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": y, "EXH_BP_R": y}, i * 0.01))
    rt.advance(299.99)
    store = TuningStore(tmp_path / "t.json")
    c = TestClient(create_app(Cell(runtime=rt, tuning=store)))

    r = c.post("/filters/EXH_BP_R_Kalman/autotune", json={"minutes": 5})
    assert r.status_code == 200, r.text
    est = r.json()
    assert est["applied"] is None and rt.blocks["EXH_BP_R_Kalman"].Q == 1e-6
    assert est["R"] == pytest.approx(2500, rel=0.15)
    assert est["Q"] == pytest.approx(4.0, rel=0.6)
    assert est["samples_used"] == 3000

    r = c.post("/filters/EXH_BP_R_Kalman/autotune", json={"minutes": 5, "apply": True})
    assert r.status_code == 200
    assert rt.blocks["EXH_BP_R_Kalman"].Q == pytest.approx(r.json()["Q"])
    saved = json.loads(store.path.read_text())["filters"]["EXH_BP_R_Kalman"]
    assert saved["R"] == pytest.approx(r.json()["R"])

    for body in ({"minutes": 0}, {"minutes": "5"}, {"apply": "yes"}, {"method": "guess"}, {"hours": 1}):
        assert c.post("/filters/EXH_BP_L_Kalman/autotune", json=body).status_code == 422, body
    assert c.post("/filters/EXH_BP_L_MAF/autotune", json={}).status_code == 422
    assert c.post("/filters/NOPE/autotune", json={}).status_code == 404


def test_restart_restores_controller_tuning_but_never_enables_the_loop(db, tmp_path):
    from cell.control.backpressure import controllers

    path = tmp_path / "tuning.json"
    rt = Runtime(db, controllers("kalman"))
    store = TuningStore(path)
    c = TestClient(create_app(Cell(runtime=rt, tuning=store)))
    assert c.patch("/controllers/PI_R", json={"enable": True, "kp": 0.004}).status_code == 200
    rt2 = Runtime(db, controllers("kalman"))
    store2 = TuningStore(path)
    store2.load()
    assert store2.restore(rt2) == []
    assert rt2.blocks["PI_R"].kp == 0.004
    assert rt2.blocks["PI_R"].enable is False
