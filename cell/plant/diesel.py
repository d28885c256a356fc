"""The large diesel and its dynamometer (engine profile ``large-diesel``, seed 004).

The engine is modelled on the one of seed 004 ("Practical application": a 60 L engine at
rated speed and load). Figure 9's two columns become the ``rated`` and ``warmup`` duty
cycles; ``transient`` adds speed/load steps with long steady holds for filter-quality checks.

Equations (``f(t, x, u, params)`` style; the plant uses their exact discretisation for a
held input):

- speed and torque follow their setpoints as first-order lags (:func:`engine_rhs`): the
  water-brake dyno's speed loop, and governor plus turbocharger spool;
- fuel is a Willans line (:func:`fuel_rate_kgph`);
- exhaust mass flow is four-stroke swept air at boosted density plus fuel
  (:func:`exhaust_flow`).
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from cell.core.errors import ConfigError
from cell.plant.base import Plant, lag_factor

#: ``ENGINE_STATE`` values (DBC ``VAL_ 259 ENGINE_STATE``).
STOPPED, RUNNING, TRIPPED = 0, 1, 2

CYCLES = ("rated", "warmup", "transient", "etc")


@dataclass(frozen=True)
class EngineParams:
    """Every constant of the engine and dynamometer, each with the reasoning behind its value.

    The closed-loop experiment (seed 004, "Practical application", Figure 10) depends on
    these numbers, so they follow from stated physics and the paper's figures, not from
    tuning the loop. Units are in the names or the docstrings.
    """

    period: float = 0.01
    """Step period, s. 100 Hz: ten plant samples per 10 Hz logger sample (seed 004 logs
    at 10 Hz), and twice the runtime's fastest task (FAS, 50 Hz)."""

    rated_speed: float = 1800.0
    """Rated speed, rpm. Seed 004's 60 L engine is a high-horsepower generator-set class
    diesel; 1800 rpm is the 60 Hz synchronous rated speed of that class."""

    rated_power: float = 2000.0
    """Rated brake power, kW. A 60 L V16 at 1800 rpm is rated about 2 MW (BMEP ~22 bar,
    typical of modern high-output diesels)."""

    idle_speed: float = 600.0
    """Low idle, rpm: one third of rated, usual for large diesels."""

    tau_speed: float = 1.0
    """Speed response time constant, s: the water-brake dyno's speed loop acting on the
    inertia of a 60 L engine plus dyno rotor. Also the run-down constant after a trip."""

    tau_torque: float = 0.5
    """Torque response time constant, s: governor plus turbocharger spool (fuel is fast, boost
    is not)."""

    displacement: float = 0.060
    """Swept volume, m³ (seed 004: 60 L)."""

    cylinders: int = 16
    """Cylinder count: a 60 L engine of this class is a V16, eight cylinders per exhaust bank.
    Sets the firing frequency of the exhaust pulsation."""

    volumetric_efficiency: float = 0.95
    """Volumetric efficiency referred to charge-air density; 0.9-1.0 for a four-valve
    turbo-diesel with positive scavenging."""

    ambient_density: float = 1.184
    """Ambient air density, kg/m³ (25 °C, 101.3 kPa). With the swept rate at idle this gives
    0.34 kg/s exhaust flow at idle (naturally aspirated there: no boost at zero load)."""

    ambient_temp: float = 298.15
    """Ambient temperature, K (25 °C), for the charge-air density ratio."""

    boost_pressure_ratio_rated: float = 3.3
    """Compressor pressure ratio at rated. Air-fuel ratio lambda ~1.9 at 22 bar BMEP needs
    ~3.3; together with ``charge_air_temp_rated`` it gives a charge density ratio of 3.04 and
    a rated exhaust flow of 3.19 kg/s (1.60 kg/s per bank)."""

    charge_air_temp_rated: float = 323.15
    """Intake manifold temperature after the charge-air cooler at rated, K (50 °C)."""

    bsfc_rated: float = 200.0
    """Brake specific fuel consumption at rated, g/kWh (best large diesels: 190-210).
    400 kg/h at 2 MW."""

    idle_fuel: float = 15.0
    """Fuel rate at low idle, L/h (about 0.6 % of rated fuel, usual for a 60 L engine at
    idle). Taken as friction fuel proportional to speed in a Willans-line model, so the
    marginal BSFC is (400 - 3 x 12.6) / 2000 kg/kWh = 181 g/kWh."""

    fuel_density: float = 0.84
    """Diesel density, kg/L (EN 590: 0.82-0.845)."""


    stop_speed: float = 1.0
    """Below this speed, rpm, a tripped engine is taken as stopped (speed and flow 0)."""


    # -- derived quantities -------------------------------------------------------------
    @property
    def rated_torque(self) -> float:
        """Torque at rated, N·m: P / ω (10 610 N·m)."""
        return self.rated_power * 1000.0 / (self.rated_speed * 2.0 * math.pi / 60.0)

    @property
    def charge_density_ratio_rated(self) -> float:
        """Charge-air density over ambient at rated: PR x T_amb / T_charge."""
        return self.boost_pressure_ratio_rated * self.ambient_temp / self.charge_air_temp_rated

    @property
    def idle_fuel_kgph(self) -> float:
        return self.idle_fuel * self.fuel_density

    @property
    def marginal_bsfc(self) -> float:
        """Willans-line slope, g/kWh: rated fuel minus friction fuel at rated speed, per kW."""
        rated_fuel = self.bsfc_rated * self.rated_power / 1000.0  # kg/h
        friction = self.idle_fuel_kgph * self.rated_speed / self.idle_speed
        return (rated_fuel - friction) / self.rated_power * 1000.0



