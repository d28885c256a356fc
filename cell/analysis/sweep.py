"""Q/R sweeps of the scalar Kalman filter over a CAN log (seed 004, Tables 1-2, Figures 7-8).

Seed 004 (McGurk et al. 2023, "Off-line experiment using real data") tunes the process and
measurement noise covariances Q and R of its scalar Kalman filter (eqs. 2-4, A = C = 1) by
eye: it replays logged data through the filter for every pair of a grid (Table 1, then the
finer Table 2) and compares plots against the raw signal and the 30-sample moving average
(Figures 7-8). Its conclusion asks for *quantitative* tuning against a benchmark. A log
written by the simulator carries its own answer key (``<SIGNAL>_TRUE``), so here every pair
gets numbers:

- with truth: RMSE, steady-state error std, lag after steps (to 63 %), max error;
- always: innovation whiteness (normalised autocorrelation at lags 1-10) and the mean
  normalised innovation squared (NIS).

All pairs run at once: :func:`kalman_bank` is the filter of
:class:`cell.estimators.filters.ScalarKalman` vectorised across pairs with numpy (one Python loop over
time, none over pairs). The gain sequence does not depend on the data, so it is computed
once per pair and stops being updated when it has converged.

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

Scores (:func:`score_estimates`)
--------------------------------
``rmse``
    Root mean square of estimate - truth over every tick where both exist.
``ss_std``
    Standard deviation of estimate - truth over *steady* ticks. A tick is steady when the
    truth has moved less than ``steady_tol`` (2 mmH2O) over the ``steady_window_s`` (5 s)
    ending at it, so the filter has had at least 5 s to settle.
``lag_s``
    Median, over the steps found in the truth, of the filter's added lag: the time at which
    the estimate first covers 63 % of the step minus the time the truth itself does. A step
    is a change of more than ``step_min`` (50 mmH2O) between the median levels of two
    consecutive steady runs; the search starts at the end of the first run. 0 is a filter
    with no lag; a noisy filter can reach 63 % early and score below 0.
``max_err``
    Largest |estimate - truth|.
``whiteness``
    max over lags k = 1..10 of |rho_k|, the normalised autocorrelation of the normalised
    innovations e/sqrt(S) (mean removed, pairs of ticks k apart that both have an
    innovation). About 2/sqrt(n) for a consistent filter; near 0.5 when the gain is close
    to 1 (the innovations are then differenced noise). ``ljung_box`` is the Ljung-Box
    statistic n(n+2) sum rho_k^2/(n-k) over the same lags (chi-squared with 10 degrees
    of freedom for white innovations: 18.3 at the 95 % level).
``nis``
    Mean of e^2/S. About 1 when Q and R are right *in absolute terms*; the paper's
    covariances are not in mmH2O^2 (only their ratio and P0 shape the gain), so their NIS
    mostly says by how much the scale is off.

Pairs are ranked by ``rmse`` when the log has truth, otherwise by ``ljung_box`` (then by
|log nis|).
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import math
import re
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError

#: Seed 004's moving average: 30 samples at 10 Hz.
MAF_SAMPLES = 30
#: Innovation autocorrelation lags scored for whiteness.
WHITENESS_LAGS = 10
#: Largest grid accepted (pairs).
MAX_PAIRS = 100_000
#: Relative change below which the gain sequence counts as converged.
GAIN_RTOL = 1e-15

Pair = tuple[float, float]

TRUTH_KEYS = ("rmse", "ss_std", "lag_s", "max_err")
ALWAYS_KEYS = ("whiteness", "ljung_box", "nis")


# -- the series -----------------------------------------------------------------------------
@dataclass
class Series:
    """One channel sampled at every MED tick of a log, with its truth when the log has it.

    Attributes
    ----------
    t:
        Tick times (bus time, s).
    y:
        The channel's value at each tick; NaN where it was stale or had no value yet.
    truth:
        ``<channel>_TRUE`` at each tick (NaN where stale), or ``None``.
    channel, truth_channel:
        Names of the sampled channels.
    rate_hz:
        The MED rate the ticks ran at.
    source:
        Where the samples came from (a log path, or ``"array"``).
    frames:
        Frames read from the log.
    """

    t: np.ndarray
    y: np.ndarray
    truth: np.ndarray | None
    channel: str
    truth_channel: str | None = None
    rate_hz: float = 10.0
    source: str = "array"
    frames: int = 0

    @property
    def n(self) -> int:
        return int(self.y.size)

    @property
    def valid(self) -> int:
        return int(np.isfinite(self.y).sum())

    @classmethod
    def from_arrays(
        cls,
        y: Sequence[float | None] | np.ndarray,
        truth: Sequence[float | None] | np.ndarray | None = None,
        rate_hz: float = 10.0,
        channel: str = "y",
        t0: float = 0.0,
    ) -> Series:
        """A series from plain samples at ``rate_hz`` (``None`` counts as stale)."""
        yy = as_samples(y)
        tt = None if truth is None else as_samples(truth)
        if tt is not None and tt.shape != yy.shape:
            raise ConfigError(f"truth has {tt.size} samples, the channel {yy.size}")
        t = t0 + np.arange(yy.size) / rate_hz
        return cls(t, yy, tt, channel, None if tt is None else f"{channel}_TRUE", rate_hz)


def as_samples(values: Sequence[float | None] | np.ndarray) -> np.ndarray:
    """A float array from samples, ``None`` (a stale tick) becoming NaN."""
    if isinstance(values, np.ndarray):
        return np.asarray(values, dtype=float).ravel()
    return np.array([np.nan if v is None else float(v) for v in values], dtype=float)


def channel_series(
    log_path: str | Path,
    channel: str,
    truth: str | bool | None = None,
    rates: Any = None,
    progress: bool | None = None,
    db: Any = None,
) -> Series:
    """Sample ``channel`` (and its truth) at every MED tick of a CAN log.

    The log runs through a :class:`cell.runtime.Runtime` with no blocks, so the samples are
    exactly the inputs the runtime's filters see: at each tick, the latest frame value at
    or before the tick, NaN when the channel is stale or has no value yet. Stale ticks are
    kept; :func:`kalman_bank` holds its state over them as the runtime does.

    Parameters
    ----------
    log_path:
        A CAN log python-can reads (candump ``.log``, ``.asc``, ``.trc``, ``.csv``, ``.blf``).
    channel:
        The signal to sample, e.g. ``EXH_BP_R``.
    truth:
        ``None`` (default) samples ``<channel>_TRUE`` when the log has it; a name samples
        that channel (which must be in the log); ``False`` samples no truth.
    rates:
        :class:`cell.runtime.Rates` (default 50/10/1 Hz); samples are taken at MED.
    progress:
        Progress bar over the log (tqdm); ``None`` lets tqdm decide, ``False`` hides it.
    db:
        The DBC codec (default: the cell's).

    Returns
    -------
    Series

    Raises
    ------
    ConfigError
        The log is missing, or has no ``channel`` (the message lists the channels it has),
        or no ``truth`` channel when one was named.
    LogFormatError
        A malformed log line; the message carries the file and line number.
    """
    from ..dbc import load
    from ..replay import read_log
    from ..runtime import Runtime

    rt = Runtime(db or load(), rates=rates)
    truth_name = f"{channel}_TRUE" if truth is None or truth is True else truth or None
    times: list[float] = []
    ys: list[float] = []
    ts: list[float] = []
    nan = math.nan

    def value(name: str | None, t: float) -> float:
        ch = rt.channels.get(name) if name else None
        if ch is None:
            return nan
        status, _ = ch.status_at(t)
        return ch.value if status == "ok" and ch.value is not None else nan

    def on_tick(t: float) -> None:
        times.append(t)
        ys.append(value(channel, t))
        ts.append(value(truth_name, t))

    rt.tick_listeners.append(on_tick)
    frames = 0
    last: float | None = None
    for msg in read_log(log_path, progress=progress):
        rt.ingest(msg)
        frames += 1
        last = msg.timestamp if last is None else max(last, msg.timestamp)
    if last is not None:
        rt.advance(last)
    known = sorted(rt.channels)
    if channel not in rt.channels:
        raise ConfigError(
            f"--channel {channel}: no such channel in {log_path} ({frames} frames); "
            f"channels in the log: {', '.join(known) or 'none'}"
        )
    if truth_name is not None and truth_name not in rt.channels:
        if truth is None:
            truth_name = None
        else:
            raise ConfigError(
                f"--truth {truth_name}: no such channel in {log_path}; "
                f"channels in the log: {', '.join(known)}"
            )
    return Series(
        t=np.asarray(times, dtype=float),
        y=np.asarray(ys, dtype=float),
        truth=None if truth_name is None else np.asarray(ts, dtype=float),
        channel=channel,
        truth_channel=truth_name,
        rate_hz=rt.rates.MED,
        source=str(log_path),
        frames=frames,
    )


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


# -- the filter bank ------------------------------------------------------------------------
def _as_pairs(Q: Any, R: Any, P0: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    q, r, p0 = np.broadcast_arrays(
        np.atleast_1d(np.asarray(Q, dtype=float)).ravel(),
        np.atleast_1d(np.asarray(R, dtype=float)).ravel(),
        np.atleast_1d(np.asarray(P0, dtype=float)).ravel(),
    )
    for name, v in (("Q", q), ("R", r), ("P0", p0)):
        if not np.all(np.isfinite(v) & (v > 0)):
            bad = v[~(np.isfinite(v) & (v > 0))][0]
            raise ConfigError(f"{name} must be finite and > 0, got {bad}")
    return q.astype(float), r.astype(float), p0.astype(float)


def gain_sequence(
    Q: Any, R: Any, P0: Any = 1.0, steps: int = 1, rtol: float = GAIN_RTOL
) -> tuple[np.ndarray, np.ndarray]:
    r"""Kalman gains and innovation variances of the scalar filter, per pair.

    The recursion of seed 004, eqs. (3)-(4) with A = C = 1, from :math:`P_0` after the first
    sample: :math:`P^-_j = P_{j-1} + Q`, :math:`S_j = P^-_j + R`, :math:`K_j = P^-_j/S_j`,
    :math:`P_j = (1 - K_j) P^-_j` for j = 1, 2, ... It does not depend on the data.

    Parameters
    ----------
    Q, R, P0:
        Scalars or arrays broadcast to m pairs.
    steps:
        The most rows wanted (updates after the first sample).
    rtol:
        Stop once every pair's gain changes by at most ``rtol`` relative from one step to
        the next; the last row then holds for every later step.

    Returns
    -------
    K, S : ndarray, shape (L, m)
        ``K[j-1]``, ``S[j-1]`` for update j, with L <= ``steps``.
    """
    q, r, p = _as_pairs(Q, R, P0)
    steps = max(int(steps), 1)
    Ks: list[np.ndarray] = []
    Ss: list[np.ndarray] = []
    k_prev = None
    for _ in range(steps):
        p_prior = p + q
        s = p_prior + r
        k = p_prior / s
        p = (1.0 - k) * p_prior
        Ks.append(k)
        Ss.append(s)
        if k_prev is not None and np.all(np.abs(k - k_prev) <= rtol * k):
            break
        k_prev = k
    return np.array(Ks), np.array(Ss)


def steady_state_gain(Q: Any, R: Any) -> np.ndarray:
    """Fixed point of the scalar Riccati recursion, as :meth:`ScalarKalman.steady_state_gain`."""
    q = np.asarray(Q, dtype=float)
    r = np.asarray(R, dtype=float)
    p_prior = (q + np.sqrt(q * q + 4.0 * q * r)) / 2.0
    return p_prior / (p_prior + r)


def kalman_bank(
    y: Sequence[float | None] | np.ndarray, Q: Any, R: Any, P0: Any = 1.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""Run the scalar Kalman filter of seed 004 (eqs. 2-4) for many (Q, R) pairs at once.

    The same filter as :class:`cell.estimators.filters.ScalarKalman`: the first valid sample sets
    :math:`\hat x = y_0` and :math:`P = P_0`; every later one predicts and corrects. A NaN
    sample (a stale tick) holds the state, as the runtime does when it skips a block whose
    input is stale, and its outputs are NaN. Pairs are vectorised with numpy; the only
    Python loop is over time, and the gains come from :func:`gain_sequence` once.

    Parameters
    ----------
    y:
        Samples, shape (n,); NaN or ``None`` marks a stale tick.
    Q, R:
        Process and measurement noise covariances, scalars or arrays of m pairs.
    P0:
        Initial error covariance (scalar or per pair); seed 004 uses 1.

    Returns
    -------
    x : ndarray, shape (n, m)
        Posterior estimates :math:`\hat x_{k|k}`; NaN before the first valid sample and at
        stale ticks.
    innovations : ndarray, shape (n, m)
        :math:`y_k - \hat x_{k-1|k-1}`; NaN at the first valid sample and at stale ticks.
    S : ndarray, shape (n, m)
        Innovation variances :math:`P_{k|k-1} + R`, NaN where the innovation is.
    """
    yy = as_samples(y)
    q, r, p0 = _as_pairs(Q, R, P0)
    n, m = yy.size, q.size
    x = np.full((n, m), np.nan)
    e = np.full((n, m), np.nan)
    S = np.full((n, m), np.nan)
    idx = np.flatnonzero(np.isfinite(yy))
    nv = idx.size
    if nv == 0:
        return x, e, S
    K, Sg = gain_sequence(q, r, p0, steps=max(nv - 1, 1))
    L = K.shape[0]
    yv = yy[idx]
    xv = np.empty((nv, m))
    ev = np.empty((nv, m))
    xv[0] = yv[0]
    ev[0] = np.nan
    sub, mul, add = np.subtract, np.multiply, np.add
    for j in range(1, nv):
        row_e = ev[j]
        row_x = xv[j]
        sub(yv[j], xv[j - 1], out=row_e)
        mul(K[j - 1] if j <= L else K[L - 1], row_e, out=row_x)
        add(xv[j - 1], row_x, out=row_x)
    x[idx] = xv
    e[idx] = ev
    sv = np.empty((nv, m))
    sv[0] = np.nan
    if nv > 1:
        used = min(L, nv - 1)
        sv[1 : used + 1] = Sg[:used]
        sv[used + 1 :] = Sg[L - 1]
    S[idx] = sv
    return x, e, S


def moving_average(y: Sequence[float | None] | np.ndarray, samples: int = MAF_SAMPLES) -> np.ndarray:
    """Seed 004 eq. (1) as :class:`cell.estimators.filters.MovingAverage` runs it: the mean of the last
    ``samples`` valid samples (fewer at the start); NaN at stale ticks."""
    yy = as_samples(y)
    out = np.full(yy.size, np.nan)
    idx = np.flatnonzero(np.isfinite(yy))
    if idx.size == 0:
        return out
    c = np.concatenate([[0.0], np.cumsum(yy[idx])])
    j = np.arange(1, idx.size + 1)
    lo = np.maximum(j - samples, 0)
    out[idx] = (c[j] - c[lo]) / (j - lo)
    return out


# -- scores ---------------------------------------------------------------------------------
def steady_mask(truth: np.ndarray, rate_hz: float, tol: float = 2.0, window_s: float = 5.0) -> np.ndarray:
    """Ticks where the truth moved less than ``tol`` over the ``window_s`` ending at them."""
    w = max(round(window_s * rate_hz), 1) + 1
    n = truth.size
    mask = np.zeros(n, dtype=bool)
    if n < w:
        return mask
    win = np.lib.stride_tricks.sliding_window_view(truth, w)
    span = win.max(axis=1) - win.min(axis=1)  # NaN anywhere in the window -> not steady
    with np.errstate(invalid="ignore"):
        mask[w - 1 :] = span < tol
    return mask


@dataclass(frozen=True)
class Step:
    """A step found in the truth: indices and levels around it."""

    start: int  # last tick of the steady run before it
    end: int  # last tick of the steady run after it
    before: float
    after: float
    t63: float  # time at which the truth covers 63 % of the change


def find_steps(
    t: np.ndarray, truth: np.ndarray, steady: np.ndarray, step_min: float = 50.0
) -> list[Step]:
    """Steps between consecutive steady runs of the truth whose levels differ by > ``step_min``."""
    runs: list[tuple[int, int]] = []
    edges = np.diff(np.concatenate([[0], steady.astype(np.int8), [0]]))
    for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True):
        runs.append((int(a), int(b) - 1))
    steps = []
    for (a0, b0), (a1, b1) in itertools.pairwise(runs):
        before = float(np.median(truth[a0 : b0 + 1]))
        after = float(np.median(truth[a1 : b1 + 1]))
        if abs(after - before) <= step_min:
            continue
        seg = (truth[b0 : b1 + 1] - before) / (after - before)
        with np.errstate(invalid="ignore"):
            hit = np.flatnonzero(seg >= 0.63)
        if hit.size == 0:
            continue
        steps.append(Step(b0, b1, before, after, float(t[b0 + hit[0]])))
    return steps


