"""Estimating the Kalman filter's Q and R from the data alone (seed 004, future work).

Seed 004 tunes Q and R of its scalar filter (eqs. 2-4, A = C = 1) by eye over Tables 1-2 and
asks, in its conclusion, for quantitative tuning. :mod:`cell.analysis.sweep` scores a grid against
simulator truth; this module needs no truth. It fits the filter's own model, a random walk
observed in white noise,

.. math:: x_{k+1} = x_k + v_k,\\ v_k \\sim N(0, Q); \\qquad y_k = x_k + w_k,\\ w_k \\sim N(0, R),

to the samples of one channel.

Methods
-------
``ml`` (default): maximum likelihood on the innovations.
    The exact Gaussian log-likelihood of the innovations e_k with variances S_k, computed by
    the filter itself. With the initial covariance P0 = R (the exact value when the first
    sample initialises the state, :math:`\\hat x_0 = y_0`: a diffuse prior conditioned on
    y_0), every S_k is R times the S_k of the filter with (q = Q/R, 1), so R has the closed
    form :math:`\\hat R(q) = \\frac{1}{n}\\sum e_k^2/s_k` and the likelihood is profiled
    over the ratio q alone. q is found on a log grid from 1e-8 to 1e2, vectorised over the
    grid with :func:`cell.estimators.backpressure.kalman_bank`, then refined twice on finer grids.
    numpy only.
``als``: autocovariance least squares on the differenced series.
    For a random walk plus white noise, :math:`\\Delta y_k = v_k + w_k - w_{k-1}` has
    :math:`\\gamma_0 = Q + 2R`, :math:`\\gamma_1 = -R` and no autocovariance beyond lag 1,
    so :math:`\\hat R = -\\hat\\gamma_1`, :math:`\\hat Q = \\hat\\gamma_0 + 2\\hat\\gamma_1`.
    Fast and closed form, but fragile on the cell's data: a lagged step makes the
    increments positively correlated, so :math:`\\gamma_1` is less negative, and Q is the
    small difference of two noisy numbers. Measured on the simulator (seed 0 unless
    stated): ``transient`` seeds 0-4 give RMSE +33 %, +1.6 %, +1.8 %, Q <= 0 (floored,
    RMSE x10), +4.6 % over the best grid pair; ``warmup`` and ``rated`` give Q <= 0. ``ml``
    stays within 0.5 % on all of them. Use ``als`` as a quick cross-check only.

Confidence
----------
For ``ml``, Q/R's interval is the profile-likelihood interval (log-likelihood within
1.92 of its maximum, chi-squared 1 dof at 95 %), widened for heavy tails: the threshold is
multiplied by max(1, (kappa - 1)/2), kappa being the kurtosis of the normalised innovations
(for Gaussian noise kappa = 3 and nothing changes; the cell's Student-t noise with spikes
has kappa ~ 5-9, and a likelihood-ratio statistic for variance parameters scales by
(kappa - 1)/2 under such noise). R's interval is the sandwich (robust) standard error of the
mean of e^2/s. Q's interval is that of Q/R times R-hat (at each end of the ratio interval).
For ``als``, intervals are the 2.5-97.5 % spread of a moving-block bootstrap.

What the estimate is good for
-----------------------------
A linear filter's mean-square error depends only on second-order statistics, so a model that
matches the spectrum of the data gives a gain close to the best one *for RMSE*, even when the
signal is not a random walk (the cell's truth is steps and holds through a lag) and the noise
is heavy tailed: the Gaussian likelihood (Whittle's approximation) fits exactly that
spectrum. Measured against the best of 241 log-spaced Q/R (P0 = 1) scored with the truth:
``transient`` seeds 0-4 +0.0, -0.1, +0.5, +0.1, +0.5 % RMSE; ``warmup`` -0.2 %; ``rated``
-0.1 % (``tests/cell/analysis/test_autotune.py`` asserts <= 10 % on two seeds). The estimate
is only as good as the data are representative: a log with no transients has Q ~ 0 and gives a
very smooth filter.

Nothing is applied here: :func:`autotune` returns a :class:`TuneResult`; ``testcell tune``
prints it and ``POST /filters/{name}/autotune`` applies it only with ``{"apply": true}``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from cell.core.errors import ConfigError
from cell.estimators.backpressure import kalman_bank, steady_state_gain
from cell.analysis.series import add_log_options, as_samples, load_series
from cell.analysis.scores import score_estimates

METHODS = ("ml", "als")
#: Fewest valid samples :func:`autotune` accepts.
MIN_SAMPLES = 50
#: Fewer valid samples than this and an estimate is shown but never applied to a live filter.
APPLY_MIN_SAMPLES = 600
#: Coarse search range of Q/R.
RATIO_RANGE = (1e-8, 1e2)
#: chi-squared(1) 95 % quantile / 2.
LR_95 = 1.920729410347062


@dataclass
class TuneResult:
    """Q and R estimated from data, with 95 % intervals.

    Attributes
    ----------
    Q, R:
        Process and measurement noise covariances in the channel's units squared, per tick
        of ``rate_hz``.
    Q_ci, R_ci:
        95 % intervals ``(low, high)``; see the module notes for how they are made.
    loglik:
        Gaussian log-likelihood of the innovations at the estimate (``nan`` for ``als``).
    method:
        ``"ml"`` or ``"als"``.
    n:
        Valid samples used.
    rate_hz:
        Sample rate the covariances refer to.
    gain:
        Steady-state Kalman gain of the estimate (depends on Q/R only).
    ratio, ratio_ci:
        Q/R and its interval.
    kurtosis:
        Kurtosis of the normalised innovations (3 for Gaussian noise).
    notes:
        Warnings, e.g. the ratio at the edge of the search range.
    """

    Q: float
    R: float
    Q_ci: tuple[float, float]
    R_ci: tuple[float, float]
    loglik: float
    method: str
    n: int
    rate_hz: float = 10.0
    gain: float = math.nan
    ratio: float = math.nan
    ratio_ci: tuple[float, float] = (math.nan, math.nan)
    kurtosis: float = math.nan
    notes: list[str] = field(default_factory=list)

    def paper_units(self, R: float = 1e-4) -> tuple[float, float]:
        """The same steady-state gain written with seed 004's R (default 1e-4): (Q, R)."""
        return self.ratio * R, R

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: tuples become lists, non-finite numbers ``None``."""

        def clean(v: Any) -> Any:
            if isinstance(v, float):
                return v if math.isfinite(v) else None
            if isinstance(v, tuple | list):
                return [clean(x) for x in v]
            return v

        return {k: clean(v) for k, v in asdict(self).items()}


# -- maximum likelihood ---------------------------------------------------------------------
def profile_loglik(y: np.ndarray, ratios: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Profile log-likelihood and R-hat for each Q/R in ``ratios`` (vectorised).

    Runs the filter with (Q, R, P0) = (q, 1, 1): with P0 = R the innovation variances scale
    with R, so R-hat = mean(e^2/s) and the likelihood is
    ``-0.5 (n log(2 pi R-hat) + sum log s + n)``.
    """
    _, e, s = kalman_bank(y, ratios, 1.0, 1.0)
    fin = np.isfinite(e[:, 0])
    e, s = e[fin], s[fin]
    n = e.shape[0]
    r_hat = (e * e / s).mean(axis=0)
    ll = -0.5 * (n * np.log(2.0 * np.pi * r_hat) + np.log(s).sum(axis=0) + n)
    return ll, r_hat


