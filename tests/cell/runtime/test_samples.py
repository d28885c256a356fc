"""Crank-angle sample streams: the DBC layout, the order tracker and stream blocks in the
runtime (every sample, in angle order, counted in /health, the same frame by frame and
in bulk)."""

from __future__ import annotations

import can
import numpy as np
import pytest

from cell.runtime.blocks import Block
from cell.core.errors import ConfigError
from cell.runtime.scheduler import Runtime
from cell.runtime.samples import SampleLayout, SampleTracker, find_sample_streams


def test_the_crank_dbc_defines_four_streams_of_four_6_deg_samples(db):
    streams = find_sample_streams(db.messages)
    assert {"AFR_UEGO", "N_CRANK", "AFR_MANIFOLD_TRUE", "N_CYL_TRUE"} <= set(streams)
    la = streams["AFR_UEGO"]
    assert (la.n, la.step_deg, la.period_deg, la.period, la.message) == (4, 6.0, 720.0, 120,
                                                                         "CRANK_AFR_UEGO")
    # ordinary messages are not streams
    assert SampleLayout.from_message(db.message("ENGINE_1")) is None


def test_a_frame_decodes_with_plain_cantools_as_documented(db):
    la = find_sample_streams(db.messages)["N_CRANK"]
    # a global sample index (here one cycle and 119 samples) goes out as its angle in the cycle
    msg = db.encode(la.message, la.frame_values(120 + 119, np.array([1500.0, 1501.5, 1499, 1480])))
    m = db.db.get_message_by_name("CRANK_N")
    values = m.decode(msg.data)  # what a user's logger does
    assert values["N_CRANK_ANGLE"] == 714.0
    index, samples = la.unpack(values)
    assert index == 119
    np.testing.assert_allclose(samples, [1500.0, 1501.5, 1499.0, 1480.0])
    # byte 0 is the angle in 6 deg steps, then 14-bit samples from bit 8, little-endian
    raw = int.from_bytes(msg.data, "little")
    assert raw & 0xFF == 119 and (raw >> 8) & 0x3FFF == 3000


def _frames(la, start, count, t0=0.0):
    for k in range(count):
        i = (start + la.n * k) % la.period
        yield i, np.arange(i, i + la.n, dtype=float), t0 + k * 1e-3


def _run(tracker, frames):
    events = []
    for i, v, t in frames:
        events.extend(tracker.push(i, v, t))
    return events


@pytest.fixture
def layout(db):
    return find_sample_streams(db.messages)["AFR_UEGO"]


def test_tracker_passes_frames_in_order_across_the_wrap(layout):
    tr = SampleTracker(layout)
    events = _run(tr, _frames(layout, 112, 5))
    assert [e[1] for e in events] == [112, 116, 0, 4, 8]
    assert tr.counts.samples == 20 and tr.counts.lost_frames == 0 and tr.counts.gaps == 0


def test_tracker_puts_a_swapped_pair_back_in_order(layout):
    tr = SampleTracker(layout)
    f = list(_frames(layout, 0, 5))
    events = _run(tr, [f[0], f[2], f[1], f[3], f[4]])
    assert [e[0] for e in events] == ["samples"] * 5
    assert [e[1] for e in events] == [0, 4, 8, 12, 16]
    assert tr.counts.reordered == 1 and tr.counts.lost_frames == 0


def test_tracker_declares_a_loss_after_the_window_and_skips_ahead(layout):
    tr = SampleTracker(layout, window=2)
    f = list(_frames(layout, 0, 8))
    events = _run(tr, [f[0], f[3], f[4], f[5], f[6], f[7]])  # frames 1 and 2 lost
    assert events[1] == ("gap", 8, 12, f[5][2])
    assert [e[1] for e in events if e[0] == "samples"] == [0, 12, 16, 20, 24, 28]
    assert tr.counts.lost_frames == 2 and tr.counts.gaps == 1
    assert tr.counts.last_gap == {"at_index": 12, "lost_samples": 8, "t": f[5][2]}


def test_tracker_drops_a_frame_whose_place_has_passed(layout):
    tr = SampleTracker(layout, window=1)
    f = list(_frames(layout, 0, 6))
    events = _run(tr, [f[0], f[2], f[3], f[1], f[4]])  # f[1] arrives after the loss was declared
    assert tr.counts.late == 1 and tr.counts.lost_frames == 1
    assert [e[1] for e in events if e[0] == "samples"] == [0, 8, 12, 16]


def test_tracker_follows_a_jump_of_more_than_half_a_cycle(layout):
    tr = SampleTracker(layout, window=2)
    f = list(_frames(layout, 0, 30))
    events = _run(tr, [f[0]] + f[20:24])  # 19 frames (76 samples) never arrive
    gaps = [e for e in events if e[0] == "gap"]
    assert gaps == [("gap", 76, 80, f[20][2])]
    assert [e[1] for e in events if e[0] == "samples"] == [0, 80, 84, 88, 92]
    assert tr.counts.late == 0 and tr.counts.lost_frames == 19


class Recorder(Block):
    """A block that keeps every sample of a stream, and publishes how many it has."""

    def __init__(self, stream="N_CRANK"):
        super().__init__("recorder", [], ["REC_COUNT"], "MED")
        self.streams = (stream,)
        self.seen: list[tuple[int, float, float]] = []
        self.gaps: list[tuple[int, int]] = []

    def _samples(self, stream, index, values, t):
        if values[0] <= 0:
            raise ZeroDivisionError("a sample the block cannot take")
        self.seen.extend((index + k, float(v), t) for k, v in enumerate(values))

    def gap(self, stream, lost, index, t):
        self.gaps.append((lost, index))

    def _step(self, t, inputs):
        return {"REC_COUNT": float(len(self.seen))}


