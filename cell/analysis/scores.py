"""Scores of an estimate: against simulator truth, and of an estimator's innovations alone.

Any estimate of a signal can be scored against its truth: a back-pressure filter against
``EXH_BP_R_TRUE``, an observer's oxygen storage against its ``_TRUE`` channel. The functions
take plain arrays and a sample rate; :func:`score_estimates` is the shortcut for a
:class:`cell.analysis.series.Series`. Estimates may be one column, shape (n,), or many,
shape (n, m), scored column by column; NaN marks a tick with no value (it is left out).

Truth scores (:func:`truth_scores`, keys :data:`TRUTH_KEYS`)
------------------------------------------------------------
Thresholds are in the signal's own units. The defaults (:data:`STEADY_TOL`,
:data:`STEADY_WINDOW_S`, :data:`STEP_MIN`) are those of exhaust back-pressure in mmH2O; pass
others for another signal.

``rmse``
    Root mean square of estimate - truth over every tick where both exist.
``ss_std``
    Standard deviation of estimate - truth over *steady* ticks. A tick is steady when the
    truth has moved less than ``steady_tol`` (2 mmH2O) over the ``steady_window_s`` (5 s)
    ending at it, so the estimator has had at least 5 s to settle (:func:`steady_mask`).
``lag_s``
    Median, over the steps found in the truth, of the estimate's added lag: the time at
    which the estimate first covers 63 % of the step minus the time the truth itself does.
    A step is a change of more than ``step_min`` (50 mmH2O) between the median levels of two
    consecutive steady runs; the search starts at the end of the first run
    (:func:`find_steps`). 0 is an estimate with no lag; a noisy one can reach 63 % early
    and score below 0.
``max_err``
    Largest |estimate - truth|.

Innovation scores (:func:`innovation_scores`, keys :data:`ALWAYS_KEYS`)
-----------------------------------------------------------------------
These need no truth: only an estimator's innovations e (measurement minus prediction) and
their predicted variances S, as any Kalman-type filter or observer has them.

``whiteness``
    max over lags k = 1..10 (:data:`WHITENESS_LAGS`) of |rho_k|, the normalised
    autocorrelation of the normalised innovations e/sqrt(S) (mean removed, pairs of ticks k
    apart that both have an innovation). About 2/sqrt(n) for a consistent filter; near 0.5
    when the gain is close to 1 (the innovations are then differenced noise). ``ljung_box``
    is the Ljung-Box statistic n(n+2) sum rho_k^2/(n-k) over the same lags (chi-squared
    with 10 degrees of freedom for white innovations: 18.3 at the 95 % level).
``nis``
    Mean of e^2/S. About 1 when the noise covariances are right *in absolute terms*; seed
    004's covariances are not in mmH2O^2 (only their ratio and P0 shape the gain), so their
    NIS mostly says by how much the scale is off.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Innovation autocorrelation lags scored for whiteness.
WHITENESS_LAGS = 10
#: Truth scores, in table order.
TRUTH_KEYS = ("rmse", "ss_std", "lag_s", "max_err")
#: Innovation scores, in table order (they need no truth).
ALWAYS_KEYS = ("whiteness", "ljung_box", "nis")
#: Default steadiness tolerance: largest move of the truth over the window (mmH2O).
STEADY_TOL = 2.0
#: Default steadiness window (s).
STEADY_WINDOW_S = 5.0
#: Default smallest step between steady levels (mmH2O).
STEP_MIN = 50.0
#: Fraction of a step that times the response (63 %, one time constant).
RISE = 0.63


def steady_mask(
    truth: np.ndarray, rate_hz: float, tol: float = STEADY_TOL, window_s: float = STEADY_WINDOW_S
) -> np.ndarray:
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
    t: np.ndarray, truth: np.ndarray, steady: np.ndarray, step_min: float = STEP_MIN
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
            hit = np.flatnonzero(seg >= RISE)
        if hit.size == 0:
            continue
        steps.append(Step(b0, b1, before, after, float(t[b0 + hit[0]])))
    return steps


def truth_scores(
    est: np.ndarray,
    truth: np.ndarray,
    rate_hz: float,
    t: np.ndarray | None = None,
    steady_tol: float = STEADY_TOL,
    steady_window_s: float = STEADY_WINDOW_S,
    step_min: float = STEP_MIN,
) -> dict[str, np.ndarray]:
    """``rmse``, ``ss_std``, ``lag_s`` and ``max_err`` of estimates against the truth.

    Parameters
    ----------
    est:
        Estimates, shape (n,) or (n, m) (m estimators scored at once); NaN where none.
    truth:
        The true signal, shape (n,); NaN where unknown.
    rate_hz:
        Sample rate (sets the steady window in ticks).
    t:
        Sample times (s) for ``lag_s``; default ``arange(n) / rate_hz``.
    steady_tol, steady_window_s, step_min:
        Steady-state and step detection in the truth, in its units (see the module notes).

    Returns
    -------
    dict of ndarray, shape (m,)
        NaN where a score cannot be made (no steady tick, no step reached).
    """
    e = np.asarray(est, dtype=float)
    if e.ndim == 1:
        e = e[:, None]
    tr = np.asarray(truth, dtype=float)
    tt = np.arange(tr.size) / rate_hz if t is None else np.asarray(t, dtype=float)
    err = e - tr[:, None]
    fin = np.isfinite(err)
    cnt = fin.sum(axis=0)
    e0 = np.where(fin, err, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rmse = np.sqrt((e0 * e0).sum(axis=0) / cnt)
        max_err = np.where(cnt > 0, np.abs(e0).max(axis=0), np.nan)
        steady = steady_mask(tr, rate_hz, steady_tol, steady_window_s)
        sf = fin & steady[:, None]
        ns = sf.sum(axis=0)
        es = np.where(sf, err, 0.0)
        mean_s = es.sum(axis=0) / ns
        ss_std = np.sqrt(np.where(sf, (err - mean_s) ** 2, 0.0).sum(axis=0) / ns)
    m = e.shape[1]
    lags = []
    for st in find_steps(tt, tr, steady, step_min):
        seg = (e[st.start : st.end + 1] - st.before) / (st.after - st.before)
        with np.errstate(invalid="ignore"):
            hit = seg >= RISE
        first = hit.argmax(axis=0)
        lag = np.where(hit.any(axis=0), tt[st.start + first] - st.t63, np.nan)
        lags.append(lag)
    lag_s = np.full(m, np.nan)
    if lags:
        arr = np.array(lags)
        have = np.isfinite(arr).any(axis=0)
        if have.any():
            lag_s[have] = np.nanmedian(arr[:, have], axis=0)
    return {"rmse": rmse, "ss_std": ss_std, "lag_s": lag_s, "max_err": max_err}


def innovation_scores(
    innovations: np.ndarray, S: np.ndarray, lags: int = WHITENESS_LAGS
) -> dict[str, np.ndarray]:
    """Whiteness (max |rho_k|, k = 1..lags), Ljung-Box statistic and mean NIS, per column.

    ``innovations`` and their predicted variances ``S``, shape (n,) or (n, m); NaN where a
    tick has no innovation. Scores are NaN for a column with fewer than ``lags + 2``.
    """
    e = np.asarray(innovations, dtype=float)
    S = np.asarray(S, dtype=float)
    if e.ndim == 1:
        e = e[:, None]
        S = S[:, None]
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
    series: Any,
    est: np.ndarray,
    steady_tol: float = STEADY_TOL,
    steady_window_s: float = STEADY_WINDOW_S,
    step_min: float = STEP_MIN,
) -> dict[str, np.ndarray]:
    """:func:`truth_scores` of estimates of a :class:`~cell.analysis.series.Series`.

    Uses the series' truth, rate and tick times; empty when the series has no truth. Used
    for the Kalman pairs of a sweep and for the raw signal and the moving average as
    references.
    """
    if series.truth is None:
        return {}
    return truth_scores(est, series.truth, series.rate_hz, series.t, steady_tol,
                        steady_window_s, step_min)


__all__ = [
    "ALWAYS_KEYS",
    "STEADY_TOL",
    "STEADY_WINDOW_S",
    "STEP_MIN",
    "TRUTH_KEYS",
    "WHITENESS_LAGS",
    "Step",
    "find_steps",
    "innovation_scores",
    "score_estimates",
    "steady_mask",
    "truth_scores",
]
