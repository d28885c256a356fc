"""The three-way catalyst of the ``si-turbo`` engine and its sensors (seed 000, section III).

Signal chain (Figure 2's layout)::

    LAMBDA_ENGINE_TRUE ─▶ λ_pre sensor ─────────────────────────────▶ LAMBDA_PRE
    EXH_MASS_FLOW_TRUE ─▶ ECU air-mass estimate ───────────────────▶ EXH_MASS_FLOW
    T_EXH_TRUE ─────────▶ inlet thermocouple ──────────────────────▶ T_EXH
                 └─▶ 5 thermal cells (eqs. 4, 13, 14) ─▶ mid-brick thermocouple ─▶ T_CAT
                 └─▶ 3 oxygen-storage cells (eqs. 12, 15-17) ─▶ λ_mid sensor ─▶ LAMBDA_MID

and the truth: ``SOX_1_TRUE`` .. ``SOX_3_TRUE`` (φ of each cell), ``SOX_TRUE`` (their
mean), ``OSC_TRUE`` (normalised to the fresh catalyst), ``LAMBDA_MID_TRUE`` and
``T_CAT_TRUE`` (the noise-free, lag-free values the sensors measure).

The equations are :mod:`cell.plant.catalyst_model`'s, stepped with explicit Euler at the plant's
100 Hz (the gas balances are solved exactly within each step). OSC is a parameter,
normalised to the fresh catalyst (``--osc 0.6``: aged); it can drift slowly
(``--osc-drift``, per hour of running) and steps to the value of a scenario command
(``testcell scenario osc=0.5``, input ``OSC``) when one arrives.

Sensors (each a first-order lag plus white Gaussian noise, from a seeded generator)
-----------------------------------------------------------------------------------
=================  ==================  ===============  ====================================
signal             lag (time const.)   noise (1σ)       why
=================  ==================  ===============  ====================================
``LAMBDA_PRE``     0.10 s              0.002            wide-band λ sensor (LSU 4.9 class:
``LAMBDA_MID``     0.10 s              0.002            < 100 ms response, ±0.007 at λ = 1)
``EXH_MASS_FLOW``  0.05 s              1 % of value     the ECU's air-mass estimate + fuel
``T_EXH``          2.0 s               1 °C             3 mm sheathed thermocouple in gas
``T_CAT``          2.0 s               1 °C             thermocouple in mid-brick (cell 3)
=================  ==================  ===============  ====================================
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from cell.core.errors import ConfigError
from cell.plant.base import Plant, lag_factor
from cell.plant.catalyst_model import (
    TWCKinetics,
    TWCThermal,
    efficiency,
    feed_gas,
    gas_concentration,
    lambda_of,
    rate_constants,
    residence_time,
    storage_cell,
)

KELVIN = 273.15
_NOISE_BLOCK = 2048


@dataclass(frozen=True)
class SensorParams:
    """Lag time constants (s) and noise standard deviations of the catalyst's sensors."""

    tau_lambda: float = 0.10
    noise_lambda: float = 0.002
    tau_flow: float = 0.05
    noise_flow_rel: float = 0.01
    tau_temp: float = 2.0
    noise_temp: float = 1.0
    t_cat_cell: int = 2
    """Thermal cell (0-based) of the mid-brick thermocouple: the third of five."""


@dataclass(frozen=True)
class CatalystParams:
    """Everything the catalyst plant needs: kinetics, thermal constants, sensors, OSC."""

    period: float = 0.01
    """Step period, s (100 Hz: the oxygen storage saturates within a fraction of a second
    in fuel cut)."""
    kinetics: TWCKinetics = field(default_factory=TWCKinetics)
    thermal: TWCThermal = field(default_factory=TWCThermal)
    sensors: SensorParams = field(default_factory=SensorParams)
    osc: float = 1.0
    """OSC at the start, normalised to the fresh catalyst (``--osc``)."""
    osc_drift: float = 0.0
    """Change of OSC per hour of running, normalised (``--osc-drift``; ageing: negative)."""
    osc_min: float = 0.05
    """OSC never drifts below this (a dead catalyst still has some storage)."""
    phi0: float = 0.5
    """φ of every cell at the start."""
    T_cat0: float | None = None
    """Substrate temperature at the start, °C; ``None``: ambient (a cold start, as the
    FTP-75's)."""


