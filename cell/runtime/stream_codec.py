"""A sample-stream frame's samples straight from its bytes, for the runtime's hot path.

A crank-angle stream brings thousands of frames a second (6 000 samples/s per stream at
6 000 rpm, four to a frame), and each one is decoded, not only the newest: cantools' general
decoder (a dict of every signal, then the stream layout reading it back) is most of the
cost. A stream message's layout is simple: little-endian integer signals with a linear
scale, no multiplexing. :func:`fast_unpacker` reads such a message once and returns a
function from a frame's data to ``(angle index of the first sample, samples)`` (the result of
:meth:`SampleLayout.unpack` over :meth:`CellDatabase.decode_payload`: the same
``raw * scale + offset`` per signal), or ``None`` for a layout it does not cover, which then
goes through cantools as before.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from cantools.database.can import Message

from cell.runtime.samples import SampleLayout

Unpacker = Callable[[bytes], tuple[int, np.ndarray]]


def _plain(signal) -> bool:
    conv = signal.conversion
    return (signal.byte_order == "little_endian" and not conv.is_float
            and getattr(signal, "multiplexer_ids", None) is None and not signal.is_multiplexer
            and signal.length <= 32)


def fast_unpacker(message: Message, layout: SampleLayout) -> Unpacker | None:
    """The unpacker of ``layout``'s frames of ``message`` (module docstring), or None."""
    by_name = {s.name: s for s in message.signals}
    names = (layout.angle_signal, *layout.sample_signals)
    if (message.is_container or message.length != 8 or any(n not in by_name for n in names)
            or not all(_plain(by_name[n]) for n in names)):
        return None
    sigs = [by_name[n] for n in names]
    shifts = np.array([s.start for s in sigs], dtype=np.uint64)
    masks = np.array([(1 << s.length) - 1 for s in sigs], dtype=np.uint64)
    signed = np.array([s.is_signed for s in sigs])
    half = np.array([1 << (s.length - 1) for s in sigs], dtype=np.int64)
    full = np.array([1 << s.length for s in sigs], dtype=np.int64)
    scale = np.array([float(s.scale) for s in sigs])
    offset = np.array([float(s.offset) for s in sigs])
    any_signed = bool(signed.any())
    step, period = layout.step_deg, layout.period

    def unpack(data: bytes) -> tuple[int, np.ndarray]:
        word = np.frombuffer(data, dtype="<u8", count=1)[0]
        raw = ((word >> shifts) & masks).astype(np.int64)
        if any_signed:
            raw = np.where(signed & (raw >= half), raw - full, raw)
        phys = raw * scale + offset
        index = int(round(float(phys[0]) / step)) % period
        return index, phys[1:]

    return unpack


__all__ = ["fast_unpacker"]