# -- equations ------------------------------------------------------------------------------
def engine_rhs(t: float, x: Sequence[float], u: Sequence[float], p: EngineParams) -> tuple[float, float]:
    """d/dt of (speed rpm, torque N·m) for setpoints u = (speed rpm, load fraction):
    first-order lags with ``tau_speed`` and ``tau_torque`` towards the setpoint."""
    speed, torque = x
    sp_speed, sp_load = u
    return ((sp_speed - speed) / p.tau_speed, (sp_load * p.rated_torque - torque) / p.tau_torque)


def fuel_rate_kgph(p: EngineParams, speed: float, power_kw: float) -> float:
    """Willans line: friction fuel proportional to speed plus marginal BSFC x power, kg/h."""
    return p.idle_fuel_kgph * speed / p.idle_speed + p.marginal_bsfc * max(power_kw, 0.0) / 1000.0


def exhaust_flow(
    p: EngineParams, speed: float, load: float, fuel_kgph: float | None = None
) -> float:
    """Total exhaust mass flow, kg/s: four-stroke swept air at boosted density, plus fuel.

    ``load`` is the fraction of rated torque; the charge density rises linearly with it from
    ambient (no boost at zero load) to the rated ratio (boost follows exhaust enthalpy,
    roughly proportional to fuel).
    """
    load = max(load, 0.0)
    if fuel_kgph is None:
        fuel_kgph = fuel_rate_kgph(
            p, speed, load * p.rated_torque * speed * math.pi / 30.0 / 1000.0
        )
    density = p.ambient_density * (1.0 + (p.charge_density_ratio_rated - 1.0) * load)
    air = p.displacement * speed / 120.0 * p.volumetric_efficiency * density
    return air + fuel_kgph / 3600.0



def rated_bank_flow(p: EngineParams, banks: int = 2) -> float:
    """Exhaust mass flow of one of ``banks`` banks at rated speed and full load, kg/s."""
    return exhaust_flow(p, p.rated_speed, 1.0) / banks


