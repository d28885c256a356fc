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

Plant variants (what an observer cannot know; defaults keep the plant above exactly)
-----------------------------------------------------------------------------------
:func:`catalyst_params` builds :class:`CatalystParams` from the engine profile's options
(:data:`CATALYST_OPTIONS`, ``testcell sim``/``up --engine si-turbo``):

- ``--lambda-sensor lambda|composition``: the λ sensors' first-order lag acts on λ itself
  (default) or on the gas composition they see. With ``composition`` the sensor lags the
  mole fractions of O₂, CO and carbon (equivalently, as both are linear in them, the oxygen
  numerator :math:`N = 2([O_2] + [CO_2]) + [CO]` and the carbon denominator
  :math:`D = 2([CO] + [CO_2])` of eq. 12) and reports :math:`N_s / D_s`: leaving fuel cut,
  where the gas carries little carbon, λ falls faster than a lag on λ lets it.
- ``--lambda-dead-time S`` (0..0.5): the gas's transport to both λ sensors and their
  electronics, a dead time before the lag (rounded to the 10 ms plant step).
- ``--lambda-tau-scale X`` (0.5..2): both λ sensors' time constant times X.
- ``--kinetics-scale X`` (0.3..3): both reaction rates (A₁, A₂ of eq. 16) times X.
- ``--storage-cells N`` (1..12): oxygen-storage cells along the brick (the paper's three by
  default). ``SOX_1_TRUE`` .. ``SOX_3_TRUE`` are then the mean φ over each third of the
  brick (the cells whose centres lie in it, or the cell holding the third's centre).
- ``--thermal-cells N`` (1..12): thermal cells (five by default); the mid-brick
  thermocouple sits in cell ``N // 2``.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from cell.core.errors import ConfigError
from cell.core.options import Option
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
LAMBDA_LAGS = ("lambda", "composition")
"""What a λ sensor's lag may act on (``--lambda-sensor``)."""


def _thirds(n: int) -> list[list[int]]:
    """The storage cells of each third of the brick: those whose centres lie in it, or the
    cell holding the third's centre (fewer than three cells)."""
    out = []
    for j in range(3):
        inside = [i for i in range(n) if j / 3 <= (i + 0.5) / n < (j + 1) / 3]
        out.append(inside or [min(int((j + 0.5) / 3 * n), n - 1)])
    return out


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
    lambda_lag: str = "lambda"
    """What the λ sensors' lag acts on: ``lambda`` or ``composition`` (module notes)."""
    dead_time_lambda: float = 0.0
    """Dead time of both λ sensors before their lag, s."""


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
        s = p.sensors
        if not (isinstance(k.cells, int) and 1 <= k.cells <= 12):
            raise ConfigError(f"--storage-cells must be 1..12, got {k.cells}")
        if not (isinstance(th.cells, int) and 1 <= th.cells <= 12):
            raise ConfigError(f"--thermal-cells must be 1..12, got {th.cells}")
        if not 0 <= s.t_cat_cell < th.cells:
            raise ConfigError(f"catalyst: the thermocouple's cell {s.t_cat_cell} is not one of "
                              f"the {th.cells} thermal cells")
        if s.lambda_lag not in LAMBDA_LAGS:
            raise ConfigError(f"--lambda-sensor must be one of {', '.join(LAMBDA_LAGS)}, got "
                              f"{s.lambda_lag!r}")
        if not (math.isfinite(s.dead_time_lambda) and 0.0 <= s.dead_time_lambda <= 0.5):
            raise ConfigError(f"--lambda-dead-time must be in [0, 0.5] s, got {s.dead_time_lambda}")
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
            i0 = min(max(int(math.floor(x)), 0), max(n_t - 2, 0))
            w = min(max(x - i0, 0.0), 1.0) if n_t > 1 else 0.0
            self._interp.append((i0, min(i0 + 1, n_t - 1), w))
        self._thirds = _thirds(n_o)
        self._a_lam = lag_factor(p.period, s.tau_lambda)
        self._composition = s.lambda_lag == "composition"
        self._delay = round(s.dead_time_lambda / p.period)
        self._plain = not self._composition and self._delay == 0
        self._queue: deque[tuple[float, ...]] = deque()
        self.gas_in = self.gas_out = (2.0, 2.0)
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
        self.s_gas = (*self.gas_in, *self.gas_out)
        seen = self.s_gas if self._composition else (self.lam_in, self.lam_out)
        self._queue = deque([seen] * self._delay)
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
        if self._plain:
            self.s_lam_pre += self._a_lam * (self.lam_in - self.s_lam_pre)
            self.s_lam_mid += self._a_lam * (self.lam_out - self.s_lam_mid)
        else:
            self._lambda_sensors()
        self.s_flow += self._a_flow * (mdot - self.s_flow)
        self.s_T_exh += self._a_temp * (self.T_exh - self.s_T_exh)
        self.s_T_cat += self._a_temp * (T_cat[p.sensors.t_cat_cell] - self.s_T_cat)

    def _lambda_sensors(self) -> None:
        """The λ sensors of a variant: dead time, then the lag on λ or on the gas's
        numerator and denominator of eq. 12 (module notes)."""
        a = self._a_lam
        if self._composition:
            seen = (*self.gas_in, *self.gas_out)
        else:
            seen = (self.lam_in, self.lam_out)
        if self._delay:
            self._queue.append(seen)
            seen = self._queue.popleft()
        if self._composition:
            g = self.s_gas = tuple(v + a * (w - v) for v, w in zip(self.s_gas, seen))
            self.s_lam_pre, self.s_lam_mid = g[0] / g[1], g[2] / g[3]
        else:
            self.s_lam_pre += a * (seen[0] - self.s_lam_pre)
            self.s_lam_mid += a * (seen[1] - self.s_lam_mid)

    def _storage(self) -> list[float]:
        """Outlet λ (into ``lam_out``) and dφ/dt of each cell at the present state."""
        k = self.params.kinetics
        T_mean = sum(self.T_cat) / len(self.T_cat) + KELVIN
        c0 = gas_concentration(T_mean, k)
        tau = residence_time(self.mdot, c0, k)
        o2, co, carbon = feed_gas(self.lam_in, c0, k)
        osc = self.osc * k.osc_fresh
        dphi = []
        for j, (i0, i1, w) in enumerate(self._interp):
            T_j = self.T_cat[i0] * (1.0 - w) + self.T_cat[i1] * w + KELVIN
            o2, co, d = storage_cell(self.phi[j], osc, o2, co, carbon, tau, c0,
                                     rate_constants(T_j, k))
            dphi.append(d)
        self.lam_out = lambda_of(o2, co, carbon)
        if not self._plain:
            d_in = 2.0 * feed_gas(self.lam_in, 1.0, k)[2]
            self.gas_in = (max(self.lam_in, 0.5) * d_in, d_in)
            self.gas_out = ((2.0 * o2 + 2.0 * carbon - co) / c0, 2.0 * carbon / c0)
        return dphi

    def output(self) -> dict[str, float]:
        s = self.params.sensors
        n = self.noise
        phi = self.phi
        if len(phi) != 3:
            phi = [sum(phi[i] for i in idx) / len(idx) for idx in self._thirds]
        return {
            "LAMBDA_PRE": self.s_lam_pre + s.noise_lambda * n[0],
            "LAMBDA_MID": self.s_lam_mid + s.noise_lambda * n[1],
            "EXH_MASS_FLOW": max(self.s_flow * (1.0 + s.noise_flow_rel * n[2]), 0.0),
            "T_EXH": self.s_T_exh + s.noise_temp * n[3],
            "T_CAT": self.s_T_cat + s.noise_temp * n[4],
            "SOX_1_TRUE": phi[0],
            "SOX_2_TRUE": phi[1],
            "SOX_3_TRUE": phi[2],
            "SOX_TRUE": sum(self.phi) / len(self.phi),
            "OSC_TRUE": self.osc,
            "LAMBDA_MID_TRUE": self.lam_out,
            "T_CAT_TRUE": self.T_cat[s.t_cat_cell],
        }


# -- plant variants ---------------------------------------------------------------------------
def _range(lo: float, hi: float, what: str):
    def check(v: float) -> str | None:
        if not (math.isfinite(v) and lo <= v <= hi):
            return f"must be in [{lo:g}, {hi:g}]{what}, got {v}"
        return None
    return check


def _cells_check(v: int) -> str | None:
    return None if 1 <= v <= 12 else f"must be 1..12, got {v}"


def _lag_check(v: str) -> str | None:
    return None if v in LAMBDA_LAGS else f"must be one of {', '.join(LAMBDA_LAGS)}, got {v!r}"


#: The catalyst's variant options (the engine profile's, module notes): key -> Option.
CATALYST_OPTIONS: tuple[Option, ...] = (
    Option("lambda_sensor", "--lambda-sensor", str, metavar="lambda|composition", check=_lag_check,
           help="what the λ sensors' lag acts on: λ (default) or the gas composition"),
    Option("lambda_dead_time", "--lambda-dead-time", float, metavar="S",
           check=_range(0.0, 0.5, " s"), help="dead time of both λ sensors, s (default 0)"),
    Option("lambda_tau_scale", "--lambda-tau-scale", float, metavar="X",
           check=_range(0.5, 2.0, ""), help="both λ sensors' time constant (0.1 s) times X "
                                            "(default 1)"),
    Option("kinetics_scale", "--kinetics-scale", float, metavar="X", check=_range(0.3, 3.0, ""),
           help="the catalyst's reaction rates (A1, A2) times X (default 1)"),
    Option("storage_cells", "--storage-cells", int, metavar="N", check=_cells_check,
           help="oxygen-storage cells of the catalyst (default 3)"),
    Option("thermal_cells", "--thermal-cells", int, metavar="N", check=_cells_check,
           help="thermal cells of the catalyst (default 5)"),
)
VARIANT_KEYS = tuple(o.key for o in CATALYST_OPTIONS)


def catalyst_params(variant: Mapping[str, Any] | None = None,
                    base: CatalystParams | None = None) -> CatalystParams:
    """:class:`CatalystParams` of a plant variant: ``base`` (default the cell's own) with the
    options of :data:`CATALYST_OPTIONS` given in ``variant`` (others are ignored: the engine
    profile passes all its options). A bad value raises :class:`ConfigError` naming the flag."""
    p = base or CatalystParams()
    v = {k: variant[k] for k in VARIANT_KEYS if variant and variant.get(k) is not None}
    for opt in CATALYST_OPTIONS:
        if opt.key in v:
            opt.validate(v[opt.key])
    sensors, kinetics, thermal = p.sensors, p.kinetics, p.thermal
    if "lambda_sensor" in v:
        sensors = replace(sensors, lambda_lag=str(v["lambda_sensor"]))
    if "lambda_dead_time" in v:
        sensors = replace(sensors, dead_time_lambda=float(v["lambda_dead_time"]))
    if "lambda_tau_scale" in v:
        sensors = replace(sensors, tau_lambda=sensors.tau_lambda * float(v["lambda_tau_scale"]))
    if "kinetics_scale" in v:
        f = float(v["kinetics_scale"])
        kinetics = kinetics.scaled(A1=f, A2=f)
    if "storage_cells" in v:
        kinetics = replace(kinetics, cells=int(v["storage_cells"]))
    if "thermal_cells" in v:
        n = int(v["thermal_cells"])
        thermal = replace(thermal, cells=n)
        sensors = replace(sensors, t_cat_cell=n // 2)
    return replace(p, sensors=sensors, kinetics=kinetics, thermal=thermal)
