"""Offline replay: the live runtime run over a recorded CAN log, one CSV row per MED tick."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cell.bus.logs import read_log
from cell.bus.signal_tables import write_table
from cell.core.errors import ConfigError, LogFormatError
from cell.runtime.feed import feed
from cell.runtime.scheduler import MAX_UNKNOWN_IDS, Runtime

@dataclass
class ReplayResult:
    rows: list[list[Any]] = field(default_factory=list)
    columns: list[str] = field(default_factory=list)
    frames: int = 0
    decoded: int = 0
    """Frames that decoded into channels (the rest: unknown IDs, bad lengths, ...)."""
    unknown_ids: dict[str, int] = field(default_factory=dict)
    """Frame IDs of the log that no DBC file defines -> frames (most frequent first)."""
    bad: dict[str, int] = field(default_factory=dict)
    """Frames that did not decode, by kind."""
    error: LogFormatError | None = None

    def summary(self) -> str:
        """One line: frames read, decoded, and the IDs no DBC file defines."""
        text = f"{self.frames} frames, {self.decoded} decoded"
        other = {k: n for k, n in self.bad.items() if n and k != "unknown_id"}
        if other:
            text += " (" + ", ".join(f"{n} {k.replace('_', ' ')}" for k, n in other.items()) + ")"
        if self.unknown_ids:
            n = sum(self.unknown_ids.values())
            ids = ", ".join(f"{i} ({c})" for i, c in list(self.unknown_ids.items())[:12])
            more = len(self.unknown_ids) - 12
            text += (f"; {self.bad.get('unknown_id', n)} with IDs in no DBC file: {ids}"
                     + (f" and {more} more" if more > 0 else ""))
        return text


class NothingDecoded(ConfigError):
    """No frame of a log decodes with the DBC files given (a foreign log)."""


def replay(
    runtime: Runtime,
    log: str | Path,
    out: str | Path | None = None,
    channels: list[str] | None = None,
    progress: bool | None = None,
) -> ReplayResult:
    """Run ``runtime`` over ``log`` and write one row per MED tick to ``out``.

    The first column is ``time`` (bus time, s); then one column per channel. A stale or
    invalid value is written empty (NaN). ``out``'s suffix picks CSV, Parquet or MDF4. If the
    log has a malformed line, the rows up to it are still written, the file says where the
    replay stopped, and the error is returned in the result.
    """
    result = ReplayResult()
    snapshots: list[tuple[float, dict[str, float | None]]] = []

    def on_tick(t: float) -> None:
        row = {}
        for name, ch in runtime.channels.items():
            status, _ = ch.status_at(t)
            row[name] = ch.value if status == "ok" else None
        snapshots.append((t, row))

    result.error = feed(runtime, read_log(log, progress=progress), on_tick).error
    result.frames = runtime.frames
    result.bad = {k: n for k, n in runtime.decode_errors.items() if n}
    result.decoded = runtime.frames - sum(result.bad.values())
    result.unknown_ids = runtime.unknown_id_counts(top=MAX_UNKNOWN_IDS)
    if result.frames == 0 and result.error is None:
        raise NothingDecoded(f"{log}: the log holds no frame")
    if result.frames and result.decoded == 0:
        raise NothingDecoded(
            f"{log}: no frame decodes with the DBC files ({result.summary()}); add the DBC "
            "that defines them with --dbc")

    seen = {name for _, row in snapshots for name, v in row.items() if v is not None}
    if channels:
        unknown = [c for c in channels if c not in seen]
        if unknown:
            raise ConfigError(
                f"--channels: no value for {', '.join(unknown)} in this replay; channels "
                f"computed: {', '.join(sorted(seen)) or 'none'}"
            )
        names = list(channels)
    else:
        names = sorted(seen)
    result.columns = ["time", *names]
    result.rows = [[t, *(row.get(n) for n in names)] for t, row in snapshots]
    if out is not None:
        units = {"time": "s", **{n: runtime.channels[n].unit for n in names}}
        note = f"stopped at {result.error}" if result.error else None
        write_table(out, result.columns, result.rows, units, note)
    return result
