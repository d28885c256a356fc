"""The simulator's cyclic-frame encoder gives the frames :meth:`CellDatabase.encode` gives
(cantools underneath), byte for byte: every message of the cell's DBC it covers, and the
messages of real vehicles' DBC files (Motorola big-endian signals, signed signals, long
frames), values beyond the DBC range (clamped), negative values and rounding ties included.
A message it does not cover (E2E-protected, multiplexed, float signals) is left to
``encode``; a NaN goes to ``encode`` too, which refuses it naming the signal."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cantools.database import EncodeError

import can
import cantools

from cell.sim.frame_encode import frame_encoder, message_encoder

REAL = Path(__file__).resolve().parents[3].parent / "shared" / "realdata" / "dbc"  # <repo>/../shared
REAL_FILES = ["toyota_prius_2010_pt.dbc", "hyundai_2015_ccan.dbc", "vw_mqb.dbc"]


def _values(message, rng, case):
    out = {}
    for s in message.signals:
        lo = -1e3 if s.minimum is None else float(s.minimum)
        hi = 1e3 if s.maximum is None else float(s.maximum)
        span = max(hi - lo, 1.0)
        if case % 3 == 0:  # a tie between two raw steps
            v = float(s.offset) + (int(rng.integers(0, 50)) + 0.5) * float(s.conversion.scale)
        else:  # inside, and beyond the range on both sides
            v = float(rng.uniform(lo - 0.2 * span, hi + 0.2 * span))
        out[s.name] = min(max(v, -1e12), 1e12)
    return out


def clamped_cantools(message):
    """The reference: each value clamped into its DBC range, then cantools' own encode."""
    def encode(values, timestamp):
        clamped = {}
        for s in message.signals:
            v = float(values[s.name])
            if s.minimum is not None:
                v = max(v, float(s.minimum))
            if s.maximum is not None:
                v = min(v, float(s.maximum))
            clamped[s.name] = v
        return can.Message(timestamp=timestamp, arbitration_id=message.frame_id,
                           is_extended_id=message.is_extended_frame,
                           data=message.encode(clamped, scaling=True, strict=False))
    return encode


def _check_all(messages, make, reference) -> int:
    rng = np.random.default_rng(11)
    covered = 0
    for m in messages:
        enc = make(m)
        if enc is None:
            continue
        covered += 1
        for case in range(12):
            vals = _values(m, rng, case)
            try:
                ref = reference(m)(dict(vals), 5.0 + case)
            except (OverflowError, EncodeError) as exc:  # a value beyond the signal's bits
                with pytest.raises(type(exc)):
                    enc(vals, 5.0 + case)
                continue
            got = enc(vals, 5.0 + case)
            assert bytes(got.data) == bytes(ref.data), (m.name, vals)
            assert (got.arbitration_id, got.is_extended_id, got.timestamp, got.dlc) == \
                (ref.arbitration_id, ref.is_extended_id, ref.timestamp, ref.dlc)
    return covered


def test_the_cells_messages_encode_as_cantools_does(db):
    sim = [m for m in db.messages if "SIM" in (m.senders or [])]
    covered = _check_all(db.messages, lambda m: frame_encoder(db, m),
                         lambda m: lambda v, t: db.encode(m.name, v, t))
    assert covered >= len(sim) // 2
    # every simulator message that is not E2E-protected is covered
    assert all(frame_encoder(db, m) is not None for m in sim if m.name not in db.e2e
               and not m.is_multiplexed() and not any(s.conversion.is_float for s in m.signals))


@pytest.mark.skipif(not REAL.is_dir(), reason="no real vehicle DBC files on this machine")
@pytest.mark.parametrize("name", REAL_FILES)
def test_real_vehicle_messages_encode_as_cantools_does(name):
    db = cantools.database.load_file(str(REAL / name), strict=False)

    def make(m):
        return message_encoder(m, lambda name, v, t: clamped_cantools(m)(v, t))
    covered = _check_all(db.messages, make, clamped_cantools)
    assert covered > 10
    big = [m for m in db.messages if any(s.byte_order == "big_endian" for s in m.signals)]
    if name.startswith("toyota"):
        assert any(make(m) is not None for m in big)


def test_e2e_messages_are_left_to_encode(db):
    assert db.e2e
    for name in db.e2e:
        assert frame_encoder(db, db.message(name)) is None


def test_a_nan_is_refused_naming_the_signal(db):
    m = next(m for m in db.messages if "SIM" in (m.senders or []) and frame_encoder(db, m))
    enc = frame_encoder(db, m)
    vals = {s.name: 0.0 for s in m.signals}
    vals[m.signals[-1].name] = float("nan")
    with pytest.raises(EncodeError, match=m.signals[-1].name):
        enc(vals, 0.0)
