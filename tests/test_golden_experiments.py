"""Every experiment's ``--json`` numbers are those recorded before the tree was laid out in
layers (issue 17), on short runs of each. The files in ``tests/data/golden_experiments/``
were written by the code before the move with the commands in :data:`RUNS` (the output
folder written as ``{out}``); a change that
moves a number on purpose regenerates the file in the same commit.

Numbers are compared to a relative 1e-7: the same code gives results that differ in the
last digits with the numpy, scipy and BLAS build and thread count (a reordered sum), which
is not a change of behaviour; every other value (names, counts, times, paths) is exact."""

from __future__ import annotations

import json
import math
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
    got = _documents(r.stdout.replace(str(tmp_path / "out"), "{out}"))
    want = _documents((GOLDEN / f"{name}.json").read_text())
    assert _differences(got, want, "") == []


def _documents(text: str) -> list:
    """One JSON document, or one per line (``twc`` prints a line per case)."""
    try:
        return [json.loads(text)]
    except json.JSONDecodeError:
        return [json.loads(line) for line in text.splitlines() if line.strip()]


def _differences(got, want, where: str) -> list[str]:
    if isinstance(want, float) and isinstance(got, (int, float)) and not isinstance(got, bool):
        ok = math.isclose(got, want, rel_tol=1e-7, abs_tol=1e-12) or (math.isnan(got) and math.isnan(want))
        return [] if ok else [f"{where}: {got!r} != {want!r}"]
    if type(got) is not type(want):
        return [f"{where}: {got!r} != {want!r}"]
    if isinstance(want, dict):
        if got.keys() != want.keys():
            return [f"{where}: keys {sorted(got)} != {sorted(want)}"]
        return [d for k in want for d in _differences(got[k], want[k], f"{where}/{k}")]
    if isinstance(want, list):
        if len(got) != len(want):
            return [f"{where}: {len(got)} items != {len(want)}"]
        return [d for i, (g, w) in enumerate(zip(got, want)) for d in _differences(g, w, f"{where}[{i}]")]
    return [] if got == want else [f"{where}: {got!r} != {want!r}"]


def test_comparison_catches_a_moved_number():
    """The tolerance hides the last digits, not a change: a number moved by 1e-5 fails."""
    want = [{"a": 1.0, "b": [0.5, "x"], "n": 3}]
    assert _differences([{"a": 1.0 + 1e-12, "b": [0.5, "x"], "n": 3}], want, "") == []
    assert _differences([{"a": 1.00001, "b": [0.5, "x"], "n": 3}], want, "") != []
    assert _differences([{"a": 1.0, "b": [0.5, "y"], "n": 3}], want, "") != []
    assert _differences([{"a": 1.0, "b": [0.5, "x"], "n": 4}], want, "") != []
