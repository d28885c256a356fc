"""The platform proven by a test-only plugin (tests/plugins/toy_cell): a toy plant, its DBC file,
an observer on the estimator core and an experiment, each registered with one line and picked up
with no edit to the CLI, the service or the runtime."""

from __future__ import annotations

import csv
import importlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from tests.helpers.client import local_client

from cell import app
from cell.core import registry
from cell.app.cli import build_runtime
from cell.app.cell import Cell
from cell.sim.lockstep import Lockstep
from cell.core.settings import Settings
from cell.sim import build as build_sim
from cell.app.tuning import TuningStore
from service.main import create_app

ROOT = Path(__file__).resolve().parents[1]
PLUGIN = "tests.plugins.toy_cell"
ENV = {**os.environ, "TESTCELL_PLUGINS": PLUGIN}


def run_testcell(*argv, cwd=ROOT, timeout=120):
    return subprocess.run([sys.executable, "-m", "cell", *argv], capture_output=True, text=True,
                          cwd=cwd, env={**ENV, "PYTHONPATH": str(ROOT)}, timeout=timeout)


@pytest.fixture
def toy(monkeypatch):
    """The plugin registered in this process; every registry table restored afterwards."""
    app.load()
    for table in ("ENGINES", "FAMILIES", "BLOCK_SETS", "EXPERIMENTS"):
        monkeypatch.setattr(registry, table, dict(getattr(registry, table)))
    monkeypatch.setattr(registry, "DBC_FILES", list(registry.DBC_FILES))
    module = sys.modules.get(PLUGIN)
    if module is None:
        importlib.import_module(PLUGIN)
    else:
        importlib.reload(module)
    return module


def rmse(a, b):
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


def test_sim_then_replay_gives_the_observer_channels(tmp_path):
    r = run_testcell("sim", "--engine", "toy", "--duration", "30", "--seed", "2",
                 "--out", str(tmp_path / "x.log"))
    assert r.returncode == 0, r.stderr
    r = run_testcell("replay", str(tmp_path / "x.log"), "--out", str(tmp_path / "x.csv"), "--quiet")
    assert r.returncode == 0, r.stderr
    with open(tmp_path / "x.csv") as fh:
        rows = [row for row in csv.DictReader(fh) if not row["time"].startswith("#")]
    assert {"TOY_EST_POS", "TOY_EST_VEL", "TOY_EST_TOY_POS_HAT"} <= set(rows[0])
    late = [r for r in rows if float(r["time"]) >= 5.0]
    t = np.array([float(r["time"]) for r in late])
    est = np.array([float(r["TOY_EST_VEL"]) for r in late])
    true = np.array([float(r["TOY_VEL_TRUE"]) for r in late])
    pos = np.array([float(r["TOY_POS"]) for r in late])
    # an independent baseline: velocity by differencing the raw position at 10 Hz
    diff = np.diff(pos) / np.diff(t)
    mid = (true[1:] + true[:-1]) / 2
    assert rmse(est, true) < 0.25 * np.std(true)
    assert rmse(est, true) < 0.5 * rmse(diff, mid)


def test_experiment_list_and_run_include_the_plugins():
    r = run_testcell("experiment", "--list")
    assert r.returncode == 0 and "toy-step" in r.stdout and "closed-loop" in r.stdout
    r = run_testcell("experiment", "toy-step", "--seconds", "15")
    assert r.returncode == 0, r.stderr
    scores = json.loads(r.stdout)
    assert scores["vel_rmse"] < 0.25 * scores["vel_std"]


def test_observers_are_tuned_over_http_saved_and_restored(toy, tmp_path):
    settings = Settings.build({"engine": "toy"}, environ={})
    store = TuningStore(tmp_path / "tuning.json")
    store.load()
    rt, scripts = build_runtime(settings, store)
    assert scripts.names() == []  # seed 004's shipped scripts read another engine's frames
    sim = build_sim(settings, rt.db)
    Lockstep(sim, rt).run(5.0)
    client = local_client(create_app(Cell(runtime=rt, bus="none", tuning=store)))
    assert client.get("/filters").status_code == 404  # this cell has no filters
    listed = client.get("/observers").json()
    assert [b["name"] for b in listed] == ["toy"]
    toy_obs = client.get("/observers/toy").json()
    assert toy_obs["family"] == "observer" and toy_obs["params"]["Q"] == [1e-6, 1e-3]
    assert toy_obs["state"]["updates"] == 50 and rt.channels["TOY_EST_VEL"].unit == "m/s"

    bad = client.patch("/observers/toy", json={"Q": [1e-6], "R": [1e-3]})
    assert bad.status_code == 422 and "Q" in json.dumps(bad.json())
    bad = client.patch("/observers/toy", json={"R": [-1.0]})
    assert bad.status_code == 422 and "R" in json.dumps(bad.json())
    assert client.get("/observers/toy").json()["params"]["Q"] == [1e-6, 1e-3]  # unchanged

    ok = client.patch("/observers/toy", json={"Q": [1e-6, 5e-3]})
    assert ok.status_code == 200 and ok.json()["params"]["Q"] == [1e-6, 5e-3]
    saved = json.loads((tmp_path / "tuning.json").read_text())
    assert saved["observers"]["toy"]["Q"] == [1e-6, 5e-3]

    store2 = TuningStore(tmp_path / "tuning.json")
    store2.load()
    rt2, _ = build_runtime(settings, store2)
    assert store2.restore(rt2) == []
    assert rt2.block("toy").params()["Q"] == [1e-6, 5e-3]


def test_up_with_the_plugins_engine_serves_its_observer(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "cell", "--log-level", "WARNING", "up", "--engine", "toy",
         "--bus", "virtual", "--speed", "4", "--port", str(port), "--state", str(tmp_path / "t.json")],
        cwd=ROOT, env={**ENV, "PYTHONPATH": str(ROOT)}, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True)
    base = f"http://127.0.0.1:{port}"
    try:
        status, deadline = None, time.monotonic() + 40
        while time.monotonic() < deadline and status != "ok":
            time.sleep(0.3)
            try:
                with urllib.request.urlopen(f"{base}/channels/TOY_EST_VEL", timeout=2) as r:
                    status = json.loads(r.read())["status"]
            except OSError:
                pass
        assert status == "ok"
        with urllib.request.urlopen(f"{base}/observers/toy", timeout=2) as r:
            assert json.loads(r.read())["state"]["updates"] > 0
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0, out
    assert "Traceback" not in out, out


def test_a_plugin_that_fails_to_load_stops_start_up_naming_it(tmp_path):
    r = subprocess.run([sys.executable, "-m", "cell", "sim", "--out", str(tmp_path / "x.log")],
                       capture_output=True, text=True, cwd=ROOT, timeout=60,
                       env={**ENV, "TESTCELL_PLUGINS": "tests.plugins.no_such_plugin"})
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "tests.plugins.no_such_plugin" in r.stderr and "failed to load" in r.stderr
    assert not (tmp_path / "x.log").exists()
