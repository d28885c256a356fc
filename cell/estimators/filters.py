"""Native back-pressure filters: the moving average and the scalar Kalman filter of seed 004."""

from __future__ import annotations

import collections
import math
from typing import Any

from ..blocks import Block, Param

#: Largest moving-average window accepted: one hour of 10 Hz samples.
MAX_SAMPLES = 36_000


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
    best pair, Q = 1e-6 and R = 1e-4. Changing Q or R keeps the estimate and P.
    """

    kind = "kalman"
    family = "filter"
    keeps_input_unit = True
    PARAMS = {
        "Q": Param("Q", float, "process noise covariance", gt=0.0),
        "R": Param("R", float, "measurement noise covariance", gt=0.0),
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
        self.P0 = Param("P0", float, "initial covariance", gt=0.0).check(P0)
        self.x: float | None = None
        self.P = self.P0
        self.K = 0.0
        self.n = 0

    def _step(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        y = inputs[self.source]
        if self.x is None:
            self.x, self.P, self.K = y, self.P0, 1.0
        else:
            P_prior = self.P + self.Q
            self.K = P_prior / (P_prior + self.R)
            self.x = self.x + self.K * (y - self.x)
            self.P = (1.0 - self.K) * P_prior
        self.n += 1
        return {self.name: self.x}

    def steady_state_gain(self) -> float:
        """Gain the filter converges to for the current Q and R (scalar Riccati fixed point)."""
        P_prior = (self.Q + math.sqrt(self.Q * self.Q + 4.0 * self.Q * self.R)) / 2.0
        return P_prior / (P_prior + self.R)

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
