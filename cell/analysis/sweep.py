"""Q/R sweeps of the scalar Kalman filter over a CAN log (seed 004, Tables 1-2, Figures 7-8).

Seed 004 (McGurk et al. 2023, "Off-line experiment using real data") tunes the process and
measurement noise covariances Q and R of its scalar Kalman filter (eqs. 2-4, A = C = 1) by
eye: it replays logged data through the filter for every pair of a grid (Table 1, then the
finer Table 2) and compares plots against the raw signal and the 30-sample moving average
(Figures 7-8). Its conclusion asks for *quantitative* tuning against a benchmark. A log
written by the simulator carries its own answer key (``<SIGNAL>_TRUE``), so here every pair
gets numbers (:mod:`cell.analysis.scores`):

- with truth: RMSE, steady-state error std, lag after steps (to 63 %), max error;
- always: innovation whiteness (normalised autocorrelation at lags 1-10) and the mean
  normalised innovation squared (NIS).

All pairs run at once through :func:`cell.estimators.backpressure.kalman_bank`, the filter of
:class:`cell.estimators.backpressure.ScalarKalman` vectorised across pairs. The channel comes from
the log as a :class:`cell.analysis.series.Series`; the output files are written by
:mod:`cell.analysis.report`.

Grids (:func:`parse_grid`)
--------------------------
``table1``
    Table 1: Q = 10^0 ... 10^-7 for R in {1e-3, 1e-4}, then R = 10^0 ... 10^-7 for
    Q in {1e-5, 1e-6}: 32 listed pairs, 28 distinct (the four pairs
    {1e-5, 1e-6} x {1e-3, 1e-4} appear in both halves).
``table2``
    Table 2: Q = k·1e-6 and k·1e-5 (k = 1..9) for R in {1e-3, 1e-4} (36 pairs), then
    R = k·1e-3 and k·1e-4 (k = 1..9) for Q in {1e-5, 1e-6} (36 pairs): 72 listed pairs,
    68 distinct (again {1e-5, 1e-6} x {1e-3, 1e-4} appear in both halves). The extracted
    text of the R half shows its value columns as 1e-3, 1e-4, 1e-3, 1e-4 under
    Q = 1e-5, 1e-6, 1e-5, 1e-6, which read literally repeats two columns verbatim; we follow
    the pattern of the Q half (both fixed values for each decade), giving the 36 pairs
    {k·1e-3, k·1e-4} x {1e-5, 1e-6}.
``Q=SPEC,R=SPEC``
    The cross product of two value lists. ``SPEC`` is ``a:b:n`` for ``n`` **log-spaced**
    values from ``a`` to ``b`` inclusive (covariances span decades, so log spacing is the
    natural one), ``a:b:n:lin`` for linear spacing, or a comma-separated list
    ``1e-6,2e-6,5e-6``. Example: ``Q=1e-7:1e-5:9,R=1e-4:1e-3:2``.

:func:`parse_grid` returns the pairs as listed, duplicates included (so ``table2`` has
72); :func:`sweep` scores each distinct pair once, in order of first appearance.

Ranking
-------
Pairs are ranked by ``rmse`` when the log has truth, otherwise by ``ljung_box`` (then by
|log nis|).
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from cell.core.errors import ConfigError
from cell.estimators.backpressure import MAF_SAMPLES, kalman_bank, moving_average, steady_state_gain
from cell.analysis.report import format_ranked, json_lines, plot_png, write_csv, write_jsonl
from cell.analysis.scores import (
    ALWAYS_KEYS,
    STEADY_TOL,
    STEADY_WINDOW_S,
    STEP_MIN,
    TRUTH_KEYS,
    innovation_scores,
    score_estimates,
)
from cell.analysis.series import Series, add_log_options, load_series

#: Largest grid accepted (pairs).
MAX_PAIRS = 100_000

Pair = tuple[float, float]


# -- grids ----------------------------------------------------------------------------------
def _decade(k: int, exp: int) -> float:
    """``k`` x 10^``exp`` as the float the literal ``ke{exp}`` parses to (exact decimals)."""
    return float(f"{k}e{exp}")


def table1() -> list[Pair]:
    """Seed 004, Table 1, as listed: 32 pairs (28 distinct)."""
    decades = [_decade(1, -e) for e in range(8)]  # 10^0 ... 10^-7
    pairs = [(q, r) for r in (1e-3, 1e-4) for q in decades]
    pairs += [(q, r) for q in (1e-5, 1e-6) for r in decades]
    return pairs


def table2() -> list[Pair]:
    """Seed 004, Table 2, as listed: 72 pairs (68 distinct); see the module notes."""
    pairs = []
    for exp in (-6, -5):  # Q half: columns (R=1e-3, R=1e-4) for k·1e-6, then for k·1e-5
        for r in (1e-3, 1e-4):
            pairs += [(_decade(k, exp), r) for k in range(1, 10)]
    for exp in (-3, -4):  # R half: columns (Q=1e-5, Q=1e-6) for k·1e-3, then for k·1e-4
        for q in (1e-5, 1e-6):
            pairs += [(q, _decade(k, exp)) for k in range(1, 10)]
    return pairs


NAMED_GRIDS = {"table1": table1, "table2": table2}

_NUMBER = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"


def _grid_error(text: str, pos: int, message: str) -> ConfigError:
    return ConfigError(
        f"--grid {text!r}: at position {pos + 1}: {message}\n  {text}\n  {' ' * pos}^"
    )


def _number(text: str, token: str, pos: int, what: str) -> float:
    if not re.fullmatch(_NUMBER, token.strip()):
        raise _grid_error(text, pos, f"{what} {token.strip()!r} is not a number")
    v = float(token)
    if not math.isfinite(v) or v <= 0:
        raise _grid_error(text, pos, f"{what} must be a number > 0, got {token.strip()}")
    return v


def _range(text: str, token: str, pos: int, key: str) -> list[float]:
    parts = token.split(":")
    if len(parts) not in (3, 4) or (len(parts) == 4 and parts[3].strip().lower() != "lin"):
        raise _grid_error(
            text, pos, f"{key} range {token.strip()!r}: use a:b:n (log-spaced) or a:b:n:lin"
        )
    offsets = np.cumsum([0] + [len(p) + 1 for p in parts[:-1]])
    a = _number(text, parts[0], pos + int(offsets[0]), f"{key} start")
    b = _number(text, parts[1], pos + int(offsets[1]), f"{key} end")
    n_text = parts[2].strip()
    if not n_text.isdigit() or int(n_text) < 1:
        raise _grid_error(
            text, pos + int(offsets[2]), f"{key} count {n_text!r} must be a whole number >= 1"
        )
    n = int(n_text)
    if n == 1 and a != b:
        raise _grid_error(text, pos + int(offsets[2]), f"{key}: one value cannot span {a:g}..{b:g}")
    if n > MAX_PAIRS:
        raise _grid_error(text, pos + int(offsets[2]), f"{key}: at most {MAX_PAIRS} values")
    if len(parts) == 4:
        return [float(v) for v in np.linspace(a, b, n)]
    return [float(v) for v in np.geomspace(a, b, n)]


def parse_grid(text: str) -> list[Pair]:
    """Parse a ``--grid``: ``table1``, ``table2`` or ``Q=SPEC,R=SPEC`` (see the module notes).

    Parameters
    ----------
    text:
        The grid text.

    Returns
    -------
    list of (Q, R)
        The pairs as listed, duplicates kept (``table2`` gives 72, seed 004 Table 2).

    Raises
    ------
    ConfigError
        Naming the grid text and the 1-based position of what is wrong.
    """
    if not isinstance(text, str) or not text.strip():
        raise ConfigError("--grid is empty; use table1, table2 or Q=a:b:n,R=a:b:n")
    name = text.strip().lower()
    if name in NAMED_GRIDS:
        return NAMED_GRIDS[name]()
    values: dict[str, list[float]] = {}
    key: str | None = None
    pos = 0
    for token in text.replace(";", ",").split(","):
        start = pos
        pos += len(token) + 1
        lead = len(token) - len(token.lstrip())
        if not token.strip():
            raise _grid_error(text, start, "empty value")
        if "=" in token:
            k, _, spec = token.partition("=")
            k = k.strip().upper()
            if k not in ("Q", "R"):
                raise _grid_error(
                    text, start + lead,
                    f"unknown name {token.partition('=')[0].strip()!r}; "
                    "use Q=... and R=..., or table1/table2",
                )
            if k in values:
                raise _grid_error(text, start + lead, f"{k} is given twice")
            key = k
            values[k] = []
            spec_pos = start + len(token.partition("=")[0]) + 1
        else:
            if key is None:
                raise _grid_error(
                    text, start + lead,
                    f"{token.strip()!r} is not a grid; use table1, table2 or Q=a:b:n,R=a:b:n",
                )
            spec = token
            spec_pos = start
        if not spec.strip():
            raise _grid_error(text, spec_pos, f"{key} has no value")
        if ":" in spec:
            values[key] += _range(text, spec, spec_pos, key)
        else:
            values[key].append(_number(text, spec, spec_pos, key))
    for k in ("Q", "R"):
        if k not in values:
            raise _grid_error(text, len(text), f"{k} is missing; give both Q=... and R=...")
    if len(values["Q"]) * len(values["R"]) > MAX_PAIRS:
        raise _grid_error(text, 0, f"{len(values['Q']) * len(values['R'])} pairs; "
                                   f"at most {MAX_PAIRS}")
    return [(q, r) for q in values["Q"] for r in values["R"]]


def unique_pairs(pairs: Iterable[Pair]) -> list[Pair]:
    """Distinct pairs, in order of first appearance (Table 2: 72 listed -> 68)."""
    seen: dict[Pair, None] = {}
    for q, r in pairs:
        seen.setdefault((float(q), float(r)), None)
    return list(seen)


def _clean(v: Any) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def sweep(
    series: Series,
    pairs: Iterable[Pair],
    P0: float = 1.0,
    steady_tol: float = STEADY_TOL,
    steady_window_s: float = STEADY_WINDOW_S,
    step_min: float = STEP_MIN,
) -> list[dict[str, Any]]:
    """Run every distinct (Q, R) pair over ``series`` at once and rank them.

    Parameters
    ----------
    series:
        From :func:`cell.analysis.series.channel_series` (or :meth:`Series.from_arrays`).
    pairs:
        (Q, R) pairs, e.g. from :func:`parse_grid`; duplicates are scored once.
    P0:
        Initial covariance, as the runtime's filter (seed 004: 1).
    steady_tol, steady_window_s, step_min:
        Steady-state and step detection in the truth (:mod:`cell.analysis.scores`).

    Returns
    -------
    list of dict
        One per distinct pair, best first, with ``rank``, ``Q``, ``R``, ``gain`` (the
        steady-state gain), ``rmse``, ``ss_std``, ``lag_s``, ``max_err`` (only when the
        series has truth), ``whiteness``, ``ljung_box`` and ``nis``. Non-finite scores are
        ``None``. Ranked by ``rmse`` with truth, else by ``ljung_box`` then |log nis|.
    """
    uniq = unique_pairs(pairs)
    if not uniq:
        raise ConfigError("the grid has no pairs")
    if series.valid < 2:
        raise ConfigError(
            f"{series.channel}: {series.valid} valid samples in {series.source}; need at least 2"
        )
    q = np.array([p[0] for p in uniq])
    r = np.array([p[1] for p in uniq])
    x, e, S = kalman_bank(series.y, q, r, P0)
    scores = innovation_scores(e, S)
    scores.update(score_estimates(series, x, steady_tol, steady_window_s, step_min))
    gain = steady_state_gain(q, r)
    rows = []
    for i, (qq, rr) in enumerate(uniq):
        row: dict[str, Any] = {"Q": qq, "R": rr, "gain": float(gain[i])}
        for key in (*TRUTH_KEYS, *ALWAYS_KEYS):
            if key in scores:
                row[key] = _clean(scores[key][i])
        rows.append(row)
    return rank(rows, by_truth=series.truth is not None)


def rank(rows: Iterable[dict[str, Any]], by_truth: bool) -> list[dict[str, Any]]:
    """Rows sorted best first, each with ``rank`` (1 = best) as its first key.

    By ``rmse`` when ``by_truth``, else by ``ljung_box`` then |log nis|; a missing score
    ranks last.
    """

    def key_fn(row: dict[str, Any]) -> tuple:
        if by_truth:
            v = row["rmse"]
            return (v is None, v if v is not None else 0.0)
        lb, nis = row["ljung_box"], row["nis"]
        return (lb is None, lb if lb is not None else 0.0,
                abs(math.log(nis)) if nis else math.inf)

    ordered = sorted(rows, key=key_fn)
    return [{"rank": i, **{k: v for k, v in row.items() if k != "rank"}}
            for i, row in enumerate(ordered, 1)]


def references(series: Series, **kw: Any) -> list[dict[str, Any]]:
    """Truth scores of the raw signal and the 30-sample moving average, for comparison."""
    if series.truth is None:
        return []
    out = []
    for name, est in (("raw", series.y), (f"MAF-{MAF_SAMPLES}", moving_average(series.y))):
        s = score_estimates(series, est, **kw)
        out.append({"filter": name, **{k: _clean(s[k][0]) for k in TRUTH_KEYS}})
    return out


# -- command line ---------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``testcell sweep`` options to ``parser``."""
    parser.add_argument("log", help="CAN log: candump -L .log, .asc, .blf, .trc or python-can .csv")
    parser.add_argument("--channel", default="EXH_BP_R", help="channel to filter (default EXH_BP_R)")
    parser.add_argument(
        "--grid", default="table2",
        help="table1, table2 (seed 004 Tables 1-2) or Q=a:b:n,R=a:b:n (n log-spaced values; "
             "a:b:n:lin for linear; or a list Q=1e-6,2e-6,R=1e-4) (default table2)",
    )
    parser.add_argument("--truth", default=None,
                        help="truth channel (default <channel>_TRUE when the log has it)")
    parser.add_argument("--no-truth", action="store_true", help="ignore truth in the log")
    parser.add_argument("--out-dir", default=None, type=Path,
                        help="write sweep_<channel>.csv, .jsonl and .png into this folder and "
                             "print their paths (default: write no file)")
    parser.add_argument("--json", action="store_true",
                        help="print JSON Lines (one JSON object per pair, per line) instead of "
                             "the table")
    parser.add_argument("--top", type=int, default=10, help="rows printed (default 10)")
    parser.add_argument("--plot-top", type=int, default=3, help="pairs plotted (default 3)")
    parser.add_argument("--no-plot", action="store_true", help="do not write the PNG")
    add_log_options(parser)


