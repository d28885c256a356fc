"""Command integrity: an alive counter and a CRC on the frames that command the simulator.

In the style of AUTOSAR E2E profile 1, a protected message carries two ordinary DBC signals:
``<MESSAGE>_CTR``, a 4-bit alive counter (0..14, one more per frame, 14 wraps to 0), and
``<MESSAGE>_CRC``, a whole byte holding CRC-8 SAE J1850 (polynomial 0x1D) over the message's
16-bit data ID (low byte, then high byte: profile 1's data-ID mode "both") and every other byte
of the payload. The DBC marks a message as protected with the message attribute
``E2EDataID``; ``E2EMaxDeltaCounter`` (default 1) is the largest counter step the receiver
accepts, and 0 means "any new value" (an operator command that several senders put on the
bus, each with its own counter: the runtime, ``testcell scenario``).

As profile 1 chains ``Crc_CalculateCRC8`` (start value 0xFF and final XOR 0xFF on each call)
over the data ID bytes and the payload and XORs the result with 0xFF once more, its CRC is the
plain polynomial division with start value 0x00 and no final XOR (:func:`e2e_crc`). The
CRC arithmetic comes from ``crccheck``.

The sender side is :class:`Counters` (used by :meth:`cell.bus.dbc.CellDatabase.encode`), the
receiver side :class:`Receiver` (used by the simulator).
"""

from __future__ import annotations

import threading
from collections import Counter
from dataclasses import dataclass

from cantools.database.can import Message
from crccheck.crc import Crc8Base, Crc8SaeJ1850

from cell.core.errors import ConfigError

#: DBC message attributes.
DATA_ID_ATTR = "E2EDataID"
MAX_DELTA_ATTR = "E2EMaxDeltaCounter"
#: Largest alive counter value (profile 1: 0..14; 15 is not a valid counter).
COUNTER_MAX = 14
#: Why a receiver discards a frame, as counted.
REASONS = ("crc", "repeated", "skipped", "too_old")
#: Age allowed to a protected message without a cycle time, s.
EVENT_MAX_AGE = 0.1
_AGE_TOLERANCE = 1e-6  # bus times are sums of steps: exactly one cycle old is not too old


class _Crc8Profile1(Crc8Base):
    """CRC-8 SAE J1850 polynomial as E2E profile 1's chain computes it: start 0x00, no XOR."""

    _names = ("CRC-8/E2E-P01",)
    _width = 8
    _poly = 0x1D
    _initvalue = 0x00
    _reflect_input = False
    _reflect_output = False
    _xor_output = 0x00


def crc8_sae_j1850(data: bytes) -> int:
    """CRC-8 SAE J1850 (poly 0x1D, start 0xFF, final XOR 0xFF): AUTOSAR ``Crc_CalculateCRC8``."""
    return Crc8SaeJ1850.calc(data)


def e2e_crc(data_id: int, payload: bytes) -> int:
    """Profile 1's CRC of ``payload`` (the frame without its CRC byte) under ``data_id``."""
    return _Crc8Profile1.calc(bytes((data_id & 0xFF, (data_id >> 8) & 0xFF)) + bytes(payload))


@dataclass(frozen=True)
class E2ESpec:
    """How one message is protected: its data ID, its counter and CRC signals."""

    message: str
    data_id: int
    counter: str
    crc: str
    crc_byte: int
    max_delta: int
    cycle_s: float | None

    @property
    def max_age(self) -> float:
        """Oldest a frame may be when it arrives, s: one cycle, or :data:`EVENT_MAX_AGE`."""
        return self.cycle_s if self.cycle_s else EVENT_MAX_AGE

    def crc_of(self, data: bytes) -> int:
        """The CRC a frame with this data must carry."""
        return e2e_crc(self.data_id, data[:self.crc_byte] + data[self.crc_byte + 1:])