def _crank_frames(db, indexes, values=None):
    la = find_sample_streams(db.messages)["N_CRANK"]
    out = []
    for k, i in enumerate(indexes):
        v = np.full(4, 1500.0 + k) if values is None else values[k]
        out.append(db.encode(la.message, la.frame_values(i, v), 0.001 * (k + 1)))
    return out


def test_a_stream_block_gets_every_sample_in_angle_order_and_publishes_at_ticks(db):
    rec = Recorder()
    rt = Runtime(db, [rec])
    frames = _crank_frames(db, [0, 4, 12, 8, 16, 20])  # one swap
    rt.ingest_many(frames)
    rt.advance(0.2)
    assert [s[0] for s in rec.seen] == list(range(24))
    assert [s[1] for s in rec.seen[8:16]] == [1503.0] * 4 + [1502.0] * 4  # taken back in order
    assert rt.channels["REC_COUNT"].value == 24.0
    h = rt.health()["streams"]["N_CRANK"]
    assert h["frames"] == 6 and h["reordered"] == 1 and h["samples"] == 24 and h["lost_frames"] == 0
    # the stream's frames are also ordinary channels (the newest frame's samples)
    assert rt.channels["N_CRANK_0"].value == 1505.0


def test_the_same_samples_frame_by_frame_as_in_bulk(db):
    frames = _crank_frames(db, [0, 4, 16, 8, 20, 24, 28, 32, 36])
    a, b = Recorder(), Recorder()
    rt_a, rt_b = Runtime(db, [a]), Runtime(db, [b])
    rt_a.ingest_many(frames)
    for f in frames:  # as the live cell does
        rt_b.ingest(f)
    assert a.seen == b.seen and a.gaps == b.gaps == [(4, 16)]
    assert rt_a.health()["streams"] == rt_b.health()["streams"]


def test_a_block_error_on_samples_is_counted_and_the_stream_goes_on(db):
    rec = Recorder()
    rt = Runtime(db, [rec])
    vals = [np.full(4, 1500.0), np.full(4, 0.0), np.full(4, 1500.0)]
    rt.ingest_many(_crank_frames(db, [0, 4, 8], vals))
    assert rt.health()["block_errors"] == {"recorder": 1}
    assert [s[0] for s in rec.seen] == [0, 1, 2, 3, 8, 9, 10, 11]


def test_a_block_of_an_unknown_stream_is_refused_naming_the_streams(db):
    with pytest.raises(ConfigError, match="NO_SUCH.*streams: AFR_MANIFOLD_TRUE, AFR_UEGO"):
        Runtime(db, [Recorder("NO_SUCH")])


def test_removing_the_block_removes_its_route(db):
    rt = Runtime(db, [Recorder()])
    rt.remove_block("recorder")
    rt.ingest_many(_crank_frames(db, [0, 4]))
    assert rt.health()["streams"] == {}


def test_ordinary_frames_take_the_same_path_with_a_stream_block_present(db):
    rt = Runtime(db, [Recorder()])
    msg = db.encode("ENGINE_1", {"ENGINE_SPEED": 1500, "ENGINE_TORQUE": 100, "FUEL_RATE": 5,
                                 "ENGINE_POWER": 15}, 0.01)
    rt.ingest(msg)
    rt.ingest(can.Message(timestamp=0.02, arbitration_id=0x7FF, data=b"\x00"))
    assert rt.channels["ENGINE_SPEED"].value == 1500.0
    assert rt.health()["decode_errors"]["unknown_id"] == 1


def test_live_on_a_bus_as_offline(db):
    """The si-turbo simulator in real time on a virtual bus, the runtime live beside it:
    every sample of both streams arrives and the diagnosis is the offline one."""
    import time
    import uuid

    from cell import sim as simmod
    from cell.bus.interface import open_bus
    from cell.estimators.cylinders import imbalance_observers
    from cell.app.live import LiveCell
    from cell.sim.lockstep import Lockstep
    from cell.core.settings import Settings

    s = Settings.build({"engine": "si-turbo", "duty": "steady", "imbalance": "4:-0.25",
                        "duration": 2.0}, environ={}).for_simulator()
    off = Runtime(db, imbalance_observers())
    Lockstep(simmod.build(s, db), off).run(2.0)
    want = off.health()["streams"]["N_CRANK"]["samples"]
    channel = f"virtual:streams-{uuid.uuid4().hex[:8]}"
    rt = Runtime(db, imbalance_observers())
    bus_rt, bus_sim = open_bus(channel), open_bus(channel)
    live = LiveCell(rt, bus_rt).start()
    try:
        simmod.run(bus_sim, s, db=db)
        for _ in range(250):  # the frames still in flight
            if rt.health()["streams"]["N_CRANK"]["samples"] >= want:
                break
            time.sleep(0.02)
        time.sleep(0.2)
    finally:
        live.stop()
        bus_rt.shutdown()
        bus_sim.shutdown()
    for name in ("AFR_UEGO", "N_CRANK"):
        got, ref = rt.health()["streams"][name], off.health()["streams"][name]
        assert got == ref  # every frame, in order, none lost or late
    assert rt.channels["IMBALANCE_CYL"].value == off.channels["IMBALANCE_CYL"].value == 4.0


def test_a_refused_block_leaves_no_route_behind(db):
    class Two(Recorder):
        def __init__(self):
            super().__init__()
            self.streams = ("N_CRANK", "NO_SUCH")

    rt = Runtime(db)
    with pytest.raises(ConfigError, match="NO_SUCH"):
        rt.add_block(Two())
    assert rt.health()["streams"] == {} and "recorder" not in rt.blocks
