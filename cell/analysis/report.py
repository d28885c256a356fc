"""The output files of a Q/R sweep: CSV, JSON lines, a PNG like seed 004's Figures 7-8, and
the ranked table as text.

Rows are the ranked dicts of :func:`cell.analysis.sweep.sweep`: ``rank``, ``Q``, ``R``,
``gain``, the truth scores when the series has truth, and the innovation scores
(:mod:`cell.analysis.scores`); a missing score is ``None``.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from cell.analysis.figures import format_table, pyplot, save
from cell.estimators.backpressure import MAF_SAMPLES, kalman_bank, moving_average
from cell.analysis.scores import ALWAYS_KEYS, STEP_MIN, TRUTH_KEYS, Step, find_steps, steady_mask
from cell.analysis.series import Series


def _columns(ranked: Sequence[dict[str, Any]]) -> list[str]:
    cols = ["rank", "Q", "R", "gain"]
    if ranked and "rmse" in ranked[0]:
        cols += list(TRUTH_KEYS)
    return cols + list(ALWAYS_KEYS)


def write_csv(path: str | Path, ranked: Sequence[dict[str, Any]]) -> Path:
    """Write the ranked table as CSV (empty cells for missing scores)."""
    path = Path(path)
    cols = _columns(ranked)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for row in ranked:
            w.writerow(["" if row.get(c) is None else (repr(row[c]) if isinstance(row[c], float)
                                                        else row[c]) for c in cols])
    return path


def json_lines(ranked: Sequence[dict[str, Any]]) -> list[str]:
    """One JSON object per pair (``Q``, ``R``, the scores; ``null`` for a missing score)."""
    return [json.dumps(row, allow_nan=False) for row in ranked]


def write_jsonl(path: str | Path, ranked: Sequence[dict[str, Any]]) -> Path:
    """Write :func:`json_lines` to ``path``, one line per pair."""
    path = Path(path)
    path.write_text("".join(line + "\n" for line in json_lines(ranked)))
    return path


def _zoom(series: Series, steps: list[Step]) -> tuple[float, float]:
    t = series.t
    if steps:
        st = steps[0]
        t0 = t[st.start] - 5.0
        return t0, t0 + 30.0
    return float(t[0]), float(t[0]) + min(30.0, float(t[-1] - t[0]))


def plot_png(
    path: str | Path, series: Series, ranked: Sequence[dict[str, Any]], top: int = 3,
    P0: float = 1.0,
) -> Path:
    """Plot the raw signal, the 30-sample moving average and the ``top`` best pairs.

    Pairs whose steady-state gain is within 1 % of one already drawn are skipped (Table 2
    has several pairs with the same Q/R), so ``top`` distinct filters are shown.

    Like seed 004's Figures 7-8: the whole series on top, a 30 s zoom around the first step
    found in the truth (or the start) below; the truth in black when the log has it.
    """
    plt = pyplot()
    path = Path(path)
    best: list[dict[str, Any]] = []
    for row in ranked:  # pairs with (nearly) the same gain draw the same line: plot one
        if len(best) >= max(int(top), 0):
            break
        if all(abs(row["gain"] - b["gain"]) > 0.01 * b["gain"] for b in best):
            best.append(row)
    x = None
    if best:
        x, _, _ = kalman_bank(series.y, [r["Q"] for r in best], [r["R"] for r in best], P0)
    maf = moving_average(series.y)
    steps: list[Step] = []
    if series.truth is not None:
        steps = find_steps(series.t, series.truth,
                           steady_mask(series.truth, series.rate_hz), STEP_MIN)
    fig, axes = plt.subplots(2, 1, figsize=(11, 7.5))
    z0, z1 = _zoom(series, steps)
    for ax, zoom in zip(axes, (False, True), strict=True):
        sel = (series.t >= z0) & (series.t <= z1) if zoom else slice(None)
        t = series.t[sel]
        ax.plot(t, series.y[sel], color="0.75", lw=0.6, label=f"{series.channel} (raw)")
        ax.plot(t, maf[sel], color="tab:orange", lw=1.3, label=f"moving average, {MAF_SAMPLES}")
        if series.truth is not None:
            ax.plot(t, series.truth[sel], color="k", lw=1.0, ls="--", label=series.truth_channel)
        if x is not None:
            for i, row in enumerate(best):
                lbl = f"Kalman Q={row['Q']:.3g}, R={row['R']:.3g}"
                if row.get("rmse") is not None:
                    lbl += f" (RMSE {row['rmse']:.1f})"
                # Kalman pairs in blues/greens/purples, never the moving average's orange
                ax.plot(t, x[sel, i], lw=1.2, label=lbl,
                        color=("tab:blue", "tab:green", "tab:purple", "tab:cyan", "tab:olive")[i % 5])
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"{series.channel} [{series.unit or 'no unit'}]")
        ax.grid(alpha=0.3)
    axes[0].set_title(f"{Path(series.source).name}: best {len(best)} Q/R pairs "
                      "(seed 004, Figures 7-8)")
    axes[1].set_title(f"zoom {z0:.0f}-{z1:.0f} s")
    axes[0].legend(fontsize=8, loc="best")
    return save(fig, path)


def format_ranked(ranked: Sequence[dict[str, Any]], top: int | None = None,
                  refs: Sequence[dict[str, Any]] = ()) -> str:
    """The ranked table as text (``top`` rows), with reference filters below it."""
    cols = _columns(ranked)
    rows = list(ranked if top is None else ranked[:top])

    def fmt(c: str, v: Any) -> str:
        if v is None:
            return "-"
        if c == "rank":
            return str(v)
        if c in ("Q", "R", "gain", "nis", "whiteness"):
            return f"{v:.3g}"
        return f"{v:.2f}"

    lines = [format_table([[fmt(c, r.get(c)) for c in cols] for r in rows], cols)]
    for ref in refs:
        vals = "  ".join(f"{k}={fmt(k, ref.get(k))}" for k in TRUTH_KEYS)
        lines.append(f"reference {ref['filter']}: {vals}")
    return "\n".join(lines)


__all__ = ["format_ranked", "json_lines", "plot_png", "write_csv", "write_jsonl"]