def loglik(y: Sequence[float | None] | np.ndarray, Q: Any, R: Any) -> np.ndarray:
    """Exact Gaussian log-likelihood of the innovations for (Q, R) pairs, with P0 = R.

    ``-0.5 sum(log(2 pi S_k) + e_k^2 / S_k)`` over every innovation after the first sample:
    the quantity :func:`autotune` (``ml``) maximises, to compare any estimate with it.
    """
    yy = as_samples(y)
    yy = yy[int(np.argmax(np.isfinite(yy))) :]
    q, r = np.broadcast_arrays(np.atleast_1d(np.asarray(Q, dtype=float)),
                               np.atleast_1d(np.asarray(R, dtype=float)))
    _, e, s = kalman_bank(yy, q, r, r)
    fin = np.isfinite(e[:, 0])
    e, s = e[fin], s[fin]
    return -0.5 * (np.log(2.0 * np.pi * s) + e * e / s).sum(axis=0)


def _ml(y: np.ndarray) -> tuple[float, float, float, np.ndarray, list[str]]:
    lo, hi = math.log10(RATIO_RANGE[0]), math.log10(RATIO_RANGE[1])
    grid = np.linspace(lo, hi, 61)
    notes: list[str] = []
    ll, _ = profile_loglik(y, 10.0**grid)
    i = int(np.nanargmax(ll))
    if i in (0, grid.size - 1):
        notes.append(f"Q/R at the edge of the search range ({10.0 ** grid[i]:.3g})")
    step = grid[1] - grid[0]
    for _ in range(2):  # refine around the best point
        centre = grid[i]
        grid = np.linspace(centre - step, centre + step, 41)
        grid = grid[(grid >= lo) & (grid <= hi)]
        step = grid[1] - grid[0]
        ll, _ = profile_loglik(y, 10.0**grid)
        i = int(np.nanargmax(ll))
    log_q = float(grid[i])
    return log_q, float(ll[i]), step, grid, notes


