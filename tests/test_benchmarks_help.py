"""Every benchmark answers ``--help`` with its usage and exits 0 (issue 20 point 8); the
scripts are started side by side, so the test costs about one interpreter start."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted((ROOT / "benchmarks").glob("*.py"))


def test_every_benchmark_answers_help():
    assert len(SCRIPTS) >= 8
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    procs = {p.name: subprocess.Popen([sys.executable, str(p), "--help"], cwd=ROOT, env=env,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for p in SCRIPTS if not p.name.startswith("_")}
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, f"{name} --help exited {proc.returncode}: {err[-500:]}"
        assert out.startswith("usage:"), f"{name} --help printed no usage: {out[:200]!r}"
