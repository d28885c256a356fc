"""Reading recorded CAN logs: candump ``-L`` ``.log``, ``.asc``, ``.csv``, ``.trc`` and ``.blf``.

Text formats are read line by line, so a malformed line is refused with its line number
(:class:`~cell.core.errors.LogFormatError`); a progress bar follows the bytes read.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
from tqdm import tqdm

from cell.core.errors import ConfigError, LogFormatError

#: python-can readers by suffix; text formats are read line by line so errors carry a line.
TEXT_READERS = {
    ".log": can.CanutilsLogReader,
    ".asc": can.ASCReader,
    ".csv": can.CSVReader,
    ".trc": can.TRCReader,
}


class _CountingLines:
    """A text file that counts the lines and bytes handed out, for error positions and progress."""

    def __init__(self, fh: Any, progress: tqdm | None) -> None:
        self._fh = fh
        self.line = 0
        self._progress = progress

    def __iter__(self) -> Iterator[str]:
        for line in self._fh:
            self.line += 1
            if self._progress is not None:
                self._progress.update(len(line))
            yield line

    def readline(self) -> str:
        line = self._fh.readline()
        if line:
            self.line += 1
        return line

    def __getattr__(self, name: str) -> Any:
        return getattr(self._fh, name)


def read_log(path: str | Path, progress: bool | None = None) -> Iterator[can.Message]:
    """Yield the frames of a CAN log; a malformed line raises :class:`LogFormatError`."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"log file not found: {path}")
    reader_cls = TEXT_READERS.get(path.suffix.lower())
    size = os.path.getsize(path)
    bar = tqdm(total=size, unit="B", unit_scale=True, desc=path.name, disable=progress is False
               if progress is not None else None, leave=False)
    try:
        if reader_cls is None:
            try:
                reader = can.LogReader(str(path))
            except ValueError as exc:
                known = ", ".join(sorted({*TEXT_READERS, ".blf"}))
                raise ConfigError(f"{path}: unknown log format; use one of {known}") from exc
            for msg in reader:
                yield msg
            return
        with open(path, encoding="utf-8", errors="replace") as fh:
            lines = _CountingLines(fh, bar)
            reader = reader_cls(lines)
            it = iter(reader)
            while True:
                try:
                    msg = next(it)
                except StopIteration:
                    return
                except (ValueError, IndexError, TypeError) as exc:
                    raise LogFormatError(str(path), lines.line, f"malformed frame: {exc}") from exc
                yield msg
    finally:
        bar.close()
