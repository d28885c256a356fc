r"""Adaptive back-pressure filter: seed 004's "intelligent combination" of its two filters.

Seed 004 ("Conclusion and future works") finds that the Kalman filter follows transients
with less lag than the 30-sample moving average, which smooths more at steady state, and
proposes "an intelligent combination of Kalman filter and moving average filter to achieve
suitable transient and steady-state responses" as future work. :class:`AdaptiveFilter` is
one such combination: a scalar Kalman filter whose covariance is reset by a CUSUM step
detector on its innovations.

- A scalar Kalman filter with :math:`A = C = 1` and process noise :math:`Q = 0` has gain
  :math:`K_n = 1/n` after a reset: its estimate is the running mean of the :math:`n` samples
  since the reset, a moving average whose window grows. At steady state the filter is
  that average, with the window capped at ``samples`` (the gain never falls below
  ``1/samples``, an exponential average with the variance of a ``2·samples - 1``-sample
  moving average). With the default 30 it smooths about twice as much (in variance) as
  the paper's 30-sample moving average.
- A two-sided CUSUM on the normalised innovations :math:`z_k = (y_k - \hat x_{k-1})/\hat\sigma`
  (clipped at ±``clip`` so that a single spike cannot raise an alarm) detects a change of
  the level:

  .. math:: S^+_k = \max(0, S^+_{k-1} + z_k - \kappa), \quad
            S^-_k = \max(0, S^-_{k-1} - z_k - \kappa), \quad \text{alarm if } S^\pm_k > h.

- After an alarm, and for ``hold_s`` seconds after the last one, the gain is ``gain_fast``
  (a covariance reset: the filter behaves like a Kalman filter with a large Q, faster than
  the paper's, whose steady gain is 0.095 at 10 Hz). Then the window grows again from
  ``1/gain_fast`` samples to ``samples``.
- :math:`\hat\sigma` is learned online from the first differences of the input,
  :math:`\operatorname{var}(y_k - y_{k-1}) = 2\sigma^2` for white noise, winsorised at
  4 :math:`\hat\sigma` against spikes and level steps.

Its outputs ``EXH_BP_L_Adaptive``/``EXH_BP_R_Adaptive`` are channels only (no DBC signal):
they appear in ``/channels`` and can be the PI controller's feedback.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

from cell.runtime.blocks import Block, Param

#: Rate of the noise-scale estimate (per tick): a time constant of 10 s at 10 Hz.
_SIGMA_RATE = 0.01


class AdaptiveFilter(Block):
    """Kalman/moving-average blend switched by a CUSUM step detector (seed 004 future work).

    Parameters
    ----------
    name:
        Block and output channel name (``<source>_Adaptive`` by convention).
    source:
        Input channel (raw back-pressure).
    samples:
        Longest averaging window at steady state, samples (the gain's floor is 1/samples).
    gain_fast:
        Gain after a detected change, in (0, 1].
    threshold:
        CUSUM alarm threshold h, in noise standard deviations.
    drift:
        CUSUM drift (allowance) κ, in noise standard deviations.
    hold_s:
        Seconds of bus time after the last alarm during which the gain stays ``gain_fast``.
    clip:
        Innovations are clipped to ±clip standard deviations before the CUSUM.
    rate:
        Runtime task (default MED, 10 Hz).
    """

    kind = "adaptive"
    family = "filter"
    keeps_input_unit = True
    PARAMS: ClassVar[dict[str, Param]] = {
        "samples": Param("samples", int, "steady-state window, samples", ge=1, le=36_000),
        "gain_fast": Param("gain_fast", float, "gain after a detected change", gt=0.0, le=1.0),
        "threshold": Param("threshold", float, "CUSUM alarm threshold, std", gt=0.0, le=1000.0),
        "drift": Param("drift", float, "CUSUM drift, std", ge=0.0, le=100.0),
        "hold_s": Param("hold_s", float, "fast-gain hold after an alarm, s", ge=0.0, le=3600.0),
        "clip": Param("clip", float, "innovation clip before the CUSUM, std", gt=0.0, le=100.0),
    }

    def __init__(
        self,
        name: str,
        source: str,
        samples: int = 30,
        gain_fast: float = 0.25,
        threshold: float = 5.0,
        drift: float = 0.5,
        hold_s: float = 2.0,
        clip: float = 3.0,
        rate: str = "MED",
    ) -> None:
        super().__init__(name, [source], [name], rate)
        self.source = source
        checked = self.validate({
            "samples": samples, "gain_fast": gain_fast, "threshold": threshold,
            "drift": drift, "hold_s": hold_s, "clip": clip,
        })
        self._apply(checked)
        self.x: float | None = None
        self.n = 0.0  # effective window (1/gain) of the averaging phase
        self.var: float | None = None  # noise variance estimate
        self.s_pos = 0.0
        self.s_neg = 0.0
        self.alarms = 0
        self.last_alarm: float | None = None
        self.gain = 1.0
        self._y_last: float | None = None

    def _step(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        y = inputs[self.source]
        if self.x is None:
            self.x, self.n, self._y_last, self.gain = y, 1.0, y, 1.0
            return {self.name: y}
        # noise scale from first differences, winsorised at 4 sigma
        d2 = (y - self._y_last) ** 2 / 2.0
        self._y_last = y
        if self.var is None:
            self.var = max(d2, 1e-12)
        else:
            self.var += _SIGMA_RATE * (min(d2, 16.0 * self.var) - self.var)
        sigma = math.sqrt(self.var) if self.var > 0 else 1e-6
        nu = y - self.x
        z = min(max(nu / sigma, -self.clip), self.clip)
        self.s_pos = max(0.0, self.s_pos + z - self.drift)
        self.s_neg = max(0.0, self.s_neg - z - self.drift)
        if self.s_pos > self.threshold or self.s_neg > self.threshold:
            self.s_pos = self.s_neg = 0.0
            self.alarms += 1
            self.last_alarm = t
        if self.last_alarm is not None and t - self.last_alarm < self.hold_s - 1e-9:
            self.n = 1.0 / self.gain_fast
            gain = self.gain_fast
        else:
            self.n = min(self.n + 1.0, float(self.samples))
            gain = 1.0 / self.n
        self.gain = gain
        self.x += gain * nu
        return {self.name: self.x}

    def state(self) -> dict[str, Any]:
        return {
            "x": self.x, "gain": self.gain, "window": self.n,
            "sigma": None if self.var is None else math.sqrt(self.var),
            "cusum_pos": self.s_pos, "cusum_neg": self.s_neg, "alarms": self.alarms,
            "last_alarm": self.last_alarm,
        }


def adaptive_filters(sources: tuple[str, ...] = ("EXH_BP_L", "EXH_BP_R"), **settings: Any
                     ) -> list[AdaptiveFilter]:
    """One :class:`AdaptiveFilter` per bank, named ``<source>_Adaptive``."""
    return [AdaptiveFilter(f"{src}_Adaptive", src, **settings) for src in sources]
