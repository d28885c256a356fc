"""The simulator's frames are bit-identical to those recorded before the tree was laid out
in layers (issue 17): sha256 over every frame's timestamp, ID and data, per duty cycle.

The digests in ``tests/data/golden_frames.json`` were written by the code before the move
(``python tests/test_golden_frames.py --write``). A change to a plant, a DBC file or the
simulator's scheduling changes them on purpose: regenerate them in the same commit, and say
why in its message.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import can
import pytest

GOLDEN = Path(__file__).with_name("data") / "golden_frames.json"

#: case -> ``testcell sim`` arguments (short runs that still cover each cycle's start)
CASES: dict[str, list[str]] = {
    "rated": ["--engine", "large-diesel", "--duty", "rated", "--duration", "40"],
    "warmup": ["--engine", "large-diesel", "--duty", "warmup", "--duration", "40"],
    "transient": ["--engine", "large-diesel", "--duty", "transient", "--duration", "20"],
    "etc": ["--engine", "large-diesel", "--duty", "etc", "--duration", "20"],
    "ftp": ["--engine", "si-turbo", "--duty", "ftp", "--duration", "6"],
    "throttle-steps": ["--engine", "si-turbo", "--duty", "throttle-steps", "--duration", "10",
                       "--crank", "off"],
    # the valve nearly shut at a low limit: the engine trips during the ramp
    "trip": ["--engine", "large-diesel", "--duty", "rated", "--duration", "40", "--valve", "3",
             "--bp-limit", "700"],
}


def digest(path: Path) -> tuple[str, int]:
    """sha256 over (timestamp, ID, extended flag, data) of every frame, and the frame count."""
    h = hashlib.sha256()
    n = 0
    with can.LogReader(str(path)) as reader:
        for msg in reader:
            h.update(f"{msg.timestamp:.6f} {msg.arbitration_id:08X} {int(msg.is_extended_id)} "
                     f"{bytes(msg.data).hex()}\n".encode())
            n += 1
    return h.hexdigest(), n


def record(case: str, folder: Path) -> Path:
    out = folder / f"{case}.log"
    subprocess.run([sys.executable, "-m", "cell", "sim", *CASES[case], "--out", str(out)],
                   check=True, capture_output=True, text=True, timeout=600)
    return out


@pytest.mark.parametrize("case", sorted(CASES))
def test_frames_are_bit_identical(case, tmp_path):
    golden = json.loads(GOLDEN.read_text())[case]
    sha, n = digest(record(case, tmp_path))
    assert n == golden["frames"]
    assert sha == golden["sha256"]


def test_the_trip_case_trips(tmp_path):
    """The tripping case is one: TRIP_REASON leaves 0 in its frames."""
    from cell.bus.dbc import load

    db = load()
    reasons = set()
    with can.LogReader(str(record("trip", tmp_path))) as reader:
        for msg in reader:
            try:
                _, values = db.decode(msg)
            except Exception:
                continue
            if "TRIP_REASON" in values:
                reasons.add(values["TRIP_REASON"])
    assert reasons - {0.0}, "the trip case never tripped"


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        table = {}
        for case in sorted(CASES):
            sha, n = digest(record(case, Path(tmp)))
            table[case] = {"sha256": sha, "frames": n}
            print(case, n, sha)
    GOLDEN.parent.mkdir(exist_ok=True)
    GOLDEN.write_text(json.dumps(table, indent=2) + "\n")
