"""Every experiment's ``--json`` numbers are those recorded before the tree was laid out in
layers (issue 17), on short runs of each. The files in ``tests/data/golden_experiments/``
were written by the code before the move with the commands in :data:`RUNS` (the output
folder written as ``{out}``); a change that
moves a number on purpose regenerates the file in the same commit."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

GOLDEN = Path(__file__).with_name("data") / "golden_experiments"

#: experiment -> its short-run options
RUNS: dict[str, list[str]] = {
    "closed-loop": ["--duration", "30", "--seeds", "1"],
    "twc": ["--duration", "200"],
    "airpath": [],
    "imbalance": ["--duration", "4"],
    "bias": ["--seconds", "200"],
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(RUNS))
def test_experiment_json_unchanged(name, tmp_path):
    r = subprocess.run([sys.executable, "-m", "cell", "experiment", name, "--json", *RUNS[name],
                        "--out", str(tmp_path / "out")],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    # the figures' paths name the output folder, which is this test's own
    assert r.stdout.replace(str(tmp_path / "out"), "{out}") == (GOLDEN / f"{name}.json").read_text()