def _profile_interval(y: np.ndarray, log_q: float, ll_max: float, threshold: float
                      ) -> tuple[float, float]:
    """Where the profile log-likelihood drops ``threshold`` below its maximum (log10 q)."""
    lo_lim, hi_lim = (math.log10(v) for v in RATIO_RANGE)
    grid = np.linspace(max(log_q - 3.0, lo_lim), min(log_q + 3.0, hi_lim), 241)
    ll, _ = profile_loglik(y, 10.0**grid)
    inside = ll >= ll_max - threshold
    j = int(np.argmin(np.abs(grid - log_q)))
    a = j
    while a > 0 and inside[a - 1]:
        a -= 1
    b = j
    while b < grid.size - 1 and inside[b + 1]:
        b += 1

    def cross(i0: int, i1: int) -> float:  # linear interpolation of the crossing
        l0, l1 = ll[i0] - (ll_max - threshold), ll[i1] - (ll_max - threshold)
        if l0 == l1:
            return float(grid[i0])
        return float(grid[i0] + (grid[i1] - grid[i0]) * l0 / (l0 - l1))

    low = cross(a, a - 1) if a > 0 else -math.inf
    high = cross(b, b + 1) if b < grid.size - 1 else math.inf
    return low, high


def _kurtosis(e: np.ndarray, s: np.ndarray) -> float:
    fin = np.isfinite(e)
    nu = e[fin] / np.sqrt(s[fin])
    nu = nu - nu.mean()
    v = float((nu * nu).mean())
    return float((nu**4).mean() / (v * v)) if v > 0 else math.nan


def _sandwich_r(e: np.ndarray, s: np.ndarray, R: float) -> tuple[float, float]:
    fin = np.isfinite(e)
    z = e[fin] ** 2 / s[fin]  # s is S/R (the filter ran with R = 1): mean is R-hat
    se = float(z.std(ddof=1) / math.sqrt(z.size))
    return max(R - 1.96 * se, 0.0), R + 1.96 * se


# -- autocovariance least squares -----------------------------------------------------------
def _als_point(d: np.ndarray) -> tuple[float, float]:
    """(Q, R) from first differences ``d`` (NaN where a difference spans a stale tick)."""
    fin = np.isfinite(d)
    dd = d[fin]
    mu = dd.mean()
    g0 = float(((dd - mu) ** 2).mean())
    pair = fin[:-1] & fin[1:]
    g1 = float(((d[:-1][pair] - mu) * (d[1:][pair] - mu)).mean()) if pair.any() else 0.0
    R = max(-g1, 0.0)
    Q = max(g0 - 2.0 * R, 0.0)
    return Q, R


