"""The test-only plugin's observer: an EKF of the oscillator on the cell's estimator core.

Its model reuses the plant's equation (:func:`oscillator_rhs`) with its own parameters: the
natural frequency 5 % off, as an observer's model of a real plant is.
"""

from __future__ import annotations

import numpy as np

from cell.estimators.core import Model
from cell.estimators.observer import ObserverBlock

from .plant import ToyParams, oscillator_rhs

MODEL_PARAMS = {"omega": ToyParams().omega * 1.05, "zeta": ToyParams().zeta}


def toy_observer() -> ObserverBlock:
    model = Model(states=("POS", "VEL"), inputs=("TOY_FORCE",), outputs=("TOY_POS",),
                  f=oscillator_rhs, h=lambda t, x, u, p: np.array([x[0]]),
                  params=MODEL_PARAMS, units={"POS": "m", "VEL": "m/s", "TOY_POS": "m"})
    return ObserverBlock("toy", model, prefix="TOY_EST", Q=[1e-6, 1e-3],
                         R=[ToyParams().noise ** 2], P0=[1.0, 1.0])
