"""Sample-stream frames encoded in bulk, for the simulator's hot path.

The simulator sends a crank-angle stream's samples four to a frame (750 frames per simulated
second for si-turbo's four streams). :meth:`CellDatabase.encode` per frame (clamping, then
cantools) is a large part of a step. A stream message's layout is simple: little-endian
integer signals with a linear scale, no multiplexing. :func:`stream_encoder` reads such a
message once and returns a function that encodes a run of whole frames at once with numpy:
the same clamping into the DBC range, the same ``round((value - offset) / scale)`` (round
half to even, as Python's ``round``), the same bits, so the same bytes as ``encode``. It
returns ``None`` for a layout it does not cover (the caller encodes those frame by frame).
"""

from __future__ import annotations

from collections.abc import Callable

import can
import numpy as np
from cantools.database.can import Message

from cell.runtime.samples import SampleLayout

Encoder = Callable[[int, np.ndarray, np.ndarray, float], list[can.Message] | None]


def stream_encoder(message: Message, layout: SampleLayout) -> Encoder | None:
    """The bulk encoder of ``layout``'s frames of ``message`` (module docstring), or None."""
    by_name = {s.name: s for s in message.signals}
    names = (layout.angle_signal, *layout.sample_signals)
    if (message.is_container or message.length != 8 or set(by_name) != set(names)
            or any(s.byte_order != "little_endian" or s.conversion.is_float or s.is_multiplexer
                   or s.multiplexer_ids is not None or s.length > 32 for s in by_name.values())):
        return None
    sigs = [by_name[n] for n in names]
    lo = np.array([-np.inf if s.minimum is None else float(s.minimum) for s in sigs])
    hi = np.array([np.inf if s.maximum is None else float(s.maximum) for s in sigs])
    offset = np.array([float(s.offset) for s in sigs])
    scale = np.array([float(s.scale) for s in sigs])
    masks = np.array([(1 << s.length) - 1 for s in sigs], dtype=np.int64)
    shifts = np.array([s.start for s in sigs], dtype=np.uint64)
    n, period, step = layout.n, layout.period, layout.step_deg
    frame_id, extended = message.frame_id, message.is_extended_frame

    def encode(first: int, samples: np.ndarray, times: np.ndarray, t0: float
               ) -> list[can.Message] | None:
        """Frames of the whole frames in ``samples`` from angle index ``first``; None when a
        sample is NaN (the caller's per-frame encode refuses it by name)."""
        m = len(samples) // n
        if m == 0:
            return []
        v = samples[:m * n].reshape(m, n)
        if np.isnan(v).any():
            return None
        phys = np.empty((m, n + 1))
        phys[:, 0] = ((first + n * np.arange(m)) % period) * step
        phys[:, 1:] = v
        phys = np.minimum(np.maximum(phys, lo), hi)
        raw = np.rint((phys - offset) / scale).astype(np.int64) & masks
        words = np.bitwise_or.reduce(raw.astype(np.uint64) << shifts, axis=1)
        data = words.astype("<u8").tobytes()
        stamps = (t0 + times[n - 1:m * n:n]).tolist()
        return [can.Message(timestamp=stamps[i], arbitration_id=frame_id, is_extended_id=extended,
                            data=data[8 * i:8 * i + 8]) for i in range(m)]

    return encode


__all__ = ["stream_encoder"]
