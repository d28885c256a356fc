"""Sliding-window statistics of a CyFlex-style running average (seed 004, Figure 2).

:class:`RunningStats` is standalone: it knows nothing of scripts or channels. Feed it
``add(t, value)`` once per tick and read the 22 statistics of Figure 2 with
:meth:`RunningStats.values` (in :data:`SUFFIXES` order) or :meth:`RunningStats.as_dict`.
Before the window is full the statistics cover the samples so far.
"""

from __future__ import annotations

import collections
import math
from typing import Any

from cell.core.errors import ParamError
from cell.scripts.expr import SUFFIXES

#: Largest window accepted: one hour of 10 Hz samples (as the native moving average).
MAX_SAMPLES = 36_000

_NAN = math.nan
_INDEX = {s: k for k, s in enumerate(SUFFIXES)}


class RunningStats:
    r"""Statistics of the last ``samples`` values of a signal sampled at ``rate_hz``.

    Parameters
    ----------
    samples:
        Window length :math:`N` (1 to :data:`MAX_SAMPLES`). Seed 004's Kalman filter uses
        a one-sample window whose ``FV`` is the previous estimate (Figure 2).
    rate_hz:
        Sampling rate; gives ``RA`` and the rectangle width :math:`\Delta t = 1/\text{rate}`
        of ``IN``.

    Notes
    -----
    With the window's :math:`n` samples :math:`(t_i, v_i)`, :math:`\tau_i = t_i - t_1`:

    * ``AV`` mean, ``MN``/``MX`` extremes, ``RN = MX - MN``, ``SD`` sample standard
      deviation (ddof 1; 0 for one sample), ``CV = SD/AV`` (NaN when ``AV`` is 0);
    * ``ST``/``EN`` first and last sample time, ``TN``/``TX`` time of the first minimum and
      maximum, ``IV``/``FV`` first and last value, ``DL = FV - IV``;
    * ``IN`` = :math:`\sum v_i \Delta t`, ``IT`` trapezoidal integral of :math:`v(t)`;
    * ``CL``, ``CO``: least-squares line :math:`v = CO + CL\,\tau` (``CL = 0`` and
      ``CO = AV`` when :math:`n < 2`); ``ES`` = SSR/(n-2), ``EO`` = :math:`\sqrt{ES}`,
      ``EL`` = :math:`EO/\sqrt{\sum (\tau_i - \bar\tau)^2}` (all three 0 when :math:`n < 3`);
    * ``RA`` the rate in Hz, ``NM`` = :math:`n`.

    With no sample every statistic is NaN except ``RA`` and ``NM`` (0).
    """

    SUFFIXES = SUFFIXES

    def __init__(self, samples: int, rate_hz: float) -> None:
        if isinstance(samples, bool) or not isinstance(samples, int) or not (
            1 <= samples <= MAX_SAMPLES
        ):
            raise ParamError("samples", f"must be a whole number 1..{MAX_SAMPLES}, got {samples!r}")
        if isinstance(rate_hz, bool) or not isinstance(rate_hz, (int, float)) or not (
            math.isfinite(rate_hz) and rate_hz > 0
        ):
            raise ParamError("rate_hz", f"must be a positive finite number, got {rate_hz!r}")
        self.samples = samples
        self.rate_hz = float(rate_hz)
        self._t: collections.deque[float] = collections.deque(maxlen=samples)
        self._v: collections.deque[float] = collections.deque(maxlen=samples)

    @property
    def n(self) -> int:
        """Number of samples in the window."""
        return len(self._v)

    def add(self, t: float, value: float) -> None:
        """Append one sample taken at bus time ``t``; the oldest leaves a full window."""
        self._t.append(float(t))
        self._v.append(float(value))

    def clear(self) -> None:
        self._t.clear()
        self._v.clear()

    def window(self) -> list[tuple[float, float]]:
        """The window's ``(t, value)`` pairs, oldest first."""
        return list(zip(self._t, self._v))

    def load(self, pairs: list[tuple[float, float]]) -> None:
        """Replace the window by ``pairs`` (the newest ``samples`` of them are kept)."""
        self.clear()
        for t, v in pairs:
            self.add(t, v)

    def values(self) -> list[float]:
        """The 22 statistics in :data:`SUFFIXES` order."""
        n = len(self._v)
        rate = self.rate_hz
        if n == 0:
            out = [_NAN] * len(SUFFIXES)
            out[_INDEX["RA"]] = rate
            out[_INDEX["NM"]] = 0.0
            return out
        if n == 1:
            v = self._v[0]
            t = self._t[0]
            cv = 0.0 if v else _NAN
            return [v, v, v, 0.0, 0.0, cv, t, t, t, t, v, v, 0.0, v / rate, 0.0,
                    0.0, 0.0, 0.0, 0.0, v, rate, 1.0]
        vs = list(self._v)
        ts = list(self._t)
        fsum = math.fsum
        total = fsum(vs)
        av = total / n
        mn = min(vs)
        mx = max(vs)
        dev = [v - av for v in vs]
        sd = math.sqrt(fsum([d * d for d in dev]) / (n - 1))
        cv = sd / av if av else _NAN
        st = ts[0]
        it = fsum([(vs[k] + vs[k + 1]) * 0.5 * (ts[k + 1] - ts[k]) for k in range(n - 1)])
        tau = [t - st for t in ts]
        tbar = fsum(tau) / n
        dt = [x - tbar for x in tau]
        stt = fsum([d * d for d in dt])
        if stt > 0.0:
            cl = fsum([a * b for a, b in zip(dt, dev)]) / stt
        else:
            cl = 0.0
        co = av - cl * tbar
        if n >= 3:
            es = fsum([(v - co - cl * x) ** 2 for v, x in zip(vs, tau)]) / (n - 2)
            eo = math.sqrt(es)
            el = eo / math.sqrt(stt) if stt > 0.0 else _NAN
        else:
            es = eo = el = 0.0
        return [av, mn, mx, mx - mn, sd, cv, st, ts[-1], ts[vs.index(mn)], ts[vs.index(mx)],
                vs[0], vs[-1], vs[-1] - vs[0], total / rate, it, es, eo, el, cl, co, rate,
                float(n)]

    def as_dict(self) -> dict[str, float]:
        """The 22 statistics keyed by suffix."""
        return dict(zip(SUFFIXES, self.values()))

    def state(self) -> dict[str, Any]:
        return {"samples": self.samples, "rate_hz": self.rate_hz, "filled": self.n}
