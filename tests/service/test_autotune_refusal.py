"""Live autotune never applies an estimate it flags itself: edge of the search range, or too
little data. It answers 409 naming why, and the filter and the tuning file stay as they were."""

import numpy as np
import pytest
from tests.helpers.client import local_client

from cell.app.cell import Cell
from cell.estimators.backpressure import native_filters
from cell.runtime.scheduler import Runtime
from cell.app.tuning import TuningStore
from service.main import create_app


def cell_with(db, tmp_path, seconds, walk_sd):
    """A runtime fed ``seconds`` of EXH_BP at 100 Hz: a random walk (per 10 Hz tick) plus noise."""
    rt = Runtime(db, native_filters(), history_s=600)
    rng = np.random.default_rng(7)
    level = 600.0
    n = int(seconds * 100)
    for i in range(n):
        if i % 10 == 0:
            level += rng.normal(0, walk_sd)
        y = level + rng.normal(0, 50.0)
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": y, "EXH_BP_R": y}, i * 0.01))
    rt.advance((n - 1) * 0.01)
    store = TuningStore(tmp_path / "t.json")
    store.record("filters", "EXH_BP_R_Kalman", {"Q": 1e-6, "R": 1e-4})
    return rt, store, local_client(create_app(Cell(runtime=rt, tuning=store)))


@pytest.mark.parametrize("seconds, walk_sd, why", [
    (300, 0.0, "edge of the search range"),   # no drift at all: Q/R -> the range's floor
    (20, 2.0, "too little data"),             # 200 samples
])
def test_flagged_estimate_is_refused_and_changes_nothing(db, tmp_path, seconds, walk_sd, why):
    rt, store, c = cell_with(db, tmp_path, seconds, walk_sd)
    before_file = store.path.read_text()
    before = rt.blocks["EXH_BP_R_Kalman"].params()
    r = c.post("/filters/EXH_BP_R_Kalman/autotune", json={"minutes": 5, "apply": True})
    assert r.status_code == 409, r.text
    body = r.json()
    assert body["applied"] is None and any(why in x for x in body["refused"]), body
    assert why in body["detail"] and body["Q"] is not None  # the estimate is still shown
    assert rt.blocks["EXH_BP_R_Kalman"].params() == before
    assert store.path.read_text() == before_file
    # without "apply" the same estimate is simply returned
    assert c.post("/filters/EXH_BP_R_Kalman/autotune", json={"minutes": 5}).status_code == 200


def test_unflagged_estimate_is_applied(db, tmp_path):
    rt, store, c = cell_with(db, tmp_path, 300, 2.0)
    r = c.post("/filters/EXH_BP_R_Kalman/autotune", json={"minutes": 5, "apply": True})
    assert r.status_code == 200, r.text
    assert rt.blocks["EXH_BP_R_Kalman"].Q == pytest.approx(r.json()["Q"])
