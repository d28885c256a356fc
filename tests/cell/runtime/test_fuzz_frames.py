"""Frame fuzzing: 100,000 random frames (random IDs including the cell's own, DLC 0-8, random
payloads, remote, error and CAN FD frames) go through the decode path and a runtime, in
process and live over a virtual bus. Nothing crashes, every bad frame is counted by kind in
``/health``, and the good channels are exactly what they are without the fuzz."""

import math
import time

import can
import numpy as np
import pytest
from tests.helpers.client import local_client

from cell.bus.interface import open_bus
from cell.app.cell import Cell
from cell.estimators.backpressure import native_filters
from cell.app.live import LiveCell
from cell.runtime.scheduler import Runtime
from service.main import create_app

N_FUZZ = 100_000
SECONDS = 60.0
GOOD_ID = 0x101  # EXH_BP: the good channels' frame, never fuzzed with a valid length


def good_frames(db, seconds=SECONDS):
    rng = np.random.default_rng(1)
    out = []
    for i in range(int(seconds * 100)):
        t = i * 0.01
        truth = 600.0 + 200.0 * (t > seconds / 2)
        out.append(db.encode("EXH_BP", {"EXH_BP_L": truth + rng.normal(0, 40),
                                        "EXH_BP_R": truth + rng.normal(0, 40)}, t))
    return out


def fuzz_frames(db, n=N_FUZZ, seconds=SECONDS, seed=13):
    """Random frames and the count of each kind of bad frame they hold (worked out here)."""
    rng = np.random.default_rng(seed)
    own = sorted({m.frame_id for m in db.messages} - {GOOD_ID})
    lengths = {m.frame_id: m.length for m in db.messages}
    expect = {"unknown_id": 0, "bad_length": 0, "remote_frame": 0, "error_frame": 0, "valid": 0}
    ts = np.sort(rng.uniform(0.0, seconds - 0.01, n))
    kinds = rng.choice(6, n, p=[0.35, 0.25, 0.15, 0.1, 0.1, 0.05])
    frames = []
    for t, kind in zip(ts.tolist(), kinds.tolist()):
        ext = False
        if kind == 0:  # a random ID: 11 or 29 bit
            ext = bool(rng.random() < 0.5)
            arb = int(rng.integers(0, 2**29 if ext else 2**11))
            dlc = int(rng.integers(0, 9))
        elif kind == 1:  # one of the cell's own IDs, with a random length
            arb = int(rng.choice(own))
            dlc = int(rng.integers(0, 9))
        elif kind == 2:  # the good channels' ID with a wrong length
            arb = GOOD_ID
            dlc = int(rng.choice([d for d in range(9) if d != 8]))
        elif kind == 3:
            frames.append(can.Message(timestamp=t, arbitration_id=int(rng.choice([GOOD_ID, *own])),
                                      is_remote_frame=True, dlc=int(rng.integers(0, 9)),
                                      is_extended_id=False))
            expect["remote_frame"] += 1
            continue
        elif kind == 4:
            frames.append(can.Message(timestamp=t, is_error_frame=True, arbitration_id=0,
                                      data=bytes(rng.integers(0, 256, 8).tolist())))
            expect["error_frame"] += 1
            continue
        else:  # CAN FD frame on the good ID: 12..64 bytes
            arb, dlc = GOOD_ID, int(rng.choice([12, 16, 20, 24, 32, 48, 64]))
        data = bytes(rng.integers(0, 256, dlc).tolist())
        frames.append(can.Message(timestamp=t, arbitration_id=arb, data=data, is_extended_id=ext,
                                  is_fd=dlc > 8))
        known = (arb, ext) in {(m.frame_id, m.is_extended_frame) for m in db.messages}
        if not known:
            expect["unknown_id"] += 1
        elif lengths[arb] != dlc:
            expect["bad_length"] += 1
        else:
            expect["valid"] += 1
    return frames, expect


def merge(a, b):
    return sorted(a + b, key=lambda m: m.timestamp)


@pytest.fixture(scope="module")
def streams(db):
    good = good_frames(db)
    fuzz, expect = fuzz_frames(db)
    return good, fuzz, expect


def run(db, frames):
    rt = Runtime(db, native_filters())
    rows = []
    rt.tick_listeners.append(lambda t: rows.append(
        (t, *(rt.channels[n].value for n in ("EXH_BP_R", "EXH_BP_R_Kalman", "EXH_BP_L_MAF")))))
    rt.ingest_many(frames)
    rt.advance(SECONDS)
    return rt, rows


def test_fuzz_in_process_counts_every_bad_frame_and_leaves_good_channels_exact(db, streams):
    good, fuzz, expect = streams
    assert len(fuzz) >= 100_000
    clean_rt, clean = run(db, good)
    rt, fuzzed = run(db, merge(good, fuzz))
    h = local_client(create_app(Cell(runtime=rt))).get("/health").json()
    assert h["frames"] == len(good) + len(fuzz)
    errs = h["decode_errors"]
    for kind in ("unknown_id", "bad_length", "remote_frame", "error_frame"):
        assert errs[kind] == expect[kind], (kind, errs, expect)
    assert errs["decode_error"] == 0
    assert sum(h["unknown_ids"].values()) <= expect["unknown_id"] and h["unknown_ids"]
    assert fuzzed == clean  # every tick of the good channels, bit for bit
    print(f"\n{len(fuzz)} fuzz frames: {expect}")


def test_fuzz_through_a_live_runtime_over_a_virtual_bus(db, streams):
    good, fuzz, expect = streams
    frames = merge(good, fuzz)
    channel = f"fuzz-{time.monotonic_ns()}"
    rt = Runtime(db, native_filters())
    bus = open_bus(f"virtual:{channel}")
    live = LiveCell(rt, bus, grace_s=5.0).start()  # frames are sent faster than bus time
    tx = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    try:
        for msg in frames:
            tx.send(msg)
        deadline = time.monotonic() + 60
        while rt.frames < len(frames) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert live.running and live.bus_problem is None
    finally:
        live.stop()
        bus.shutdown()
        tx.shutdown()
    assert rt.frames == len(frames)
    h = rt.health()
    for kind in ("unknown_id", "bad_length", "remote_frame", "error_frame"):
        assert h["decode_errors"][kind] == expect[kind], kind
    rt.advance(SECONDS)
    clean_rt, _ = run(db, good)
    for name in ("EXH_BP_R_Kalman", "EXH_BP_L_MAF"):
        assert rt.channels[name].status == "ok"
        assert math.isclose(rt.channels[name].value, clean_rt.channels[name].value, rel_tol=1e-9)
