"""``testcell up --engine si-turbo --bus virtual``: the catalyst observer live, and a scenario
command over HTTP reaching the simulator as a frame."""

import json
import signal
import socket
import subprocess
import sys
import time
import urllib.request


def _get(port, path):
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=2) as r:
        return json.loads(r.read())


def _wait(port, path, ok, seconds=40.0):
    deadline, last = time.monotonic() + seconds, None
    while time.monotonic() < deadline:
        time.sleep(0.3)
        try:
            last = _get(port, path)
        except OSError:
            continue
        if ok(last):
            return last
    raise AssertionError(f"{path}: gave {last}")


def test_up_si_turbo_serves_the_observer_and_takes_a_scenario_command(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "cell", "--log-level", "WARNING", "up", "--bus",
                             "virtual", "--engine", "si-turbo", "--osc", "0.6", "--osc-init", "0.8",
                             "--speed", "4", "--port", str(port), "--state", str(tmp_path / "t.json")],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        est = _wait(port, "/channels/OSC_EST", lambda c: c["status"] == "ok")
        assert abs(est["value"] - 0.8) < 0.05  # the guess, held while the catalyst is cold
        assert _get(port, "/channels/OSC_TRUE")["value"] == 0.6
        twc = _get(port, "/observers/twc")
        assert twc["params"]["osc_init"] == 0.8 and twc["state"]["resets"] == 0
        req = urllib.request.Request(f"http://127.0.0.1:{port}/scenario", method="POST",
                                     data=json.dumps({"osc": 0.45}).encode(),
                                     headers={"content-type": "application/json"})
        with urllib.request.urlopen(req, timeout=2) as r:
            assert json.loads(r.read())["sent"][0]["signals"] == {"OSC": 0.45}
        _wait(port, "/channels/OSC_TRUE", lambda c: c["value"] == 0.45, seconds=20.0)
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0, out
    assert "Traceback" not in out, out