class Catalyst(Plant):
    """The three-way catalyst: thermal and oxygen-storage dynamics, sensors and truth.

    Parameters
    ----------
    params:
        :class:`CatalystParams`.
    seed:
        Seeds the sensor noise.
    """

    inputs = ("EXH_MASS_FLOW_TRUE", "T_EXH_TRUE", "LAMBDA_ENGINE_TRUE", "OSC")
    outputs = ("LAMBDA_PRE", "LAMBDA_MID", "EXH_MASS_FLOW", "T_EXH", "T_CAT",
               "SOX_1_TRUE", "SOX_2_TRUE", "SOX_3_TRUE", "SOX_TRUE", "OSC_TRUE",
               "LAMBDA_MID_TRUE", "T_CAT_TRUE")

    def __init__(self, params: CatalystParams | None = None, seed: int = 0,
                 name: str = "catalyst") -> None:
        p = self.params = params or CatalystParams()
        super().__init__(name, p.period)
        k, th = p.kinetics, p.thermal
        if k.cells != 3:
            raise ConfigError(f"catalyst: the truth frames carry three oxygen cells, got {k.cells}")
        if not (math.isfinite(p.osc) and p.osc_min <= p.osc <= 2.0):
            raise ConfigError(f"--osc must be in [{p.osc_min:g}, 2] (normalised to the fresh "
                              f"catalyst), got {p.osc}")
        if not math.isfinite(p.osc_drift) or abs(p.osc_drift) > 10.0:
            raise ConfigError(f"--osc-drift must be within ±10 per hour, got {p.osc_drift}")
        self.osc = float(p.osc)
        self._osc_cmd: float | None = None
        self.phi = [p.phi0] * k.cells
        T0 = th.T_amb if p.T_cat0 is None else p.T_cat0
        self.T_cat = [T0] * th.cells
        # thermal constants (eq. 14)
        solid = th.rho_s * (1.0 - th.epsilon) * th.c_s
        diameter = math.sqrt(4.0 * k.area / math.pi)
        self._k_conv = th.h * th.A_geo / solid
        self._k_reac = th.K_reac / solid
        self._k_out = 4.0 * th.h_out / (diameter * solid)
        self._beta_k = th.h * th.A_geo * k.area * (k.length / th.cells) / th.c_pg
        # oxygen cell centres on the thermal grid: interpolation weights
        n_t, n_o = th.cells, k.cells
        self._interp = []
        for j in range(n_o):
            x = (j + 0.5) / n_o * n_t - 0.5  # in thermal-cell index units
            i0 = min(max(int(math.floor(x)), 0), n_t - 2)
            w = min(max(x - i0, 0.0), 1.0)
            self._interp.append((i0, w))
        s = p.sensors
        self._a_lam = lag_factor(p.period, s.tau_lambda)
        self._a_flow = lag_factor(p.period, s.tau_flow)
        self._a_temp = lag_factor(p.period, s.tau_temp)
        self._rng = np.random.default_rng([seed, 0x3C])
        self._noise: list[list[float]] = []
        self._ni = _NOISE_BLOCK
        self.lam_out = 1.0
        self.t = 0.0

    # -- start and step ---------------------------------------------------------------------
    def start(self, u: Mapping[str, float]) -> None:
        self.mdot = u.get("EXH_MASS_FLOW_TRUE", 0.005)
        self.T_exh = u.get("T_EXH_TRUE", self.params.thermal.T_amb)
        self.lam_in = u.get("LAMBDA_ENGINE_TRUE", 1.0)
        self._storage()
        self.s_lam_pre = self.lam_in
        self.s_lam_mid = self.lam_out
        self.s_flow = self.mdot
        self.s_T_exh = self.T_exh
        self.s_T_cat = self.T_cat[self.params.sensors.t_cat_cell]
        self._draw()

    def _draw(self) -> None:
        if self._ni >= len(self._noise):
            self._noise = self._rng.standard_normal((_NOISE_BLOCK, 5)).tolist()
            self._ni = 0
        self.noise = self._noise[self._ni]
        self._ni += 1

    def step(self, t: float, u: Mapping[str, float]) -> None:
        p = self.params
        dt = self.period
        self.t = t
        self.mdot = mdot = max(u["EXH_MASS_FLOW_TRUE"], 0.0)
        self.T_exh = u["T_EXH_TRUE"]
        self.lam_in = u["LAMBDA_ENGINE_TRUE"]
        cmd = u.get("OSC")
        if cmd is not None and cmd != self._osc_cmd:
            self._osc_cmd = cmd
            self.osc = min(max(cmd, p.osc_min), 2.0)
        if p.osc_drift:
            self.osc = max(self.osc + p.osc_drift * dt / 3600.0, p.osc_min)
        # thermal model, eqs. 13-14 (explicit Euler for the substrate)
        th = p.thermal
        beta = self._beta_k / max(mdot, 1e-5)
        q_reac = self._k_reac * mdot
        T_g = self.T_exh
        T_cat = self.T_cat
        for i in range(th.cells):
            Tc = T_cat[i]
            T_g = (T_g + beta * Tc) / (1.0 + beta)
            dT = (-self._k_conv * (Tc - T_g) + q_reac * efficiency(Tc, th)
                  - self._k_out * (Tc - th.T_amb))
            T_cat[i] = Tc + dt * dT
        # oxygen storage, eqs. 15-17
        dphi = self._storage()
        phi = self.phi
        for j in range(len(phi)):
            phi[j] = min(max(phi[j] + dt * dphi[j], 0.0), 1.0)
        # sensors
        self._draw()
        self.s_lam_pre += self._a_lam * (self.lam_in - self.s_lam_pre)
        self.s_lam_mid += self._a_lam * (self.lam_out - self.s_lam_mid)
        self.s_flow += self._a_flow * (mdot - self.s_flow)
        self.s_T_exh += self._a_temp * (self.T_exh - self.s_T_exh)
        self.s_T_cat += self._a_temp * (T_cat[p.sensors.t_cat_cell] - self.s_T_cat)

    def _storage(self) -> list[float]:
        """Outlet λ (into ``lam_out``) and dφ/dt of each cell at the present state."""
        k = self.params.kinetics
        T_mean = sum(self.T_cat) / len(self.T_cat) + KELVIN
        c0 = gas_concentration(T_mean, k)
        tau = residence_time(self.mdot, c0, k)
        o2, co, carbon = feed_gas(self.lam_in, c0, k)
        osc = self.osc * k.osc_fresh
        dphi = []
        for j, (i0, w) in enumerate(self._interp):
            T_j = self.T_cat[i0] * (1.0 - w) + self.T_cat[i0 + 1] * w + KELVIN
            o2, co, d = storage_cell(self.phi[j], osc, o2, co, carbon, tau, c0,
                                     rate_constants(T_j, k))
            dphi.append(d)
        self.lam_out = lambda_of(o2, co, carbon)
        return dphi

    def output(self) -> dict[str, float]:
        s = self.params.sensors
        n = self.noise
        phi = self.phi
        return {
            "LAMBDA_PRE": self.s_lam_pre + s.noise_lambda * n[0],
            "LAMBDA_MID": self.s_lam_mid + s.noise_lambda * n[1],
            "EXH_MASS_FLOW": max(self.s_flow * (1.0 + s.noise_flow_rel * n[2]), 0.0),
            "T_EXH": self.s_T_exh + s.noise_temp * n[3],
            "T_CAT": self.s_T_cat + s.noise_temp * n[4],
            "SOX_1_TRUE": phi[0],
            "SOX_2_TRUE": phi[1],
            "SOX_3_TRUE": phi[2],
            "SOX_TRUE": (phi[0] + phi[1] + phi[2]) / 3.0,
            "OSC_TRUE": self.osc,
            "LAMBDA_MID_TRUE": self.lam_out,
            "T_CAT_TRUE": self.T_cat[s.t_cat_cell],
        }