# -- duty cycles ----------------------------------------------------------------------------
class DutyCycle:
    """A deterministic setpoint schedule of (speed rpm, load fraction) against time.

    Parameters
    ----------
    name:
        Name of the cycle.
    knots:
        ``(t, speed, load)`` points, times non-decreasing; the setpoint is linear between
        knots and held after the last. Two knots at the same time make a step.
    duration:
        Nominal length in s (a default run length; the last setpoint holds forever).
    """

    def __init__(
        self, name: str, knots: Sequence[tuple[float, float, float]], duration: float
    ) -> None:
        if not knots:
            raise ConfigError(f"duty cycle {name!r} has no setpoints")
        times = [k[0] for k in knots]
        if any(b < a for a, b in itertools.pairwise(times)) or times[0] != 0.0:
            raise ConfigError(f"duty cycle {name!r}: knot times must start at 0 and not decrease")
        self.name = name
        self.knots = [(float(t), float(s), float(ld)) for t, s, ld in knots]
        self.duration = float(duration)
        self._times = [k[0] for k in self.knots]

    def setpoint(self, t: float) -> tuple[float, float]:
        """Speed (rpm) and load (fraction of rated torque) demanded at time ``t``."""
        i = bisect.bisect_right(self._times, t)
        if i >= len(self.knots):
            _, s, ld = self.knots[-1]
            return s, ld
        if i == 0:
            _, s, ld = self.knots[0]
            return s, ld
        t0, s0, l0 = self.knots[i - 1]
        t1, s1, l1 = self.knots[i]
        if t1 <= t0:
            return s1, l1
        f = (t - t0) / (t1 - t0)
        return s0 + f * (s1 - s0), l0 + f * (l1 - l0)

    def step_times(self) -> list[float]:
        """Times at which the setpoint starts to change (a step, or the start of a ramp)."""
        out: list[float] = []
        for (t0, s0, l0), (_t1, s1, l1) in itertools.pairwise(self.knots):
            if (s1, l1) != (s0, l0) and (not out or out[-1] != t0):
                out.append(t0)
        return out

    def steady_windows(self, settle: float = 8.0) -> list[tuple[float, float]]:
        """Intervals of constant setpoint, starting ``settle`` s after the setpoint stopped
        changing; the last hold ends at :attr:`duration`. Windows shorter than 1 s are left out.

        ``settle`` = 8 s covers the slowest plant lag (speed, 1 s) eight times over:
        e^-8 of a 500 mmH2O step is 0.2 mmH2O.
        """
        out = []
        for (t0, s0, l0), (t1, s1, l1) in itertools.pairwise(self.knots):
            if (s1, l1) == (s0, l0) and t1 - t0 > settle + 1.0:
                out.append((t0 + settle, t1))
        t_last = self.knots[-1][0]
        if self.duration - t_last > settle + 1.0:
            out.append((t_last + settle, self.duration))
        return out


def duty_cycle(name: str, p: EngineParams | None = None) -> DutyCycle:
    """The named duty cycle: ``rated``, ``warmup``, ``transient`` or ``etc`` (:func:`etc_cycle`).

    - ``rated``: idle 20 s, ramp 60 s, rated held (seed 004, Figure 9 left column: "ramp
      cycle ... starting from idle", then steady state);
    - ``warmup``: idle 30 s, then 5 s ramps to four part-load holds of 45 s and rated
      (Figure 9 right column: PUMA data "from an engine warm-up condition");
    - ``transient``: eight speed/load steps every 35 s from 1800 rpm at 25 % load, valve at a
      fixed opening. At the default valve each step moves the back-pressure by at least
      150 mmH2O, and each 35 s hold has 27 s of true steady state.
    """
    p = p or EngineParams()
    idle, rated = p.idle_speed, p.rated_speed
    if name == "rated":
        return DutyCycle("rated", [(0, idle, 0), (20, idle, 0), (80, rated, 1.0)], 300.0)
    if name == "warmup":
        pts = [(0.0, idle, 0.0), (30.0, idle, 0.0)]
        t = 30.0
        for speed, load in ((1000, 0.2), (1200, 0.4), (1500, 0.6), (1650, 0.8), (rated, 1.0)):
            pts.append((t + 5.0, speed, load))
            t += 50.0
            pts.append((t, speed, load))
        pts.pop()  # the last (rated) setpoint holds forever
        return DutyCycle("warmup", pts, t + 60.0)
    if name == "transient":
        points = [
            (rated, 0.25),
            (rated, 1.0),
            (1500, 0.5),
            (rated, 0.75),
            (1200, 0.5),
            (1650, 1.0),
            (1400, 0.8),
            (rated, 1.0),
            (rated, 0.5),
        ]
        hold = 35.0
        pts = []
        for i, (speed, load) in enumerate(points):
            pts.append((i * hold, speed, load))
            if i < len(points) - 1:
                pts.append(((i + 1) * hold, speed, load))
        return DutyCycle("transient", pts, hold * len(points))
    if name == "etc":
        return etc_cycle(p)
    raise ConfigError(f"unknown duty cycle {name!r}; choose one of: {', '.join(CYCLES)}")