def main(args: argparse.Namespace) -> int:
    """Run ``testcell sweep``; return the exit code.

    Raises :class:`ConfigError` for bad options, a missing channel or a bad grid, and
    :class:`LogFormatError` (with the line number) for a malformed log.
    """
    if args.top < 0 or args.plot_top < 0:
        raise ConfigError("--top and --plot-top must be >= 0")
    pairs = parse_grid(args.grid)  # fail on a bad grid before reading the log
    series = load_series(args)
    ranked = sweep(series, pairs)
    written = []
    if args.out_dir is not None:
        out_dir = Path(args.out_dir)
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"--out-dir {out_dir}: {exc.strerror or exc}") from None
        stem = f"sweep_{series.channel}"
        written = [write_csv(out_dir / f"{stem}.csv", ranked),
                   write_jsonl(out_dir / f"{stem}.jsonl", ranked)]
        if not args.no_plot:
            written.append(plot_png(out_dir / f"{stem}.png", series, ranked, top=args.plot_top))
    distinct = len(ranked)
    head = (f"{series.source}: {series.channel}, {series.n} ticks at {series.rate_hz:g} Hz "
            f"({series.valid} valid), truth {series.truth_channel or 'none'}; "
            f"{len(pairs)} pairs listed, {distinct} distinct; ranked by "
            f"{'rmse' if series.truth is not None else 'ljung_box'}")
    if args.json:
        for line in json_lines(ranked):
            print(line)
        print(head, file=sys.stderr)
    else:
        print(head)
        print(format_ranked(ranked, args.top, references(series)))
    for path in written:
        print(f"wrote {path}", file=sys.stderr)
    return 0


__all__ = [
    "MAX_PAIRS",
    "NAMED_GRIDS",
    "add_arguments",
    "main",
    "parse_grid",
    "rank",
    "references",
    "sweep",
    "table1",
    "table2",
    "unique_pairs",
]