def _truth_scores(
    t: np.ndarray,
    est: np.ndarray,
    truth: np.ndarray,
    rate_hz: float,
    steady_tol: float,
    steady_window_s: float,
    step_min: float,
) -> dict[str, np.ndarray]:
    err = est - truth[:, None]
    fin = np.isfinite(err)
    cnt = fin.sum(axis=0)
    e0 = np.where(fin, err, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rmse = np.sqrt((e0 * e0).sum(axis=0) / cnt)
        max_err = np.where(cnt > 0, np.abs(e0).max(axis=0), np.nan)
        steady = steady_mask(truth, rate_hz, steady_tol, steady_window_s)
        sf = fin & steady[:, None]
        ns = sf.sum(axis=0)
        es = np.where(sf, err, 0.0)
        mean_s = es.sum(axis=0) / ns
        ss_std = np.sqrt(np.where(sf, (err - mean_s) ** 2, 0.0).sum(axis=0) / ns)
    m = est.shape[1]
    lags = []
    for st in find_steps(t, truth, steady, step_min):
        seg = (est[st.start : st.end + 1] - st.before) / (st.after - st.before)
        with np.errstate(invalid="ignore"):
            hit = seg >= 0.63
        first = hit.argmax(axis=0)
        lag = np.where(hit.any(axis=0), t[st.start + first] - st.t63, np.nan)
        lags.append(lag)
    if lags:
        arr = np.array(lags)
        lag_s = np.full(m, np.nan)
        have = np.isfinite(arr).any(axis=0)
        if have.any():
            lag_s[have] = np.nanmedian(arr[:, have], axis=0)
    else:
        lag_s = np.full(m, np.nan)
    return {"rmse": rmse, "ss_std": ss_std, "lag_s": lag_s, "max_err": max_err}


def innovation_scores(
    innovations: np.ndarray, S: np.ndarray, lags: int = WHITENESS_LAGS
) -> dict[str, np.ndarray]:
    """Whiteness (max |rho_k|, k = 1..lags), Ljung-Box statistic and mean NIS, per column."""
    e = np.asarray(innovations, dtype=float)
    if e.ndim == 1:
        e = e[:, None]
        S = np.asarray(S, dtype=float)[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        nis_all = e * e / S
        fin = np.isfinite(nis_all)
        n = fin.sum(axis=0)
        nis = np.where(fin, nis_all, 0.0).sum(axis=0) / n
        nu = np.where(fin, e / np.sqrt(S), 0.0)
        mean = nu.sum(axis=0) / n
        nu = np.where(fin, nu - mean, 0.0)
        c0 = (nu * nu).sum(axis=0)
        rho = np.zeros((lags, e.shape[1]))
        for k in range(1, lags + 1):
            if k < nu.shape[0]:
                rho[k - 1] = (nu[:-k] * nu[k:]).sum(axis=0) / c0
        whiteness = np.abs(rho).max(axis=0)
        kk = np.arange(1, lags + 1)[:, None]
        lb = n * (n + 2) * (rho * rho / np.maximum(n - kk, 1)).sum(axis=0)
    bad = n < lags + 2
    whiteness[bad] = np.nan
    lb = np.where(bad, np.nan, lb)
    return {"whiteness": whiteness, "ljung_box": lb, "nis": nis}


def score_estimates(
    series: Series,
    est: np.ndarray,
    steady_tol: float = 2.0,
    steady_window_s: float = 5.0,
    step_min: float = 50.0,
) -> dict[str, np.ndarray]:
    """The truth scores (rmse, ss_std, lag_s, max_err) of estimates, shape (n,) or (n, m).

    Empty when the series has no truth. Used for the Kalman pairs and for the raw signal and
    the moving average as references.
    """
    if series.truth is None:
        return {}
    e = np.asarray(est, dtype=float)
    if e.ndim == 1:
        e = e[:, None]
    return _truth_scores(series.t, e, series.truth, series.rate_hz, steady_tol,
                         steady_window_s, step_min)


def _clean(v: Any) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def sweep(
    series: Series,
    pairs: Iterable[Pair],
    P0: float = 1.0,
    steady_tol: float = 2.0,
    steady_window_s: float = 5.0,
    step_min: float = 50.0,
) -> list[dict[str, Any]]:
    """Run every distinct (Q, R) pair over ``series`` at once and rank them.

    Parameters
    ----------
    series:
        From :func:`channel_series` (or :meth:`Series.from_arrays`).
    pairs:
        (Q, R) pairs, e.g. from :func:`parse_grid`; duplicates are scored once.
    P0:
        Initial covariance, as the runtime's filter (seed 004: 1).
    steady_tol, steady_window_s, step_min:
        Steady-state and step detection in the truth (see the module notes).

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

    def key_fn(row: dict[str, Any]) -> tuple:
        if series.truth is not None:
            v = row["rmse"]
            return (v is None, v if v is not None else 0.0)
        lb, nis = row["ljung_box"], row["nis"]
        return (lb is None, lb if lb is not None else 0.0,
                abs(math.log(nis)) if nis else math.inf)

    rows.sort(key=key_fn)
    for i, row in enumerate(rows, 1):
        row["rank"] = i
    return [{"rank": row.pop("rank"), **row} for row in rows]


def references(series: Series, **kw: Any) -> list[dict[str, Any]]:
    """Truth scores of the raw signal and the 30-sample moving average, for comparison."""
    if series.truth is None:
        return []
    out = []
    for name, est in (("raw", series.y), (f"MAF-{MAF_SAMPLES}", moving_average(series.y))):
        s = score_estimates(series, est, **kw)
        out.append({"filter": name, **{k: _clean(s[k][0]) for k in TRUTH_KEYS}})
    return out


# -- outputs --------------------------------------------------------------------------------
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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
                           steady_mask(series.truth, series.rate_hz), 50.0)
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
        ax.set_ylabel(series.channel)
        ax.grid(alpha=0.3)
    axes[0].set_title(f"{Path(series.source).name}: best {len(best)} Q/R pairs "
                      "(seed 004, Figures 7-8)")
    axes[1].set_title(f"zoom {z0:.0f}-{z1:.0f} s")
    axes[0].legend(fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def format_table(ranked: Sequence[dict[str, Any]], top: int | None = None,
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

    cells = [cols] + [[fmt(c, r.get(c)) for c in cols] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(cols))]
    lines = ["  ".join(s.rjust(w) for s, w in zip(row, widths, strict=True)) for row in cells]
    for ref in refs:
        vals = "  ".join(f"{k}={fmt(k, ref.get(k))}" for k in TRUTH_KEYS)
        lines.append(f"reference {ref['filter']}: {vals}")
    return "\n".join(lines)


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
    parser.add_argument("--out-dir", default=".", type=Path,
                        help="folder for sweep_<channel>.csv/.png/.jsonl (default: current)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object per pair instead of the table")
    parser.add_argument("--top", type=int, default=10, help="rows printed (default 10)")
    parser.add_argument("--plot-top", type=int, default=3, help="pairs plotted (default 3)")
    parser.add_argument("--no-plot", action="store_true", help="do not write the PNG")
    add_log_options(parser)


def add_log_options(parser: argparse.ArgumentParser) -> None:
    """Options shared by the commands that read a channel from a log (``sweep``, ``tune``)."""
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--cycle", default=None, metavar="HZ|FAS=..,MED=..,SLO=..",
                        help="task rates; samples are taken at MED (default 10 Hz)")
    parser.add_argument("--dbc", default=None, help="DBC file (default: the cell's)")


def load_series(args: argparse.Namespace) -> Series:
    """The series a ``sweep``/``tune`` command line asks for."""
    from ..dbc import load
    from ..runtime import Rates

    truth: str | bool | None = getattr(args, "truth", None)
    if getattr(args, "no_truth", False):
        truth = False
    return channel_series(
        args.log, args.channel, truth=truth, rates=Rates.parse(getattr(args, "cycle", None)),
        progress=False if getattr(args, "quiet", False) else None,
        db=load(getattr(args, "dbc", None)),
    )


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
    out_dir = Path(args.out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out-dir {out_dir}: {exc.strerror or exc}") from None
    stem = f"sweep_{series.channel}"
    written = [write_csv(out_dir / f"{stem}.csv", ranked), write_jsonl(out_dir / f"{stem}.jsonl", ranked)]
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
        print(format_table(ranked, args.top, references(series)))
    print("wrote " + ", ".join(str(p) for p in written), file=sys.stderr)
    return 0


__all__ = [
    "Series",
    "add_arguments",
    "channel_series",
    "format_table",
    "gain_sequence",
    "innovation_scores",
    "json_lines",
    "kalman_bank",
    "main",
    "moving_average",
    "parse_grid",
    "plot_png",
    "references",
    "score_estimates",
    "steady_state_gain",
    "sweep",
    "table1",
    "table2",
    "unique_pairs",
    "write_csv",
    "write_jsonl",
]