#: The ``etc`` cycle's stationary holds: (start s, speed fraction of idle..rated, load).
ETC_HOLDS = ((40.0, 0.5, 0.45), (140.0, 0.85, 0.8), (230.0, 0.65, 0.6),
             (620.0, 0.35, 0.3), (1240.0, 1.0, 0.95), (1500.0, 0.8, 0.7))
#: Length of each hold, s.
ETC_HOLD = 40.0


def etc_cycle(p: EngineParams | None = None, duration: float = 1800.0) -> DutyCycle:
    """``etc``: a cycle shaped like the European Transient Cycle, mapped to this engine.

    Like the ETC (seed 002, §6.2) it has three parts of 600 s, urban (low speed, frequent
    idle), rural (mid speed, mid to high load) and motorway (high speed), made of 2-6 s
    ramps between random set-points (a fixed random stream, so the cycle is always the
    same). Unlike the ETC it has six stationary holds of :data:`ETC_HOLD` s
    (:data:`ETC_HOLDS`, three in the first 300 s, so short runs have them too): the design
    step of seed 002 (§4.2, Approach 2) needs stationary residuals at several operating
    points.
    """
    import numpy as np

    p = p or EngineParams()
    idle, rated = p.idle_speed, p.rated_speed
    rng = np.random.default_rng(2)
    phases = ((0.0, (0.0, 0.45), (0.0, 0.6)), (600.0, (0.35, 0.8), (0.2, 0.95)),
              (1200.0, (0.7, 1.0), (0.1, 1.0)))
    holds = list(ETC_HOLDS)
    pts: list[tuple[float, float, float]] = [(0.0, idle, 0.0)]
    t = 0.0
    while t < duration:
        if holds and t >= holds[0][0]:
            _, sf, ld = holds.pop(0)
            t += 4.0
            pts.append((t, idle + sf * (rated - idle), ld))
            t += ETC_HOLD
            pts.append((t, idle + sf * (rated - idle), ld))
            continue
        _, (s_lo, s_hi), (l_lo, l_hi) = [ph for ph in phases if ph[0] <= t][-1]
        t += float(rng.uniform(2.0, 6.0))
        if s_lo == 0.0 and rng.uniform() < 0.15:
            sf, ld = 0.0, 0.0  # back to idle, as the urban part does
        else:
            sf, ld = float(rng.uniform(s_lo, s_hi)), float(rng.uniform(l_lo, l_hi))
        pts.append((min(t, duration), idle + sf * (rated - idle), ld))
    return DutyCycle("etc", pts, duration)



