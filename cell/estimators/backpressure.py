"""Back-pressure filters of seed 004: the moving average and the scalar Kalman filter.

Each filter comes twice, and the two are tested against each other:

- **online**, as a runtime block stepped once per tick (:class:`MovingAverage`,
  :class:`ScalarKalman`);
- **batch**, over a whole series of samples at once (:func:`moving_average`,
  :func:`kalman_bank`), for offline work such as Q/R sweeps (:mod:`cell.analysis.sweep`) and
  tuning (:mod:`cell.analysis.autotune`).

:func:`kalman_bank` is the filter of :class:`ScalarKalman` vectorised across (Q, R) pairs with
numpy (one Python loop over time, none over pairs). The gain sequence does not depend on the
data, so :func:`gain_sequence` computes it once per pair and stops updating it when it has
converged (:data:`GAIN_RTOL`). A NaN sample is a stale tick: the batch filters hold their state
over it, as the runtime does when it skips a block whose input is stale.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from cell.runtime.blocks import COVARIANCE_BOUNDS, Block, Param
from cell.core.errors import ConfigError

#: Bounds of Q, R and P0 (:data:`~cell.runtime.blocks.COVARIANCE_BOUNDS`).
COV_MIN, COV_MAX = COVARIANCE_BOUNDS

#: Largest moving-average window accepted: one hour of 10 Hz samples.
MAX_SAMPLES = 36_000
#: Seed 004's moving average: 30 samples at 10 Hz.
MAF_SAMPLES = 30
#: Relative change below which the gain sequence counts as converged.
GAIN_RTOL = 1e-15


class MovingAverage(Block):
    r"""Moving average of the last ``samples`` inputs (seed 004, eq. 1).

    .. math:: \bar y[i] = \frac{1}{M}\sum_{j=0}^{M-1} y[i-j]

    Until ``M`` samples have arrived the mean covers the samples so far. Changing ``M``
    keeps the window: a shorter one drops the oldest samples, a longer one fills up.
    """

    kind = "moving_average"
    family = "filter"
    keeps_input_unit = True
    PARAMS = {
        "samples": Param("samples", int, "window length M in samples", ge=1, le=MAX_SAMPLES),
    }

    def __init__(self, name: str, source: str, samples: int = 30, rate: str = "MED") -> None:
        super().__init__(name, [source], [name], rate)
        self.source = source
        self.samples = self.PARAMS["samples"].check(samples)
        self._window: collections.deque[float] = collections.deque(maxlen=self.samples)

    def _apply(self, checked: dict[str, Any]) -> None:
        super()._apply(checked)
        self._window = collections.deque(self._window, maxlen=self.samples)

    def _step(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        self._window.append(inputs[self.source])
        return {self.name: math.fsum(self._window) / len(self._window)}

    def state(self) -> dict[str, Any]:
        return {"filled": len(self._window)}


class ScalarKalman(Block):
    r"""Textbook scalar Kalman filter of seed 004, eqs. (2)-(4), with :math:`A = C = 1`.

    Prediction (eq. 3) and correction (eq. 4):

    .. math::
        P_{k|k-1} = P_{k-1|k-1} + Q, \quad
        K_k = \frac{P_{k|k-1}}{P_{k|k-1} + R}, \quad
        \hat x_{k|k} = \hat x_{k-1|k-1} + K_k (y_k - \hat x_{k-1|k-1}), \quad
        P_{k|k} = (1 - K_k) P_{k|k-1}

    The first sample sets :math:`\hat x_0 = y_0` and :math:`P_0`. Defaults are the paper's
    best pair, Q = 1e-6 and R = 1e-4. Changing Q or R keeps the estimate and P. An input so
    large that the estimate leaves the float range resets the filter (the next sample starts
    it again) and marks that tick invalid; :math:`0 \le K \le 1` keeps :math:`P \ge 0`.
    """

    kind = "kalman"
    family = "filter"
    keeps_input_unit = True
    PARAMS = {
        "Q": Param("Q", float, "process noise covariance", ge=COV_MIN, le=COV_MAX),
        "R": Param("R", float, "measurement noise covariance", ge=COV_MIN, le=COV_MAX),
    }

    def __init__(
        self,
        name: str,
        source: str,
        Q: float = 1e-6,
        R: float = 1e-4,
        P0: float = 1.0,
        rate: str = "MED",
    ) -> None:
        super().__init__(name, [source], [name], rate)
        self.source = source
        self.Q = self.PARAMS["Q"].check(Q)
        self.R = self.PARAMS["R"].check(R)
        self.P0 = Param("P0", float, "initial covariance", ge=COV_MIN, le=COV_MAX).check(P0)
        self.x: float | None = None
        self.P = self.P0
        self.K = 0.0
        self.n = 0
        self.resets = 0

    def _step(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        y = inputs[self.source]
        if self.x is None:
            self.x, self.P, self.K = y, self.P0, 1.0
        else:
            P_prior = self.P + self.Q
            self.K = P_prior / (P_prior + self.R)
            x = self.x + self.K * (y - self.x)
            if not math.isfinite(x):  # an input beyond the float range: start again
                self.x, self.P, self.resets = None, self.P0, self.resets + 1
                raise ArithmeticError(f"non-finite estimate from input {y!r}; filter reset")
            self.x = x
            self.P = (1.0 - self.K) * P_prior
        self.n += 1
        return {self.name: self.x}

    def steady_state_gain(self) -> float:
        """Gain the filter converges to for the current Q and R (:func:`steady_state_gain`)."""
        return float(steady_state_gain(self.Q, self.R))

    def state(self) -> dict[str, Any]:
        return {"x": self.x, "P": self.P, "K": self.K, "n": self.n,
                "K_steady": self.steady_state_gain()}


def native_filters(sources: tuple[str, ...] = ("EXH_BP_L", "EXH_BP_R")) -> list[Block]:
    """The cell's default native filters: a 30-sample moving average and a Kalman filter per bank."""
    blocks: list[Block] = []
    for src in sources:
        blocks.append(MovingAverage(f"{src}_MAF", src, samples=30))
        blocks.append(ScalarKalman(f"{src}_Kalman", src))
    return blocks


# -- batch versions -------------------------------------------------------------------------
def as_samples(values: Sequence[float | None] | np.ndarray) -> np.ndarray:
    """A float array from samples, ``None`` (a stale tick) becoming NaN."""
    if isinstance(values, np.ndarray):
        return np.asarray(values, dtype=float).ravel()
    return np.array([np.nan if v is None else float(v) for v in values], dtype=float)


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
    r"""Gain the scalar filter converges to: the fixed point of the Riccati recursion.

    :math:`P^-` solves :math:`(P^-)^2 - Q P^- - Q R = 0`; the gain is :math:`P^-/(P^- + R)`.
    Scalars or arrays (element-wise); :meth:`ScalarKalman.steady_state_gain` is this for one
    filter.
    """
    q = np.asarray(Q, dtype=float)
    r = np.asarray(R, dtype=float)
    p_prior = (q + np.sqrt(q * q + 4.0 * q * r)) / 2.0
    return p_prior / (p_prior + r)


def kalman_bank(
    y: Sequence[float | None] | np.ndarray, Q: Any, R: Any, P0: Any = 1.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""Run the scalar Kalman filter of seed 004 (eqs. 2-4) for many (Q, R) pairs at once.

    The same filter as :class:`ScalarKalman`: the first valid sample sets
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
    """Seed 004 eq. (1) as :class:`MovingAverage` runs it: the mean of the last ``samples``
    valid samples (fewer at the start); NaN at stale ticks."""
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
