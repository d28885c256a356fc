"""The CI soak (issue 20 points 7 and 8): ``benchmarks/soak.py`` over 80 s, both engines in
turn, each with ``/channels`` polled at 20 Hz and a WebSocket reading every channel on
``/stream``, on a private udp_multicast group and port. ``scripts/soak.sh MINUTES`` runs it
longer, at ``--speed 20`` for both engines.

What it proves: the loss accounting end to end (the frames the simulator says it sent are
the frames on the wire, and the runtime's count of its IDs, read from ``/metrics``, never
exceeds them), and that
none is lost by the diesel cell at ``--speed 10`` (about 5 000 frames/s, the load the
earlier CI soak held). The si-turbo cell (crank streams and four observers, ``--speed 1``)
is soaked and its loss printed, **not asserted**: on a shared 2-core machine under load its
runtime loses frames even at real time (27 % at a load average of 14; issue 20's goal of 0
is not met yet, BENCHMARKS.md). Also: the stream delivers ticks, the service logs no error
and its memory does not grow by 20 MB. The stream's p50/p99 lag is printed, not asserted
(a timing)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.buses import private_group

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.multiprocess
def test_short_soak_loses_no_frame_and_reports_the_stream_lag():
    group, port = private_group()
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "soak.py"), "--seconds", "80",
                          "--speed", "10", "--speed-for", "si-turbo=1", "--group", group,
                          "--port", str(port)],
                         capture_output=True, text=True, timeout=400, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    print(out.stderr)
    results = json.loads(out.stdout.strip().splitlines()[-1])
    assert {r["engine"] for r in results} >= {"large-diesel", "si-turbo"}
    for r in results:
        assert r["sim_sent"] and abs(r["wire_frames"] - r["sim_sent"]) <= 32, r  # said what it sent
        # never more than it sent: a runtime behind its socket by over 2 s once took the
        # echoes of its own outputs for received frames (78,197 counted of 78,117 sent),
        # which the soak compares in the total when /metrics' count by ID is not to be had.
        # The frames of the step SIGTERM interrupts are sent but not in the simulator's count
        # (at most 25 for si-turbo): the same tolerance as the wire's above
        assert r["runtime_frames"] <= r["sim_sent"] + 32, r
        if r["engine"] == "large-diesel":
            assert r["lost"] == 0, r
        assert r["stream_messages"] > 0 and r["channels_requests"] > 0, r
        assert r["service_errors"] == [] and r["errors"] == [] and r["sim_errors"] == [], r
        assert r["rss_growth_mb"] < 20, r
        print(f"{r['engine']}: lost {r['lost']} of {r['sim_sent']}; stream p50 "
              f"{r['stream_p50_ms']} ms, p99 {r['stream_p99_ms']} ms")