def spec_of(message: Message, where: str = "DBC") -> E2ESpec | None:
    """The E2E protection of a message (``None``: not protected).

    Raises
    ------
    ConfigError
        The message has ``E2EDataID`` but no ``<NAME>_CTR`` of 4 bits or no ``<NAME>_CRC``
        of one whole byte (the text names the file and the signal).
    """
    attrs = message.dbc.attributes if message.dbc is not None else {}
    if DATA_ID_ATTR not in attrs:
        return None
    data_id = int(attrs[DATA_ID_ATTR].value)
    max_delta = int(attrs[MAX_DELTA_ATTR].value) if MAX_DELTA_ATTR in attrs else 1
    names = {s.name: s for s in message.signals}
    ctr, crc = f"{message.name}_CTR", f"{message.name}_CRC"
    c = names.get(ctr)
    if c is None or c.length != 4 or c.is_signed or c.scale != 1 or c.offset != 0:
        raise ConfigError(f"{where}: E2E message {message.name} needs an unsigned 4-bit "
                          f"signal {ctr} with scale 1")
    r = names.get(crc)
    if (r is None or r.length != 8 or r.start % 8 or r.byte_order != "little_endian"
            or r.is_signed or r.scale != 1 or r.offset != 0):
        raise ConfigError(f"{where}: E2E message {message.name} needs an unsigned 8-bit "
                          f"signal {crc} on a whole byte with scale 1")
    if not 0 <= max_delta <= COUNTER_MAX:
        raise ConfigError(f"{where}: {message.name}: {MAX_DELTA_ATTR} must be 0..{COUNTER_MAX}, "
                          f"got {max_delta}")
    cycle = message.cycle_time / 1000.0 if message.cycle_time else None
    return E2ESpec(message.name, data_id, ctr, crc, r.start // 8, max_delta, cycle)


class Counters:
    """The sender's alive counters, one per protected message (thread safe)."""

    def __init__(self) -> None:
        self._next: dict[str, int] = {}
        self._lock = threading.Lock()

    def take(self, message: str) -> int:
        """The counter for the next frame of ``message``: 0, 1, ... 14, 0, ..."""
        with self._lock:
            n = self._next.get(message, 0)
            self._next[message] = (n + 1) % (COUNTER_MAX + 1)
            return n


def protect(spec: E2ESpec, data: bytes) -> bytes:
    """``data`` with its CRC byte set (the counter is already encoded in it)."""
    out = bytearray(data)
    out[spec.crc_byte] = 0
    out[spec.crc_byte] = spec.crc_of(bytes(out))
    return bytes(out)


class Receiver:
    """Checks of the receiving side: CRC, alive counter and age, with counts.

    A frame passes when its CRC matches, its counter is a new one within the message's
    ``max_delta`` of the last accepted (any new value when ``max_delta`` is 0; the first frame
    of a message is accepted), and it is at most one cycle old. A frame whose counter
    jumped too far is discarded and the counter followed from it, so that one lost frame
    costs one more, not the stream; a repeated counter is discarded and not followed.
    """

    def __init__(self) -> None:
        self.last: dict[str, int] = {}
        #: discarded frames by (message, reason)
        self.discarded: Counter[tuple[str, str]] = Counter()

    def by_reason(self) -> dict[str, int]:
        out = {r: 0 for r in REASONS}
        for (_, reason), n in self.discarded.items():
            out[reason] += n
        return out

    def check(self, spec: E2ESpec, data: bytes, counter: int, age: float) -> str | None:
        """``None`` if the frame passes, else the reason (one of :data:`REASONS`), counted."""
        reason = self._reason(spec, data, counter, age)
        if reason is not None:
            self.discarded[(spec.message, reason)] += 1
        return reason

    def _reason(self, spec: E2ESpec, data: bytes, counter: int, age: float) -> str | None:
        if counter > COUNTER_MAX or data[spec.crc_byte] != spec.crc_of(data):
            return "crc"
        if age > spec.max_age + _AGE_TOLERANCE:
            return "too_old"
        last = self.last.get(spec.message)
        if last is not None:
            delta = (counter - last) % (COUNTER_MAX + 1)
            if delta == 0:
                return "repeated"
            if spec.max_delta and delta > spec.max_delta:
                self.last[spec.message] = counter  # resynchronise on the new sequence
                return "skipped"
        self.last[spec.message] = counter
        return None


__all__ = ["COUNTER_MAX", "Counters", "DATA_ID_ATTR", "E2ESpec", "MAX_DELTA_ATTR", "REASONS",
           "Receiver", "crc8_sae_j1850", "e2e_crc", "protect", "spec_of"]
