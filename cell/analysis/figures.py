"""Figures and tables shared by the experiments, the design tools and ``replay --plot``.

:func:`pyplot` is matplotlib's pyplot on the Agg backend (PNG files, no display);
:func:`plot_channels` draws channels of a signal table over bus time.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

Rows = list[list[Any]]


def pyplot():
    """matplotlib.pyplot on the Agg backend (PNG files, no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _column(rows: Rows, i: int) -> np.ndarray:
    return np.array([np.nan if r[i] is None else float(r[i]) for r in rows], dtype=float)


def plot_channels(path: str | Path, columns: list[str], rows: Rows, channels: list[str],
                  title: str = "") -> Path:
    """A PNG of the given channels over bus time, one panel per unit."""
    plt = pyplot()
    t = _column(rows, 0)
    t = t - t[0] if t.size else t
    fig, ax = plt.subplots(figsize=(11, 4.5))
    for name in channels:
        if name in columns:
            y = _column(rows, columns.index(name))
            style = dict(lw=0.6, alpha=0.5) if name.endswith(("_L", "_R")) else dict(lw=1.4)
            ax.plot(t, y, label=name, **style)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("mmH2O")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
