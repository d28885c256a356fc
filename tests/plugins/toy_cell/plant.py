"""A damped oscillator driven by a square-wave force: the test-only plugin's plant.

    x'' + 2 zeta omega x' + omega^2 x = omega^2 F

written as ``oscillator_rhs(t, x, u, p)`` for x = (position, velocity), u = (force,). The
plant steps it exactly for a held force (scipy's matrix exponential); the observer's model
integrates the same function with its own, slightly wrong, parameters.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from cell.plant import Composition, Plant


@dataclass(frozen=True)
class ToyParams:
    period: float = 0.01
    omega: float = 2.0
    """Natural frequency, rad/s."""
    zeta: float = 0.1
    """Damping ratio."""
    force: float = 1.0
    """Square-wave force amplitude, N; its period is ``force_period``."""
    force_period: float = 8.0
    noise: float = 0.05
    """Position sensor noise std, m."""


def oscillator_rhs(t, x, u, p: Mapping):
    """dx/dt of (position, velocity) for force u[0], with p = {"omega": .., "zeta": ..}."""
    omega, zeta = p["omega"], p["zeta"]
    return np.array([x[1], -2.0 * zeta * omega * x[1] - omega**2 * (x[0] - u[0])])


class Oscillator(Plant):
    inputs = ("TOY_FORCE_OFFSET",)
    outputs = ("TOY_POS", "TOY_FORCE", "TOY_POS_TRUE", "TOY_VEL_TRUE")

    def __init__(self, params: ToyParams | None = None, seed: int = 0) -> None:
        p = self.params = params or ToyParams()
        super().__init__("oscillator", p.period)
        a = np.array([[0.0, 1.0], [-p.omega**2, -2.0 * p.zeta * p.omega]])
        b = np.array([[0.0], [p.omega**2]])
        m = expm(np.block([[a, b], [np.zeros((1, 3))]]) * p.period)
        self._ad, self._bd = m[:2, :2], m[:2, 2]
        self._rng = np.random.default_rng([seed, 0x70])
        self.x = np.zeros(2)
        self.force = self._force(0.0, {})
        self.noise = 0.0

    def _force(self, t: float, u: Mapping[str, float]) -> float:
        p = self.params
        square = p.force if (t % p.force_period) < p.force_period / 2 else -p.force
        return square + u.get("TOY_FORCE_OFFSET", 0.0)

    def step(self, t, u):
        self.x = self._ad @ self.x + self._bd * self.force  # the force held over the step
        self.force = self._force(t, u)
        self.noise = float(self._rng.normal(0.0, self.params.noise))

    def output(self):
        return {"TOY_POS": self.x[0] + self.noise, "TOY_FORCE": self.force,
                "TOY_POS_TRUE": self.x[0], "TOY_VEL_TRUE": self.x[1]}


    @classmethod
    def composition(cls, seed: int = 0) -> Composition:
        return Composition("toy", [cls(seed=seed)], duration=40.0,
                           about={"duty": "square", "seed": seed})
