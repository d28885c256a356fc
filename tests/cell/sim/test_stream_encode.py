"""The simulator's bulk encoder of sample-stream frames gives the frames
:meth:`CellDatabase.encode` gives, byte for byte and stamp for stamp, values beyond the DBC
range (clamped) and rounding ties included; a NaN goes back to the per-frame encoder."""

from __future__ import annotations

import numpy as np
import pytest

from cell.runtime.samples import find_sample_streams
from cell.sim.stream_encode import stream_encoder


@pytest.mark.parametrize("stream", ["AFR_UEGO", "N_CRANK", "AFR_MANIFOLD_TRUE", "N_CYL_TRUE"])
def test_bulk_frames_are_the_frames_encode_gives(db, stream):
    layout = find_sample_streams(db.messages)[stream]
    message = db.message(layout.message)
    bulk = stream_encoder(message, layout)
    assert bulk is not None
    sig = message.get_signal_by_name(layout.sample_signals[0])
    rng = np.random.default_rng(5)
    span = float(sig.maximum) - float(sig.minimum)
    for first in (0, 4, 112, 116):
        m = 30
        vals = rng.uniform(float(sig.minimum) - 0.1 * span, float(sig.maximum) + 0.1 * span, 4 * m)
        vals[::7] = float(sig.offset) + (np.arange(len(vals[::7])) + 0.5) * float(sig.scale)  # ties
        times = np.sort(rng.uniform(0.0, 10.0, 4 * m))
        got = bulk(first, vals, times, 1000.0)
        for i, msg in enumerate(got):
            ref = db.encode(layout.message,
                            layout.frame_values(first + 4 * i, vals[4 * i:4 * i + 4]),
                            1000.0 + float(times[4 * i + 3]))
            assert bytes(msg.data) == bytes(ref.data), (i, vals[4 * i:4 * i + 4])
            assert msg.timestamp == ref.timestamp and msg.arbitration_id == ref.arbitration_id
    vals[3] = np.nan
    assert bulk(0, vals, times, 0.0) is None
