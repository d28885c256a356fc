"""Writing per-tick channel tables: CSV, Parquet or MDF4, chosen by the output's suffix.

Each format is a name -> writer entry in :data:`WRITERS`, imported lazily, so the heavy
libraries (pyarrow, asammdf) load only when their format is asked for.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cell.core.errors import ConfigError

Rows = Sequence[Sequence[Any]]


def _column(rows: Rows, i: int) -> np.ndarray:
    return np.array([np.nan if r[i] is None else float(r[i]) for r in rows], dtype=float)


def _fmt(v: Any) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    return repr(float(v))


def write_csv(path: Path, columns: list[str], rows: Rows, units: dict[str, str], note: str | None) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(columns)
        for row in rows:
            w.writerow([f"{row[0]:.6f}", *(_fmt(v) for v in row[1:])])
        if note:
            fh.write(f"# {note}\n")


def write_parquet(path: Path, columns: list[str], rows: Rows, units: dict[str, str],
                  note: str | None) -> None:
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise ConfigError("writing .parquet needs pyarrow: pip install pyarrow") from None
    arrays = [pa.array(_column(rows, i), type=pa.float64()) for i in range(len(columns))]
    meta = {f"unit:{c}": units.get(c, "") for c in columns}
    if note:
        meta["testcell:stopped"] = note
    table = pa.Table.from_arrays(arrays, names=columns).replace_schema_metadata(meta)
    pq.write_table(table, path)


def write_mdf(path: Path, columns: list[str], rows: Rows, units: dict[str, str], note: str | None) -> None:
    try:
        from asammdf import MDF, Signal
    except ImportError:
        raise ConfigError("writing .mf4 needs asammdf: pip install asammdf") from None
    t = _column(rows, 0)
    signals = [Signal(_column(rows, i), t, name=c, unit=units.get(c, ""))
               for i, c in enumerate(columns) if i > 0]
    mdf = MDF(version="4.10")
    if signals:
        mdf.append(signals, comment="testcell replay" + (f"; {note}" if note else ""))
    mdf.save(path, overwrite=True)


WRITERS: dict[str, Callable[..., None]] = {
    ".csv": write_csv,
    ".parquet": write_parquet,
    ".mf4": write_mdf,
    ".mdf": write_mdf,
}


def write_table(path: str | Path, columns: list[str], rows: Rows,
                units: dict[str, str] | None = None, note: str | None = None) -> Path:
    """Write ``rows`` (first column ``time``) to ``path``; the suffix picks the format.

    ``note`` (for example where a replay stopped) goes into the file: a trailing ``#`` line
    in CSV, schema metadata in Parquet, the data group comment in MDF4.
    """
    path = Path(path)
    writer = WRITERS.get(path.suffix.lower())
    if writer is None:
        raise ConfigError(f"--out {path}: unknown table format {path.suffix!r}; use one of "
                          f"{', '.join(WRITERS)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    writer(path, columns, rows, units or {}, note)
    return path