# -- the plant ------------------------------------------------------------------------------
class DieselEngine(Plant):
    """The engine on its water-brake dynamometer, following a duty cycle.

    Speed and torque follow the duty cycle's setpoints (:func:`engine_rhs`, discretised
    exactly for the step); fuel and exhaust flow follow from them. When the protection
    trips the engine (input ``ENGINE_STATE`` = 2) the fuel is cut and speed and torque
    run down with their own time constants, to standstill below ``stop_speed``; when the
    trip is reset (``ENGINE_STATE`` back to 1) the engine restarts and follows its cycle.

    Parameters
    ----------
    cycle:
        ``"rated"``, ``"warmup"``, ``"transient"`` or a :class:`DutyCycle`.
    params:
        :class:`EngineParams`.

    The engine starts in steady state at the cycle's first setpoint.
    """

    inputs = ("ENGINE_STATE",)
    outputs = ("ENGINE_SPEED", "ENGINE_TORQUE", "FUEL_RATE", "ENGINE_POWER", "ENGINE_LOAD",
               "EXH_FLOW_TRUE")

    def __init__(self, cycle: str | DutyCycle = "rated", params: EngineParams | None = None,
                 name: str = "engine") -> None:
        p = self.params = params if params is not None else EngineParams()
        super().__init__(name, p.period)
        self.schedule = cycle if isinstance(cycle, DutyCycle) else duty_cycle(cycle, p)
        self.state = RUNNING
        self.safe = False  # safe state: low idle, no load, whatever the cycle says
        self._T_rated = p.rated_torque
        self._a_speed = lag_factor(p.period, p.tau_speed)
        self._a_torque = lag_factor(p.period, p.tau_torque)
        self._air_k = p.displacement / 120.0 * p.volumetric_efficiency * p.ambient_density
        self._boost = p.charge_density_ratio_rated - 1.0
        self._fuel_speed = p.idle_fuel_kgph / p.idle_speed
        self._fuel_power = p.marginal_bsfc / 1000.0
        speed, load = self.schedule.setpoint(0.0)
        self.speed = speed
        self.torque = load * self._T_rated
        self._update_flow()

    def _update_flow(self) -> None:
        speed = self.speed
        power_kw = self.torque * speed * (math.pi / 30.0) / 1000.0
        self.power_kw = power_kw
        if self.state == RUNNING:
            fuel = self._fuel_speed * speed + self._fuel_power * max(power_kw, 0.0)
        else:
            fuel = 0.0
        self.fuel_kgph = fuel
        load = max(self.torque / self._T_rated, 0.0)
        self.flow = self._air_k * speed * (1.0 + self._boost * load) + fuel / 3600.0

    def step(self, t: float, u: Mapping[str, float]) -> None:
        if self.state == RUNNING and u.get("ENGINE_STATE", RUNNING) != RUNNING:
            self.state = int(u["ENGINE_STATE"])  # tripped: stays down until reset
        elif self.state == TRIPPED and u.get("ENGINE_STATE") == RUNNING:
            self.state = RUNNING  # the trip was reset (ENGINE_CMD): restart and follow the cycle
        if self.state == RUNNING:
            sp_speed, sp_load = (self.params.idle_speed, 0.0) if self.safe \
                else self.schedule.setpoint(t)
            self.speed += self._a_speed * (sp_speed - self.speed)
            self.torque += self._a_torque * (sp_load * self._T_rated - self.torque)
        else:
            self.speed -= self._a_speed * self.speed
            self.torque -= self._a_torque * self.torque
            if self.speed < self.params.stop_speed:
                self.speed = 0.0
                self.torque = 0.0
        self._update_flow()

    def set_safe(self, safe: bool) -> None:
        self.safe = safe

    def output(self) -> dict[str, float]:
        return {
            "ENGINE_SPEED": self.speed,
            "ENGINE_TORQUE": max(self.torque, 0.0),
            "FUEL_RATE": self.fuel_kgph / self.params.fuel_density,
            "ENGINE_POWER": max(self.power_kw, 0.0),
            "ENGINE_LOAD": min(max(100.0 * self.torque / self._T_rated, 0.0), 110.0),
            "EXH_FLOW_TRUE": self.flow,
        }
