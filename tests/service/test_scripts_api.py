"""/scripts: shipped scripts beside the native filters, hot swap, constants, persistence."""

import json
import math

import pytest
from tests.helpers.client import local_client

from cell.app.cell import Cell
from cell.estimators.backpressure import native_filters
from cell.runtime.scheduler import Runtime
from cell.scripts.manager import ScriptManager
from cell.app.tuning import TuningStore
from service.main import create_app
from tests.helpers.frames import feed as bp_feed

COUNTER = """
[init]
dim n
n = 0
dim total
total = 0
[formulas]
public COUNT_TICKS
public MEAN_BP_R
n = n + 1
total = total + EXH_BP_R
COUNT_TICKS = n
MEAN_BP_R = total / n
"""


def make(db, tmp_path):
    rt = Runtime(db, native_filters())
    store = TuningStore(tmp_path / "tuning.json")
    store.load()
    mgr = ScriptManager(rt, store)
    assert mgr.load_defaults() == []
    store.restore(rt)
    return rt, mgr, store, local_client(create_app(Cell(runtime=rt, tuning=store, scripts=mgr)))


def feed(rt, db, t0, t1, value=lambda t: 680.0 + 30 * math.sin(t)):
    bp_feed(rt, db, t0, t1, left=value)


def test_shipped_scripts_run_beside_native_filters(db, tmp_path):
    rt, mgr, store, c = make(db, tmp_path)
    names = {s["name"] for s in c.get("/scripts").json()}
    assert names == {"kalman.fdv", "kalman.labels", "maf.fdv", "maf.labels"}
    feed(rt, db, 0.0, 20.0)
    chans = {ch["name"]: ch for ch in c.get("/channels").json()}
    for bank in "LR":
        for name in (f"EXH_BP_{bank}_Kalman", f"EXH_BP_{bank}_Kalman_FDV", f"EXH_BP_{bank}_Kalman_CYF",
                     f"EXH_BP_{bank}_MAF", f"EXH_BP_{bank}_MAF_FDV", f"EXH_BP_{bank}_MAF_CYF"):
            assert chans[name]["status"] == "ok", (name, chans[name])
            assert chans[name]["value"] == pytest.approx(680, abs=40), name
    # the scripted moving averages equal the native one (the CyFlex one reads .AV a tick late)
    assert chans["EXH_BP_R_MAF_FDV"]["value"] == pytest.approx(chans["EXH_BP_R_MAF"]["value"], abs=1e-9)
    d = c.get("/scripts/kalman.labels").json()
    assert d["dialect"] == "cyflex" and "X_hat_prev_EXH_BP_R" in d["source"] and d["ravg_source"]


def test_put_hot_swap_keeps_state_of_unchanged_outputs(db, tmp_path):
    rt, mgr, store, c = make(db, tmp_path)
    r = c.put("/scripts/count.fdv", content=COUNTER)
    assert r.status_code == 201, r.text
    feed(rt, db, 0.0, 5.0)
    assert rt.channels["COUNT_TICKS"].value == 50
    changed = COUNTER.replace("MEAN_BP_R = total / n", "MEAN_BP_R = total / n + 1000")
    r = c.put("/scripts/count.fdv", content=changed)
    assert r.status_code == 200, r.text
    assert "n" in r.json()["kept_state"] or "COUNT_TICKS" in r.json()["kept_state"]
    feed(rt, db, 5.0, 6.0)
    assert rt.channels["COUNT_TICKS"].value == 60  # the counter was not reset by the swap
    assert rt.channels["MEAN_BP_R"].value > 1000
    assert (tmp_path / "scripts" / "count.fdv").read_text() == changed


def test_bad_put_is_400_with_positions_and_keeps_the_running_script(db, tmp_path):
    rt, mgr, store, c = make(db, tmp_path)
    c.put("/scripts/count.fdv", content=COUNTER)
    bad = COUNTER.replace("total = total + EXH_BP_R", "total = total + (EXH_BP_R")
    r = c.put("/scripts/count.fdv", content=bad)
    assert r.status_code == 400
    err = r.json()["errors"][0]
    assert err["file"] == "count.fdv" and err["line"] == 11 and err["column"] > 1
    assert c.get("/scripts/count.fdv").json()["source"] == COUNTER
    r = c.put("/scripts/x.fdv", content="[formulas]\npublic Y\nY = __import__(1)\n")
    assert r.status_code == 400
    assert c.put("/scripts/notes.txt", content="x").status_code == 422
    assert c.put("/scripts/..fdv", content=COUNTER).status_code == 422
    assert c.put("/scripts/bin.fdv", content=b"\xff\xfe").status_code == 400


def test_one_producer_per_channel(db, tmp_path):
    rt, mgr, store, c = make(db, tmp_path)
    clash = "[formulas]\npublic EXH_BP_R_Kalman\nEXH_BP_R_Kalman = EXH_BP_R\n"
    r = c.put("/scripts/clash.fdv", content=clash)
    assert r.status_code == 409
    assert "clash.fdv" in r.json()["detail"] and "EXH_BP_R_Kalman" in r.json()["detail"]
    assert "clash.fdv" not in c.get("/scripts").text


