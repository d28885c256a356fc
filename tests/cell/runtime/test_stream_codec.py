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
