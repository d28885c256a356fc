"""The DBC codec: the one place where frames become channel values and back.

Every frame in the cell is defined in ``dbc/*.dbc`` and encoded or decoded here through
cantools; nothing else packs bytes by hand.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import can
import cantools
from cantools.database.can import Database, Message

from .errors import ConfigError

#: Kinds of undecodable frame, as counted in ``/health``.
DECODE_ERROR_KINDS = ("unknown_id", "bad_length", "decode_error")


def dbc_dir() -> Path:
    """Folder holding the DBC files: packaged copy first, then the repository's ``dbc/``."""
    here = Path(__file__).resolve().parent
    for candidate in (here / "_dbc", here.parent / "dbc"):
        if candidate.is_dir():
            return candidate
    raise ConfigError(f"no DBC folder found next to {here}")


def default_dbc_path() -> Path:
    return dbc_dir() / "testcell.dbc"


@dataclass(frozen=True)
class SignalInfo:
    """What the cell knows about one DBC signal."""

    name: str
    message: str
    frame_id: int
    unit: str
    minimum: float | None
    maximum: float | None
    cycle_time_s: float | None
    comment: str | None


class FrameDecodeError(ValueError):
    """A frame could not be decoded; ``kind`` is one of :data:`DECODE_ERROR_KINDS`."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


class CellDatabase:
    """The cell's frame catalogue, loaded from a DBC file by cantools."""

    def __init__(self, path: str | Path | None = None) -> None:
        self.path = Path(path) if path else default_dbc_path()
        try:
            self.db: Database = cantools.database.load_file(str(self.path))
        except FileNotFoundError as exc:
            raise ConfigError(f"DBC file not found: {self.path}") from exc
        except Exception as exc:  # cantools raises several parser error types
            raise ConfigError(f"{self.path}: cannot load DBC: {exc}") from exc
        self._by_id: dict[tuple[int, bool], Message] = {
            (m.frame_id, m.is_extended_frame): m for m in self.db.messages
        }
        self.signals: dict[str, SignalInfo] = {}
        self._message_of: dict[str, Message] = {}
        for m in self.db.messages:
            cycle = m.cycle_time / 1000.0 if m.cycle_time else None
            for s in m.signals:
                if s.name in self.signals:
                    raise ConfigError(f"{self.path}: signal {s.name} is defined twice")
                self.signals[s.name] = SignalInfo(
                    name=s.name,
                    message=m.name,
                    frame_id=m.frame_id,
                    unit=s.unit or "",
                    minimum=s.minimum,
                    maximum=s.maximum,
                    cycle_time_s=cycle,
                    comment=s.comment,
                )
                self._message_of[s.name] = m

    # -- decoding -----------------------------------------------------------------
    def check(self, msg: can.Message) -> Message:
        """The DBC message of a frame; raises :class:`FrameDecodeError` (``unknown_id`` or
        ``bad_length``) when the frame is not one the DBC describes."""
        message = self._by_id.get((msg.arbitration_id, bool(msg.is_extended_id)))
        if message is None:
            raise FrameDecodeError("unknown_id", f"frame id 0x{msg.arbitration_id:X} is not in the DBC")
        if len(msg.data) != message.length:
            raise FrameDecodeError(
                "bad_length",
                f"{message.name} (0x{msg.arbitration_id:X}) has {len(msg.data)} data bytes, "
                f"the DBC says {message.length}",
            )
        return message

    def decode_payload(self, message: Message, data: bytes) -> dict[str, float]:
        """Physical values of a checked frame's data; ``decode_error`` if cantools refuses it."""
        try:
            values = message.decode(data, decode_choices=False, scaling=True)
        except Exception as exc:
            raise FrameDecodeError("decode_error", f"{message.name}: {exc}") from exc
        return {k: float(v) for k, v in values.items()}

    def decode(self, msg: can.Message) -> tuple[Message, dict[str, float]]:
        """Decode one frame to ``{signal: physical value}``.

        Raises :class:`FrameDecodeError` with kind ``unknown_id`` (not in the DBC),
        ``bad_length`` (data length differs from the DBC's) or ``decode_error``.
        """
        message = self.check(msg)
        return message, self.decode_payload(message, bytes(msg.data))

    # -- encoding -----------------------------------------------------------------
    def message_for(self, signal: str) -> Message:
        try:
            return self._message_of[signal]
        except KeyError:
            raise ConfigError(f"signal {signal!r} is not in {self.path.name}") from None

    def message(self, name: str) -> Message:
        try:
            return self.db.get_message_by_name(name)
        except KeyError:
            raise ConfigError(f"message {name!r} is not in {self.path.name}") from None

    def encode(self, message_name: str, values: dict[str, float], timestamp: float = 0.0) -> can.Message:
        """Encode physical values into a frame, clamping each to its DBC range."""
        message = self.message(message_name)
        clamped = {}
        for s in message.signals:
            v = float(values[s.name])
            if s.minimum is not None:
                v = max(v, float(s.minimum))
            if s.maximum is not None:
                v = min(v, float(s.maximum))
            clamped[s.name] = v
        data = message.encode(clamped, scaling=True, strict=True)
        return can.Message(
            timestamp=timestamp,
            arbitration_id=message.frame_id,
            is_extended_id=message.is_extended_frame,
            data=data,
        )

    def messages_carrying(self, signals: set[str]) -> list[Message]:
        """DBC messages all of whose signals are in ``signals``."""
        return [m for m in self.db.messages if m.signals and all(s.name in signals for s in m.signals)]


@lru_cache(maxsize=4)
def load(path: str | None = None) -> CellDatabase:
    """Load (and cache) a DBC file; ``None`` gives the cell's own ``testcell.dbc``."""
    return CellDatabase(path)
