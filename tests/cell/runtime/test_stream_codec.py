"""The runtime's fast path for sample-stream frames, against cantools, and the stream work
counted in the blocks' step time and the ticks' work (issue 18 point 6)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from cell.runtime import stream_time
from cell.runtime.blocks import Block
from cell.runtime.samples import find_sample_streams
from cell.runtime.scheduler import Runtime
from cell.runtime.stream_codec import fast_unpacker


@pytest.mark.parametrize("stream", ["AFR_UEGO", "N_CRANK", "AFR_MANIFOLD_TRUE", "N_CYL_TRUE"])
def test_fast_unpack_gives_what_cantools_and_the_layout_give(db, stream):
    layout = find_sample_streams(db.messages)[stream]
    message = db.message(layout.message)
    fast = fast_unpacker(message, layout)
    assert fast is not None  # the cell's own streams all take the fast path
    rng = np.random.default_rng(3)
    for _ in range(300):
        data = bytes(rng.integers(0, 256, message.length, dtype=np.uint8))
        index, samples = fast(data)
        ref_index, ref = layout.unpack(db.decode_payload(message, data))
        assert index == ref_index
        assert samples.tolist() == ref.tolist()  # the same floats, not merely close


class Slow(Block):
    """A stream block whose samples take a known least time."""

    def __init__(self):
        super().__init__("slow", [], ["SLOW_N"], "MED")
        self.streams = ("N_CRANK",)
        self.n = 0

    def _samples(self, stream, index, values, t):
        time.sleep(0.002)
        self.n += len(values)

    def _step(self, t, inputs):
        return {"SLOW_N": float(self.n)}


def test_stream_work_counts_in_step_time_and_in_the_next_ticks_work(db):
    layout = find_sample_streams(db.messages)["N_CRANK"]
    frames = [db.encode(layout.message, layout.frame_values(4 * k, np.full(4, 1500.0)),
                        0.001 * (k + 1)) for k in range(10)]
    rt = Runtime(db, [Slow()])
    rt.ingest_many(frames)  # no tick yet: bus time 0.01 s
    seconds, steps = rt.counters.step_time["slow"]
    assert steps == 0 and seconds >= 10 * 0.002  # ten frames of samples, no step
    assert stream_time.take(rt) >= 10 * 0.002  # what the next tick adds to its work...
    assert stream_time.take(rt) == 0.0  # ...once


@pytest.mark.parametrize("stream", ["AFR_UEGO", "N_CRANK"])
def test_a_batch_decodes_to_the_numbers_of_frame_by_frame(db, stream):
    """StreamUnpacker.many (a live batch's stream frames at once) against the unpacker of one
    frame, itself checked against cantools above: the same indexes, the same floats."""
    layout = find_sample_streams(db.messages)[stream]
    fast = fast_unpacker(db.message(layout.message), layout)
    rng = np.random.default_rng(7)
    datas = [bytes(rng.integers(0, 256, 8, dtype=np.uint8)) for _ in range(500)]
    datas += [layout_bytes for layout_bytes in (db.encode(layout.message, layout.frame_values(
        4 * k, np.full(4, 1234.5 + k)), 0.0).data for k in range(30))]
    indexes, samples = fast.many([bytearray(d) for d in datas])
    assert samples.shape == (len(datas), layout.n)
    for data, index, row in zip(datas, indexes, samples):
        ref_index, ref = fast(data)
        assert index == ref_index and type(index) is int
        assert row.tolist() == ref.tolist()


def test_a_runtime_fed_in_batches_gives_its_stream_blocks_what_frame_by_frame_gives(db):
    """The live loop's batches (stream frames decoded together, the tracker's fast path)
    against one frame at a time from a generator (the per-frame path): the same samples,
    gaps and counts, with reordering, loss and a late frame in the stream."""
    from tests.cell.runtime.test_samples import Recorder, _crank_frames

    order = [0, 4, 8, 16, 12, 20, 24, 40, 44, 48, 52, 56, 36, 60, 64, 68] + list(range(72, 720, 4))
    frames = _crank_frames(db, order, [np.full(4, 1000.0 + 3 * k) for k in range(len(order))])
    a, b = Recorder(), Recorder()
    rt_a, rt_b = Runtime(db, [a]), Runtime(db, [b])
    for i in range(0, len(frames), 37):
        rt_a.ingest_many(frames[i:i + 37])  # lists: decoded per batch
    rt_b.ingest_many(f for f in frames)  # a generator: frame by frame
    assert a.seen == b.seen and a.gaps == b.gaps and len(a.seen) > 600
    assert rt_a.health()["streams"] == rt_b.health()["streams"]
    h = rt_a.health()["streams"]["N_CRANK"]
    assert h["reordered"] == 1 and h["gaps"] >= 1 and h["late"] == 1
