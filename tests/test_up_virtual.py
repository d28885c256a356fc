"""``testcell up --bus virtual``: simulator thread and runtime in one process, over HTTP."""

import json
import signal
import socket
import subprocess
import sys
import time
import urllib.request


def test_up_on_a_virtual_bus_serves_filtered_values_and_stops_cleanly(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "cell", "--log-level", "WARNING", "up", "--bus", "virtual",
                             "--port", str(port), "--state", str(tmp_path / "t.json")],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        status, deadline = None, time.monotonic() + 30
        while time.monotonic() < deadline and status != "ok":
            time.sleep(0.3)
            try:
                url = f"http://127.0.0.1:{port}/channels/EXH_BP_R_Kalman"
                with urllib.request.urlopen(url, timeout=2) as r:
                    status = json.loads(r.read())["status"]
            except OSError:
                pass
        assert status == "ok"
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=2) as r:
            health = json.loads(r.read())
        assert health["bus"] == "virtual:testcell" and health["frames"] > 0
        # an open event stream (curl -N .../stream/sse) must not keep the cell from stopping
        sse = urllib.request.urlopen(f"http://127.0.0.1:{port}/stream/sse?channels=EXH_BP_R", timeout=10)
        assert sse.readline().startswith(b"event: subscribed")
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0, out
    assert "not properly shut down" not in out and "Traceback" not in out, out
