"""The DBC codec: the one place where frames become channel values and back.

Every frame in the cell is defined in DBC files and encoded or decoded here through
cantools; nothing else packs bytes by hand. The catalogue is the cell's own ``dbc/*.dbc``,
and the files it is handed (those plugins register, :data:`cell.core.registry.DBC_FILES`, and
a user's own ``--dbc``), loaded into one :class:`CellDatabase`. A frame ID, message name or signal
name defined in two files is refused, naming both.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import can
import cantools
from cantools.database import EncodeError
from cantools.database.can import Database, Message

from cell.bus import e2e
from cell.core.errors import ConfigError

#: Kinds of undecodable frame, as counted in ``/health``.
DECODE_ERROR_KINDS = ("unknown_id", "bad_length", "decode_error")


def dbc_dir() -> Path:
    """Folder holding the DBC files: packaged copy first, then the repository's ``dbc/``."""
    package = Path(__file__).resolve().parents[1]  # cell/
    for candidate in (package / "_dbc", package.parent / "dbc"):
        if candidate.is_dir():
            return candidate
    raise ConfigError(f"no DBC folder found next to {package}")


def default_dbc_path() -> Path:
    return dbc_dir() / "testcell.dbc"


def resolve_dbc_paths(items: Iterable[str | Path], option: str = "--dbc") -> list[Path]:
    """Expand DBC files and folders (a folder gives its ``*.dbc``, sorted) to files.

    Parameters
    ----------
    items
        Files or folders, in order.
    option
        How the items were given, for the error text (``--dbc``, ``registered DBC``).

    Raises
    ------
    ConfigError
        A path does not exist, or a folder holds no ``.dbc`` file.
    """
    files: list[Path] = []
    for item in items:
        p = Path(item).expanduser()
        if p.is_dir():
            found = sorted(f for f in p.glob("*.dbc") if f.is_file())
            if not found:
                raise ConfigError(f"{option} {item}: folder holds no .dbc file")
            files += found
        elif p.is_file():
            files.append(p)
        else:
            raise ConfigError(f"{option} {item}: no such file or folder")
    return files


def cell_dbc_paths() -> list[Path]:
    """The cell's own DBC files: ``testcell.dbc`` first, then the rest of ``dbc/``."""
    own = default_dbc_path()
    rest = sorted(p for p in dbc_dir().glob("*.dbc") if p != own)
    return [own, *rest]


@dataclass(frozen=True)
class SignalInfo:
    """What the cell knows about one DBC signal, and the file that defines it."""

    name: str
    message: str
    frame_id: int
    unit: str
    minimum: float | None
    maximum: float | None
    cycle_time_s: float | None
    comment: str | None
    file: Path | None = None