def _als(y: np.ndarray, seed: int = 0, boots: int = 300) -> tuple[float, float, tuple, tuple,
                                                                 tuple]:
    d = np.diff(y)
    Q, R = _als_point(d)
    rng = np.random.default_rng(seed)
    block = max(20, round(d.size ** (1 / 3)) * 5)
    nb = max(d.size // block, 1)
    starts_all = np.arange(max(d.size - block + 1, 1))
    qs, rs, ratios = [], [], []
    for _ in range(boots):
        starts = rng.choice(starts_all, nb)
        dd = np.concatenate([np.append(d[s : s + block], np.nan) for s in starts])
        q, r = _als_point(dd)
        qs.append(q)
        rs.append(r)
        ratios.append(q / r if r > 0 else np.inf)
    pct = [2.5, 97.5]
    return (Q, R, tuple(np.percentile(qs, pct)), tuple(np.percentile(rs, pct)),
            tuple(np.percentile(ratios, pct)))


# -- entry point ----------------------------------------------------------------------------
def autotune(
    y: Sequence[float | None] | np.ndarray, rate_hz: float = 10.0, method: str = "ml"
) -> TuneResult:
    """Estimate Q and R of the scalar Kalman filter (seed 004, eqs. 2-4) from samples alone.

    Parameters
    ----------
    y:
        Samples at ``rate_hz`` (e.g. a channel's history); NaN or ``None`` marks a stale
        tick, over which the filter holds its state.
    rate_hz:
        Sample rate; Q is per sample at this rate (the runtime's MED rate).
    method:
        ``"ml"`` (maximum likelihood on the innovations, default) or ``"als"``
        (autocovariance least squares on the differences). See the module notes.

    Returns
    -------
    TuneResult

    Raises
    ------
    ConfigError
        Unknown method, bad rate, fewer than :data:`MIN_SAMPLES` valid samples, or a
        constant signal.
    """
    if method not in METHODS:
        raise ConfigError(f"method {method!r}: use one of {', '.join(METHODS)}")
    if not (isinstance(rate_hz, int | float) and math.isfinite(rate_hz) and rate_hz > 0):
        raise ConfigError(f"rate_hz must be a number > 0, got {rate_hz!r}")
    yy = as_samples(y)
    fin = np.isfinite(yy)
    n = int(fin.sum())
    if n < MIN_SAMPLES:
        raise ConfigError(f"autotune needs at least {MIN_SAMPLES} valid samples, got {n}")
    if float(np.ptp(yy[fin])) == 0.0:
        raise ConfigError("the samples are constant: no noise to estimate R from")
    # keep from the first valid sample on; stale ticks inside stay NaN (state held)
    yy = yy[int(np.argmax(fin)) :]
    if method == "als":
        Q, R, Q_ci, R_ci, ratio_ci = _als(yy)
        notes = []
        if R <= 0:  # floors keep the pair usable by a filter (Q, R > 0)
            R = RATIO_RANGE[0] * max(Q, 1e-300)
            notes.append("lag-1 autocovariance of the differences is not negative: R floored")
        if Q <= 0:
            Q = RATIO_RANGE[0] * R
            notes.append(f"var(diff) <= 2 R: Q floored at {RATIO_RANGE[0]:g} x R")
        ratio = Q / R if R > 0 else math.inf
        return TuneResult(
            Q=Q, R=R, Q_ci=(float(Q_ci[0]), float(Q_ci[1])), R_ci=(float(R_ci[0]), float(R_ci[1])),
            loglik=math.nan, method="als", n=n, rate_hz=float(rate_hz),
            gain=float(steady_state_gain(Q, R)) if R > 0 else 1.0, ratio=ratio,
            ratio_ci=(float(ratio_ci[0]), float(ratio_ci[1])), notes=notes,
        )
    log_q, ll, _, _, notes = _ml(yy)
    q = 10.0**log_q
    _, e, s = kalman_bank(yy, q, 1.0, 1.0)
    e, s = e[:, 0], s[:, 0]
    fin_e = np.isfinite(e)
    R = float((e[fin_e] ** 2 / s[fin_e]).mean())
    Q = q * R
    kappa = _kurtosis(e, s)
    threshold = LR_95 * max(1.0, (kappa - 1.0) / 2.0 if math.isfinite(kappa) else 1.0)
    lo, hi = _profile_interval(yy, log_q, ll, threshold)
    ratio_ci = (10.0**lo if math.isfinite(lo) else 0.0, 10.0**hi if math.isfinite(hi) else math.inf)
    r_at = {}
    for end, lq in (("lo", lo), ("hi", hi)):
        if math.isfinite(lq):
            _, r_hat = profile_loglik(yy, np.array([10.0**lq]))
            r_at[end] = float(r_hat[0])
    Q_ci = (ratio_ci[0] * r_at.get("lo", R), ratio_ci[1] * r_at.get("hi", R))
    R_ci = _sandwich_r(e, s, R)
    if not math.isfinite(hi) or not math.isfinite(lo):
        notes.append("the Q/R interval reaches the search range: the data say little about Q")
    return TuneResult(
        Q=Q, R=R, Q_ci=Q_ci, R_ci=R_ci, loglik=ll, method="ml", n=n, rate_hz=float(rate_hz),
        gain=float(steady_state_gain(Q, R)), ratio=q, ratio_ci=ratio_ci, kurtosis=kappa,
        notes=notes,
    )


def apply_refusals(result: TuneResult) -> list[str]:
    """Why an estimate must not be applied to a running filter (empty: it may be).

    Every note the tuner makes flags an estimate it cannot vouch for: Q/R at the edge of the
    search range (a Q/R of 1e-8 freezes the filter a controller reads), an interval reaching
    the range, a floored Q or R; so does too little data (fewer than
    :data:`APPLY_MIN_SAMPLES` valid samples).
    """
    reasons = list(result.notes)
    if result.n < APPLY_MIN_SAMPLES:
        reasons.append(f"too little data: {result.n} valid samples, at least "
                       f"{APPLY_MIN_SAMPLES} are needed to apply an estimate")
    return reasons


def em_reference(
    y: Sequence[float | None] | np.ndarray, n_iter: int = 30, Q0: float | None = None,
    R0: float | None = None,
) -> tuple[float, float]:
    """Q and R by pykalman's EM on the same random-walk model: a peer reference for tests.

    pykalman is not a dependency of testcell; this raises :class:`ImportError` without it.
    Stale samples are passed as masked values. EM converges slowly; ``n_iter`` iterations
    from (``Q0``, ``R0``) (default: the ALS estimate, floored).
    """
    from pykalman import KalmanFilter

    yy = as_samples(y)
    yy = yy[int(np.argmax(np.isfinite(yy))) :]
    if Q0 is None or R0 is None:
        q_als, r_als = _als_point(np.diff(yy))
        var = float(np.nanvar(yy)) or 1.0
        Q0 = Q0 if Q0 is not None else max(q_als, 1e-6 * var)
        R0 = R0 if R0 is not None else max(r_als, 1e-6 * var)
    kf = KalmanFilter(
        transition_matrices=[[1.0]], observation_matrices=[[1.0]],
        transition_covariance=[[Q0]], observation_covariance=[[R0]],
        initial_state_mean=[float(yy[0])], initial_state_covariance=[[R0]],
        em_vars=["transition_covariance", "observation_covariance"],
    )
    data = np.ma.masked_invalid(yy)[:, None]
    kf = kf.em(data, n_iter=n_iter)
    return float(np.ravel(kf.transition_covariance)[0]), float(np.ravel(kf.observation_covariance)[0])


# -- command line ---------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``testcell tune`` options to ``parser``."""
    parser.add_argument("log", help="CAN log: candump -L .log, .asc, .blf, .trc or python-can .csv")
    parser.add_argument("--channel", default="EXH_BP_R", help="channel to tune for (default EXH_BP_R)")
    parser.add_argument("--method", default="ml", choices=METHODS,
                        help="ml: maximum likelihood on the innovations (default); "
                             "als: autocovariance least squares")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    add_log_options(parser)


def main(args: argparse.Namespace) -> int:
    """Run ``testcell tune``: estimate and print; it never applies anything.

    When the log has ``<channel>_TRUE``, the tuned filter's RMSE against it is printed too
    (``rmse_vs_truth``), next to the paper's pair (Q = 1e-6, R = 1e-4).
    """
    args.truth, args.no_truth = None, False
    series = load_series(args)
    res = autotune(series.y, series.rate_hz, method=args.method)
    out = res.to_dict()
    out["channel"] = series.channel
    q_p, r_p = res.paper_units()
    out["paper_units"] = {"Q": q_p, "R": r_p}
    out["apply_refused"] = apply_refusals(res)
    if series.truth is not None:
        x, _, _ = kalman_bank(series.y, [res.Q, 1e-6], [res.R, 1e-4])
        rmse = score_estimates(series, x)["rmse"]
        out["rmse_vs_truth"] = float(rmse[0])
        out["rmse_paper_pair"] = float(rmse[1])
    if args.json:
        print(json.dumps(out, allow_nan=False, default=lambda v: None))
        return 0
    print(f"{series.source}: {series.channel}, {res.n} valid samples at {res.rate_hz:g} Hz, "
          f"method {res.method}")
    print(f"  Q = {res.Q:.4g}  (95 % {res.Q_ci[0]:.3g} .. {res.Q_ci[1]:.3g})")
    print(f"  R = {res.R:.4g}  (95 % {res.R_ci[0]:.3g} .. {res.R_ci[1]:.3g})")
    print(f"  Q/R = {res.ratio:.4g}  (95 % {res.ratio_ci[0]:.3g} .. {res.ratio_ci[1]:.3g}), "
          f"steady-state gain {res.gain:.4f}")
    print(f"  same gain in seed 004's units: Q = {q_p:.3g}, R = {r_p:.3g}")
    if math.isfinite(res.loglik):
        print(f"  log-likelihood {res.loglik:.1f}, innovation kurtosis {res.kurtosis:.1f}")
    if "rmse_vs_truth" in out:
        print(f"  RMSE vs {series.truth_channel}: {out['rmse_vs_truth']:.2f} "
              f"(seed 004's Q=1e-6, R=1e-4: {out['rmse_paper_pair']:.2f})")
    for note in res.notes:
        print(f"  note: {note}")
    refused = apply_refusals(res)
    if refused:
        print("  a live autotune would not apply this estimate: " + "; ".join(refused))
    print("  not applied; apply with PATCH /filters/{name} or POST /filters/{name}/autotune "
          '{"apply": true}', file=sys.stderr)
    return 0


__all__ = ["APPLY_MIN_SAMPLES", "METHODS", "TuneResult", "add_arguments", "apply_refusals",
           "autotune", "em_reference", "loglik", "main", "profile_loglik"]
