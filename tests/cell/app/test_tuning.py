"""Tuning and scripts survive ``kill -9`` at any moment: a writer process is killed mid-write
in a loop and the files are always the old or the new version, never corrupt. A file
corrupted by hand is moved aside with a clear message and the defaults are used."""

import json
import logging
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

from cell.estimators.backpressure import native_filters
from cell.runtime.scheduler import Runtime
from cell.scripts.manager import ScriptManager
from cell.app.tuning import TuningStore

KILLS = 50

WRITER = r"""
import sys
from pathlib import Path
from cell.app.tuning import TuningStore, write_text_atomic

folder = Path(sys.argv[1])
store = TuningStore(folder / "tuning.json")
store.load()
versions = [{f"F{i}": {"Q": q, "R": 1e-4, "pad": "x" * 400} for i in range(400)} for q in (1e-6, 2e-6)]
scripts = [f"[formulas]\npublic Y\nY = EXH_BP_R * {k}\n" + "// pad\n" * 20000 for k in (1, 2)]
k = 0
while True:
    store.data["filters"] = versions[k % 2]
    store.save()
    write_text_atomic(folder / "scripts" / "mine.fdv", scripts[k % 2])
    if k == 0:
        print("ready", flush=True)
    k += 1
"""


def _expected():
    versions = [{"filters": {f"F{i}": {"Q": q, "R": 1e-4, "pad": "x" * 400} for i in range(400)}}
                for q in (1e-6, 2e-6)]
    scripts = [f"[formulas]\npublic Y\nY = EXH_BP_R * {k}\n" + "// pad\n" * 20000 for k in (1, 2)]
    return versions, scripts


def test_kill_9_mid_write_leaves_the_old_or_the_new_file(tmp_path):
    versions, scripts = _expected()
    rng = random.Random(13)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[3])}
    mid_write = 0
    for i in range(KILLS):
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path)], stdout=subprocess.PIPE,
                                text=True, env=env)
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(rng.uniform(0.0, 0.05))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
        leftovers = [p for p in tmp_path.rglob(".*") if p.is_file()]
        mid_write += bool(leftovers)
        data = json.loads((tmp_path / "tuning.json").read_text())
        assert data in versions, f"kill {i}: tuning file is neither version"
        assert (tmp_path / "scripts" / "mine.fdv").read_text() in scripts, f"kill {i}: script torn"
    print(f"\n{KILLS} kills, {mid_write} of them mid-write (a temporary file was left)")
    assert mid_write > 0  # the loop did hit writes in progress
    store = TuningStore(tmp_path / "tuning.json")
    assert store.load() in versions and store.problem is None
    assert not [p for p in tmp_path.glob(".tuning.json.*")]  # leftovers cleaned at load


def test_tuning_file_corrupted_by_hand_is_moved_aside_and_defaults_used(db, tmp_path, caplog):
    path = tmp_path / "tuning.json"
    for bad in ("{ half a file", '["not", "sections"]', '{"filters": {"EXH_BP_R_Kalman": 5}}',
                '{"scripts": {"removed": "kalman.fdv"}}', "\x00\x01\x02"):
        path.write_text(bad)
        earlier = set(tmp_path.glob("tuning.json.corrupt-*"))
        store = TuningStore(path)
        with caplog.at_level(logging.WARNING, logger="cell.app.tuning"):
            assert store.load() == {}
        assert "unreadable" in store.problem and "starting from defaults" in store.problem
        assert str(path) in caplog.text
        assert not path.exists()
        (aside,) = set(tmp_path.glob("tuning.json.corrupt-*")) - earlier
        assert aside.read_text() == bad and str(aside) in store.problem
        rt = Runtime(db, native_filters())
        assert store.restore(rt) == [] and rt.blocks["EXH_BP_R_Kalman"].Q == 1e-6
        caplog.clear()


def test_a_saved_script_corrupted_by_hand_is_moved_aside(db, tmp_path):
    store = TuningStore(tmp_path / "tuning.json")
    folder = tmp_path / "scripts"
    folder.mkdir()
    (folder / "good.fdv").write_text("[formulas]\npublic GOOD\nGOOD = EXH_BP_R\n")
    (folder / "bad.fdv").write_bytes(b"\xff\xfe\x00garbage")
    mgr = ScriptManager(Runtime(db, native_filters()), store)
    problems = mgr.load_defaults(shipped=False)
    assert len(problems) == 1 and "bad.fdv" in problems[0] and "moved to" in problems[0]
    assert mgr.names() == ["good.fdv"]
    assert not (folder / "bad.fdv").exists() and list(folder.glob("bad.fdv.corrupt-*"))


def _free_port():
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


SERVICE_KILLS = 4


def test_kill_9_of_the_running_service_mid_patch_keeps_a_whole_file(tmp_path):
    """The real service (``testcell up``) is killed while PATCH and PUT requests stream in:
    the tuning file and the saved script are whole, and hold what was last acknowledged or
    something sent after it."""
    import threading
    import urllib.request

    rng = random.Random(7)
    state = tmp_path / "tuning.json"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[3])}
    env.pop("TESTCELL_TOKEN", None)
    scripts = {f"[formulas]\npublic MINE\nMINE = EXH_BP_R * {k}\n" for k in range(1000)}
    q_sent = 0
    for round_ in range(SERVICE_KILLS):
        port = _free_port()
        proc = subprocess.Popen([sys.executable, "-m", "cell", "--log-level", "WARNING", "up",
                                 "--bus", f"virtual:kill9-{round_}", "--no-sim", "--port", str(port),
                                 "--state", str(state)], env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        base = f"http://127.0.0.1:{port}"
        acked = []
        stop = threading.Event()

        def hammer(base=base, acked=acked, stop=stop):
            nonlocal q_sent
            k = 0
            while not stop.is_set():
                q_sent += 1
                q = q_sent * 1e-7
                body = json.dumps({"Q": q}).encode()
                try:
                    req = urllib.request.Request(f"{base}/filters/EXH_BP_R_Kalman", data=body,
                                                 method="PATCH",
                                                 headers={"content-type": "application/json"})
                    urllib.request.urlopen(req, timeout=2).read()
                    acked.append(q)
                    text = f"[formulas]\npublic MINE\nMINE = EXH_BP_R * {k % 1000}\n".encode()
                    req = urllib.request.Request(f"{base}/scripts/mine.fdv", data=text, method="PUT")
                    urllib.request.urlopen(req, timeout=2).read()
                    k += 1
                except OSError:
                    time.sleep(0.05)

        t = threading.Thread(target=hammer, daemon=True)
        t.start()
        deadline = time.monotonic() + 30
        while not acked and time.monotonic() < deadline:
            time.sleep(0.05)
        assert acked, "the service never answered"
        time.sleep(rng.uniform(0.1, 0.6))
        last_acked = acked[-1]
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        stop.set()
        t.join(5)
        data = json.loads(state.read_text())  # whole, parseable
        q = data["filters"]["EXH_BP_R_Kalman"]["Q"]
        assert q >= last_acked - 1e-15, (q, last_acked)
        assert (tmp_path / "scripts" / "mine.fdv").read_text() in scripts
    store = TuningStore(state)
    assert store.load() and store.problem is None