def test_patch_constants_next_tick_and_bad_ones_change_nothing(db, tmp_path):
    rt, mgr, store, c = make(db, tmp_path)
    feed(rt, db, 0.0, 10.0)
    block = rt.blocks["kalman.fdv"]
    before = dict(block.constants())
    r = c.patch("/scripts/kalman.fdv", json={"constants": {"Q_EXH_BP_R": 1e-2}})
    assert r.status_code == 200 and r.json()["constants"]["Q_EXH_BP_R"] == 1e-2
    x_prev = rt.channels["EXH_BP_R_Kalman_FDV"].value
    feed(rt, db, 10.0, 10.1, value=lambda t: 2000.0)
    # Figure 6: K = P / (P + R) with P the previous posterior; a large Q makes the next P large
    assert rt.channels["EXH_BP_R_Kalman_FDV"].value - x_prev > 100
    assert json.loads(store.path.read_text())["scripts"]["constants"]["kalman.fdv"]["Q_EXH_BP_R"] == 1e-2
    for body, field in [({"constants": {"Q_EXH_BP_R": "big"}}, "Q_EXH_BP_R"),
                        ({"constants": {"NOPE": 1.0}}, "NOPE"),
                        ({"constants": {"R_EXH_BP_R": 1.0, "Q_EXH_BP_L": float("inf")}}, "Q_EXH_BP_L"),
                        ({"Q_EXH_BP_R": 1.0}, "Q_EXH_BP_R"), ({}, "constants")]:
        raw = json.dumps(body).replace("Infinity", "Infinity")
        r = c.patch("/scripts/kalman.fdv", content=raw, headers={"content-type": "application/json"})
        assert r.status_code == 422 and field in json.dumps(r.json()), (body, r.text)
    assert block.constants() == {**before, "Q_EXH_BP_R": 1e-2}
    assert c.patch("/scripts/none.fdv", json={"constants": {}}).status_code == 404


def test_runtime_error_marks_only_that_output(db, tmp_path):
    rt, mgr, store, c = make(db, tmp_path)
    script = "[formulas]\npublic INV\npublic OK_TOO\nINV = 1 / (EXH_BP_R - 680)\nOK_TOO = EXH_BP_R * 2\n"
    assert c.put("/scripts/inv.fdv", content=script).status_code == 201
    feed(rt, db, 0.0, 1.0, value=lambda t: 680.0)
    inv = c.get("/channels/INV").json()
    assert inv["status"] == "invalid" and "zero" in inv["reason"].lower()
    assert c.get("/channels/OK_TOO").json()["status"] == "ok"
    assert c.get("/channels/EXH_BP_R_Kalman_FDV").json()["status"] == "ok"
    assert c.get("/health").json()["block_errors"]["inv.fdv"] >= 1
    feed(rt, db, 1.0, 1.2, value=lambda t: 690.0)
    assert c.get("/channels/INV").json()["status"] == "ok"


def test_scripts_constants_and_removals_survive_restart(db, tmp_path):
    rt, mgr, store, c = make(db, tmp_path)
    assert c.put("/scripts/count.fdv", content=COUNTER).status_code == 201
    assert c.patch("/scripts/kalman.fdv", json={"constants": {"R_EXH_BP_L": 5e-4}}).status_code == 200
    assert c.delete("/scripts/maf.labels").status_code == 204
    assert c.get("/scripts/maf.labels").status_code == 404
    assert "EXH_BP_R_MAF_CYF" not in rt.channels

    rt2, mgr2, store2, c2 = make(db, tmp_path)
    names = {s["name"] for s in c2.get("/scripts").json()}
    assert names == {"kalman.fdv", "kalman.labels", "maf.fdv", "count.fdv"}
    assert rt2.blocks["kalman.fdv"].constants()["R_EXH_BP_L"] == 5e-4


def test_put_ravg_replaces_the_running_averages_of_its_set(db, tmp_path):
    rt, mgr, store, c = make(db, tmp_path)
    feed(rt, db, 0.0, 3.0)
    # a running-average-only set: a 10-sample window of the raw right bank
    r = c.put("/scripts/stats.ravg", content="EXH_BP_R 10 MED a_BP_R_10.\n")
    assert r.status_code == 201, r.text
    feed(rt, db, 3.0, 5.0)
    assert rt.channels["a_BP_R_10.NM"].value == 10
    assert rt.channels["a_BP_R_10.AV"].status == "ok"
    # the .ravg of an existing .labels set: same labels, new running averages
    old = c.get("/scripts/maf.labels").json()
    assert old["ravg_source"]
    new_ravg = old["ravg_source"].replace(" 30 ", " 20 ")
    assert new_ravg != old["ravg_source"]
    r = c.put("/scripts/maf.ravg", content=new_ravg)
    assert r.status_code == 200, r.text
    now = c.get("/scripts/maf.labels").json()
    assert now["ravg_source"] == new_ravg and now["source"] == old["source"]
    feed(rt, db, 5.0, 10.0)
    assert rt.channels["a_EXH_BP_R_maf.NM"].value == 20
    assert (tmp_path / "scripts" / "maf.ravg").read_text() == new_ravg
    rt2, mgr2, store2, c2 = make(db, tmp_path)  # restart: the changed set comes back whole
    assert c2.get("/scripts/maf.labels").json()["ravg_source"] == new_ravg
    assert "stats.ravg" in {s["name"] for s in c2.get("/scripts").json()}
