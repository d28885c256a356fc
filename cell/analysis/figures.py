"""Figures and tables shared by the experiments, the design tools and ``replay --plot``.

Figures: :func:`pyplot` is matplotlib's pyplot on the Agg backend (PNG files, no display);
:func:`save` lays a figure out, writes it and closes it; :func:`output_folder` makes the
folder the files go in; :func:`plot_channels` draws channels of a signal table over bus time.

Tables: :func:`format_table` lines cells up in columns, :func:`format_value` writes one
cell (``None`` as a dash), :func:`write_csv` writes rows of dicts as CSV.
"""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cell.core.errors import ConfigError

Rows = list[list[Any]]


# -- figures ----------------------------------------------------------------------------------
def pyplot():
    """matplotlib.pyplot on the Agg backend (PNG files, no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: str | Path, dpi: int = 110) -> Path:
    """Write ``fig`` as a PNG at ``path`` (its folder made) and close it.

    A figure made without a layout engine of its own (``layout="constrained"``) gets
    ``tight_layout`` first.
    """
    if fig.get_layout_engine() is None:
        fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return path


def output_folder(path: str | Path, option: str = "--out") -> Path:
    """The folder for a command's figures and files, made if need be; a folder that cannot
    be made is a :class:`ConfigError` naming ``option``."""
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{option} {out}: cannot create the folder: {exc.strerror or exc}"
                          ) from None
    return out


def _column(rows: Rows, i: int) -> np.ndarray:
    return np.array([np.nan if r[i] is None else float(r[i]) for r in rows], dtype=float)


def plot_channels(path: str | Path, columns: list[str], rows: Rows, channels: list[str],
                  title: str = "", units: Mapping[str, str | None] | None = None) -> Path:
    """A PNG of the given channels over time since the first row, one panel per unit, each
    y axis labelled with its unit (``units``: channel -> unit; a channel not in it, or
    with no unit, goes on the panel "(no unit)")."""
    plt = pyplot()
    t = _column(rows, 0)
    t = t - t[0] if t.size else t
    units = units or {}
    present = [n for n in channels if n in columns]
    by_unit: dict[str, list[str]] = {}
    for name in present:
        by_unit.setdefault(units.get(name) or "", []).append(name)
    groups = list(by_unit.items()) or [("", [])]
    fig, axes = plt.subplots(len(groups), 1, figsize=(11, 1.2 + 3.3 * len(groups)), sharex=True,
                             squeeze=False)
    for ax, (unit, names) in zip(axes[:, 0], groups):
        for name in names:
            y = _column(rows, columns.index(name))
            style = dict(lw=0.6, alpha=0.5) if name.endswith(("_L", "_R")) else dict(lw=1.4)
            ax.plot(t, y, label=name, **style)
        ax.set_ylabel(unit or "(no unit)")
        ax.grid(alpha=0.3)
        if names:
            ax.legend(loc="best", fontsize=8)
    axes[0, 0].set_title(title)
    axes[-1, 0].set_xlabel("time since the first row [s]")
    return save(fig, path, dpi=120)


# -- tables -----------------------------------------------------------------------------------
def format_value(v: Any, spec: str = ".1f", missing: str = "-") -> str:
    """One cell: ``None`` as ``missing``, a bool as yes/no, a float by ``spec``."""
    if v is None:
        return missing
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return format(v, spec)
    return str(v)


def format_table(rows: Sequence[Sequence[Any]], columns: Sequence[str] | None = None, *,
                 widths: Sequence[int] | None = None, align: str | None = None,
                 sep: str = "  ") -> str:
    """Rows of cells as lines of text, each column under its header.

    ``columns`` is the header row (none: no header). Each cell is ``str()``-ed and aligned in
    its column by ``align``, one character per column, ``">"`` (right, the default) or
    ``"<"`` (left); the columns are joined by ``sep``. ``widths`` are the columns' widths
    (default: the widest cell of each); a wider cell overflows its column, as in an f-string.
    """
    cells = ([list(map(str, columns))] if columns is not None else []) + \
        [[str(c) for c in row] for row in rows]
    if not cells:
        return ""
    n = len(cells[0])
    if widths is None:
        widths = [max(len(row[i]) for row in cells) for i in range(n)]
    align = align or ">" * n
    return "\n".join(sep.join(format(c, f"{a}{w}") for c, a, w in zip(row, align, widths, strict=True))
                     for row in cells)


def write_csv(path: str | Path, rows: Sequence[Mapping[str, Any]]) -> Path:
    """Rows of dicts as CSV, the first row's keys as the header."""
    path = Path(path)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return path
