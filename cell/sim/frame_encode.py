"""Cyclic frames encoded without cantools' per-call machinery, for the simulator's hot path.

:meth:`CellDatabase.encode` clamps each value into its DBC range, then hands the message to
cantools, whose encode walks its codec tree and builds a dict of raw values on every call:
about 20 µs a frame, a frame every 10 ms for each of the simulator's ~9 cyclic messages.
:func:`frame_encoder` reads a message once and returns a function that does the same work
directly: the same clamping, each signal's own cantools conversion for the raw value (so the
same rounding), and the raw values packed at the bit positions cantools packs them at
(little-endian signals from their start bit; big-endian ones in network order), so the same
bytes (``tests/cell/sim/test_frame_encode.py`` checks every simulator message against
``encode``). It returns ``None`` for a message it does not cover (E2E-protected: counter and
CRC; multiplexed; container; float signals; overlapping signals), which the caller encodes with ``encode``.
A NaN value, or one whose raw value does not fit its bits (a DBC range wider than the
signal), is refused by ``encode``: the encoder hands such a frame back to it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import can
from cantools.database.can import Message

from cell.bus.dbc import CellDatabase

Encoder = Callable[[Mapping[str, float], float], can.Message]


def frame_encoder(db: CellDatabase, message: Message) -> Encoder | None:
    """The fast encoder of ``db``'s ``message`` (module docstring), or None when it does not
    apply (E2E-protected messages among them)."""
    if message.name in db.e2e:
        return None
    return message_encoder(message, db.encode)


def message_encoder(message: Message, refuse: Callable[[str, dict, float], can.Message]
                    ) -> Encoder | None:
    """The fast encoder of a cantools ``message`` with no E2E protection, or None;
    ``refuse(name, values, timestamp)`` encodes a frame with a NaN value (it raises)."""
    if (message.is_container or message.is_multiplexed()
            or any(s.conversion.is_float or s.is_multiplexer or s.multiplexer_ids
                   for s in message.signals)):
        return None
    n_bytes = message.length
    bits = 8 * n_bytes
    fields = []
    for s in message.signals:
        lo = None if s.minimum is None else float(s.minimum)
        hi = None if s.maximum is None else float(s.maximum)
        if s.byte_order == "little_endian":
            little, shift = True, s.start
        else:  # network bit number of the MSB, counted from the first byte's MSB
            little = False
            shift = bits - (8 * (s.start // 8) + (7 - s.start % 8) + s.length)
        if shift < 0 or shift + s.length > bits:
            return None
        r_lo, r_hi = ((-(1 << (s.length - 1)), (1 << (s.length - 1)) - 1) if s.is_signed
                      else (0, (1 << s.length) - 1))
        fields.append((s.name, lo, hi, s.conversion.numeric_scaled_to_raw, r_lo, r_hi,
                       (1 << s.length) - 1, shift, little))
    used = 0  # the frame's bits taken so far: overlapping signals are cantools' to refuse
    for *_, mask, shift, little in fields:
        bits_of = mask << shift
        if not little:
            bits_of = int.from_bytes(bits_of.to_bytes(n_bytes, "big"), "little")
        if used & bits_of:
            return None
        used |= bits_of
    name, frame_id, extended = message.name, message.frame_id, message.is_extended_frame

    def encode(values: Mapping[str, float], timestamp: float) -> can.Message:
        le = be = 0
        for sig, lo, hi, to_raw, r_lo, r_hi, mask, shift, little in fields:
            v = float(values[sig])
            if v != v:
                return refuse(name, dict(values), timestamp)  # raises, naming it
            if lo is not None and v < lo:
                v = lo
            if hi is not None and v > hi:
                v = hi
            raw = to_raw(v)
            if not r_lo <= raw <= r_hi:  # a DBC range wider than the signal's bits
                return refuse(name, dict(values), timestamp)  # raises, as cantools does
            raw = (raw & mask) << shift
            if little:
                le |= raw
            else:
                be |= raw
        word = int.from_bytes(le.to_bytes(n_bytes, "little"), "big") | be
        return can.Message(timestamp=timestamp, arbitration_id=frame_id,
                           is_extended_id=extended, data=word.to_bytes(n_bytes, "big"))

    return encode


__all__ = ["frame_encoder", "message_encoder"]