class FrameDecodeError(ValueError):
    """A frame could not be decoded; ``kind`` is one of :data:`DECODE_ERROR_KINDS`."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


def _load_file(path: Path) -> Database:
    try:
        return cantools.database.load_file(str(path))
    except FileNotFoundError as exc:
        raise ConfigError(f"DBC file not found: {path}") from exc
    except Exception as exc:  # cantools raises several parser error types
        reason = " ".join(str(exc).split())  # one line
        raise ConfigError(f"{path}: cannot load DBC: {reason}") from exc


class CellDatabase:
    """The cell's frame catalogue: one or more DBC files loaded by cantools.

    Parameters
    ----------
    paths
        DBC files or folders, in order; ``None`` loads the cell's set
        (:func:`cell_dbc_paths`). A file named twice is loaded once.

    Raises
    ------
    ConfigError
        A file is missing or unparsable, or two files define the same frame ID, message
        name or signal name (the text names both files, the hex ID and the names).
    """

    def __init__(self, paths: Sequence[str | Path] | str | Path | None = None) -> None:
        if paths is None:
            items: list[Path] = cell_dbc_paths()
        else:
            items = resolve_dbc_paths([paths] if isinstance(paths, (str, Path)) else paths,
                                      "DBC file")
        if not items:
            raise ConfigError("no DBC file to load")
        self.files: list[Path] = []
        seen: set[Path] = set()
        for p in items:
            if p.resolve() not in seen:
                seen.add(p.resolve())
                self.files.append(p)

        self._by_id: dict[tuple[int, bool], Message] = {}
        self._by_name: dict[str, Message] = {}
        self._file_of: dict[str, Path] = {}  # message name -> file
        #: E2E-protected messages by name (:mod:`cell.bus.e2e`)
        self.e2e: dict[str, e2e.E2ESpec] = {}
        #: the alive counters of the protected messages this process sends
        self.counters = e2e.Counters()
        self.signals: dict[str, SignalInfo] = {}
        self._message_of: dict[str, Message] = {}
        databases = [(path, _load_file(path)) for path in self.files]
        for path, fdb in databases:
            self._add_file(path, fdb)
        first = databases[0][1]
        nodes = {n.name: n for _, fdb in databases for n in fdb.nodes}
        #: All files' messages in one cantools database (for ``db.db.messages``).
        self.db = Database(messages=list(self._by_name.values()), nodes=list(nodes.values()),
                           version=first.version, dbc_specifics=first.dbc)

    def _add_file(self, path: Path, fdb: Database) -> None:
        file_ids: dict[tuple[int, bool], Message] = {}
        for m in fdb.messages:
            key = (m.frame_id, m.is_extended_frame)
            other = self._by_id.get(key)
            if other is not None:
                raise ConfigError(
                    f"frame ID 0x{m.frame_id:X} is defined twice: {other.name} in "
                    f"{self._file_of[other.name]} and {m.name} in {path}")
            other = self._by_name.get(m.name)
            if other is not None:
                raise ConfigError(
                    f"message {m.name} is defined twice: 0x{other.frame_id:X} in "
                    f"{self._file_of[m.name]} and 0x{m.frame_id:X} in {path}")
            file_ids[key] = m
        for m in fdb.messages:
            cycle = m.cycle_time / 1000.0 if m.cycle_time else None
            for s in m.signals:
                info = self.signals.get(s.name)
                if info is not None and info.file == path:
                    raise ConfigError(f"{path}: signal {s.name} is defined twice")
                if info is not None:
                    raise ConfigError(
                        f"signal {s.name} is defined twice: in {info.message} "
                        f"(0x{info.frame_id:X}) of {info.file} and in {m.name} "
                        f"(0x{m.frame_id:X}) of {path}")
                self.signals[s.name] = SignalInfo(
                    name=s.name,
                    message=m.name,
                    frame_id=m.frame_id,
                    unit=s.unit or "",
                    minimum=s.minimum,
                    maximum=s.maximum,
                    cycle_time_s=cycle,
                    comment=s.comment,
                    file=path,
                )
                self._message_of[s.name] = m
            self._file_of[m.name] = path
            self._by_name[m.name] = m
            spec = e2e.spec_of(m, str(path))
            if spec is not None:
                self.e2e[m.name] = spec
        self._by_id.update(file_ids)

    # -- the catalogue ----------------------------------------------------------------
    @property
    def path(self) -> Path:
        """The first file: the cell's own ``testcell.dbc`` (for callers that name one)."""
        return self.files[0]

    @property
    def messages(self) -> list[Message]:
        """Every message of every file, in file order."""
        return list(self._by_name.values())

    @property
    def by_id(self) -> Mapping[tuple[int, bool], Message]:
        """Every message by ``(frame ID, extended)``; read only (the codec's own table)."""
        return self._by_id

    def file_of(self, message_name: str) -> Path:
        """The DBC file that defines a message."""
        self.message(message_name)  # the one place that words the error
        return self._file_of[message_name]

    def _names(self) -> str:
        return ", ".join(p.name for p in self.files)

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
            raise ConfigError(f"signal {signal!r} is not in {self._names()}") from None

    def message(self, name: str) -> Message:
        try:
            return self._by_name[name]
        except KeyError:
            raise ConfigError(f"message {name!r} is not in {self._names()}") from None

    def encode(self, message_name: str, values: dict[str, float], timestamp: float = 0.0) -> can.Message:
        """Encode physical values into a frame, clamping each to its DBC range; a NaN is
        refused (:class:`cantools.database.EncodeError`), as it has no place in a frame.

        An E2E-protected message (:mod:`cell.bus.e2e`) gets its alive counter (the next of
        this database's per-message counter, unless ``values`` gives one) and its CRC (over
        the data ID and the payload, unless ``values`` gives one: a forged frame in a test)."""
        message = self.message(message_name)
        spec = self.e2e.get(message.name)
        if spec is not None:
            values = {**values}
            if spec.counter not in values:
                values[spec.counter] = self.counters.take(message.name)
            forged_crc = spec.crc in values
            values.setdefault(spec.crc, 0)
        clamped = {}
        for s in message.signals:
            v = float(values[s.name])
            if v != v:
                raise EncodeError(f"{message.name}: signal {s.name} is NaN")
            if s.minimum is not None:
                v = max(v, float(s.minimum))
            if s.maximum is not None:
                v = min(v, float(s.maximum))
            clamped[s.name] = v
        # every value is clamped into its DBC range above, so the strict range check of
        # cantools would only repeat it
        data = message.encode(clamped, scaling=True, strict=False)
        if spec is not None and not forged_crc:
            data = e2e.protect(spec, data)
        return can.Message(
            timestamp=timestamp,
            arbitration_id=message.frame_id,
            is_extended_id=message.is_extended_frame,
            data=data,
        )

    def payload_signals(self, message: Message) -> list[str]:
        """The signals of a message a sender gives: all but its E2E counter and CRC."""
        spec = self.e2e.get(message.name)
        skip = () if spec is None else (spec.counter, spec.crc)
        return [s.name for s in message.signals if s.name not in skip]

    def messages_carrying(self, signals: set[str]) -> list[Message]:
        """DBC messages all of whose signals (but an E2E counter and CRC) are in ``signals``."""
        out = []
        for m in self._by_name.values():
            names = self.payload_signals(m)
            if names and all(n in signals for n in names):
                out.append(m)
        return out


@lru_cache(maxsize=8)
def _load(files: tuple[Path, ...]) -> CellDatabase:
    return CellDatabase(files)


def load(extra: Sequence[str | Path] = ()) -> CellDatabase:
    """The cell's catalogue plus a user's DBC files or folders, cached per set of files.

    Parameters
    ----------
    extra
        Files or folders added after the cell's own files: the files plugins registered
        (:data:`cell.core.registry.DBC_FILES`), then a user's ``--dbc``. The catalogue is
        handed them; it does not look them up.

    Raises
    ------
    ConfigError
        A ``--dbc`` path is missing or an empty folder, a file cannot be parsed, or two
        files collide.
    """
    if isinstance(extra, (str, Path)):
        extra = (extra,)
    files = [*cell_dbc_paths(), *resolve_dbc_paths(extra or ())]
    return _load(tuple(files))
