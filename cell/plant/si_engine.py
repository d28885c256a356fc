"""The turbocharged SI engine of the ``si-turbo`` profile: duty cycles, λ control, breathing.

A 4-cylinder, 2 L class turbocharged gasoline engine in a light-duty vehicle (the engine of
seeds 000, 001 and 003). Two plants:

- :class:`SIEngine`: the duty cycle (:data:`SI_CYCLES`) gives ``ENGINE_SPEED`` and the
  relative load demand ``SI_LOAD_DEMAND``; the engine's λ controller gives the engine-out
  ``LAMBDA_ENGINE_TRUE``: the limit cycle of a switching controller about 1, rich excursions
  on tip-in and lean ones on tip-out, fuel cut on overrun (``FUEL_CUT_TRUE``) and the rich
  purge that follows it.
- :class:`SIBreathing`: a simple mean-value breathing model, from speed, load demand and λ
  to ``EXH_MASS_FLOW_TRUE``, ``T_EXH_TRUE``, ``ENGINE_TORQUE``, ``FUEL_RATE`` and
  ``ENGINE_POWER``. The mean-value air path of seed 003 replaces it in the profile and
  produces the same signals.

Duty cycles
-----------
``ftp``
    A light-duty driving cycle shaped like the US EPA's FTP-75 (40 CFR 86, App. I: the
    Urban Dynamometer Driving Schedule's 1369 s, then its first 505 s again as the hot-start
    phase; 1874 s, 17.8 km, 91 km/h peak, about 23 stops). It is *not* the regulatory speed
    table: it is rebuilt here from that published shape, as micro-trips (idle, acceleration,
    cruise with small speed variations, deceleration to stop) whose peaks follow the
    schedule's: phase 1 (0-505 s) holds the 91 km/h "hill" early, then urban trips of
    30-55 km/h; phase 2 (505-1369 s) is stop-and-go under 55 km/h; phase 3 (1369-1874 s)
    repeats phase 1. The vehicle speed becomes engine speed through a six-speed gearbox and
    load demand through road load (:class:`VehicleParams`). The cycle starts with the engine
    at idle and the catalyst cold, as the FTP-75 does.
``steady``
    Fixed speed and load (2000 rpm, 40 % load demand), for 600 s.

Each cycle is an :class:`SICycle` in :data:`SI_CYCLES`; another one is one entry more.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from cell.core.errors import ConfigError
from cell.plant.base import Plant, lag_factor

KMH = 1.0 / 3.6

#: λ the engine puts out in fuel cut: pure air has no finite λ; 10 stands for it (the
#: wide-band sensors' range ends at 16, and the catalyst's feed-gas model takes λ > 5 as air).
LAMBDA_FUEL_CUT = 10.0


# -- vehicle and duty cycles ---------------------------------------------------------------
@dataclass(frozen=True)
class VehicleParams:
    """A compact car with the 2 L turbo engine: road load and driveline."""

    mass: float = 1500.0
    """Test mass, kg (curb mass plus 136 kg, as the FTP's equivalent test weight)."""
    cda: float = 0.65
    """Drag coefficient times frontal area, m² (Cd 0.29 x 2.25 m²)."""
    crr: float = 0.010
    """Rolling-resistance coefficient."""
    wheel_radius: float = 0.31
    """Dynamic tyre radius, m (205/55 R16)."""
    final_drive: float = 3.9
    gears: tuple[float, ...] = (3.5, 2.1, 1.4, 1.05, 0.85, 0.7)
    """Six-speed gearbox ratios."""
    min_speed: float = 1300.0
    """Lowest engine speed in gear, rpm: the gear is the highest keeping the engine above it
    (a driver of a turbo engine at light load keeps it between 1300 and 2500 rpm); in first
    gear below it, the clutch slips down to idle."""
    driveline_efficiency: float = 0.92
    aux_torque: float = 8.0
    """Accessory torque (alternator, pumps), N·m."""
    rho_air: float = 1.184


@dataclass(frozen=True)
class SIEngineParams:
    """The engine's speed range, torque curve and λ controller."""

    period: float = 0.01
    """Step period, s (100 Hz: the λ limit cycle has periods near 1 s)."""
    idle_speed: float = 750.0
    """Idle speed of a warm 2 L gasoline engine, rpm."""
    rated_speed: float = 5500.0
    max_torque: float = 320.0
    """Full-load torque plateau of a 2 L turbo SI engine (1500-4500 rpm), N·m."""
    idle_load: float = 0.12
    """Load demand at idle (friction and accessories), relative."""
    # -- λ controller (switching type, jump and ramp) ------------------------------------
    lambda_amplitude: float = 0.02
    """Amplitude of the limit cycle, relative to λ = 1: the integral ramp is this over the
    transport delay (ECUs schedule the ramp on air mass flow, so the amplitude stays about
    the same over the map) and the proportional jump is half of it. The period is then
    five transport delays (0.75 s at 2000 rpm)."""
    transport_delay: float = 0.15
    """Gas transport and sensor delay from the injectors to the upstream sensor at 2000 rpm,
    s; it scales with 2000/speed, up to ``max_transport_delay``."""
    max_transport_delay: float = 0.4
    # -- transients ------------------------------------------------------------------------
    transient_gain: float = 0.4
    """λ excursion per unit rate of load change (1/s) over ``transient_tau``: a tip-in of
    0.6 load in 1 s gives about λ 0.9 (rich: acceleration enrichment), a tip-out as much
    lean; the FTP's accelerations give 0.93-0.97."""
    transient_tau: float = 0.5
    """Decay time of the transient excursion (the wall film's), s."""
    # -- fuel cut ---------------------------------------------------------------------------
    fuel_cut_speed: float = 1200.0
    """Fuel is cut on overrun (no load demand) above this speed, rpm..."""
    fuel_cut_resume_speed: float = 1000.0
    """...and resumes when the speed falls below this one, or load is demanded."""
    fuel_cut_delay: float = 0.5
    """Overrun time before the fuel is cut, s."""
    purge_lambda: float = 0.93
    """λ of the rich purge after a fuel cut (the ECU empties the catalyst it saturated)."""
    purge_mass: float = 2.0e-3
    """Size of the rich purge, kg: it lasts until ∫ ṁ_exh (1 - λ) dt reaches this, which
    takes away 70 % of a fresh catalyst's oxygen (0.0094 of 0.0134 mol O₂ at 13 % carbon);
    an aged catalyst breaks through rich before the purge ends."""
    purge_time_max: float = 10.0
    """Longest purge, s (also the purge's length when no exhaust mass flow is known)."""
    # -- two-sensor control --------------------------------------------------------------
    lambda_target: float = 0.998
    """λ target of the upstream loop: slightly rich, as ECUs run for NOx conversion."""
    trim_gain: float = 0.2
    """Downstream trim, 1/s: the target moves by this x (1 - λ_mid) per second (λ_mid the
    catalyst's outlet λ), lean after a rich breakthrough and rich after a lean one."""
    trim_limit: float = 0.02
    """Largest trim of the target."""


class SICycle:
    """A duty cycle: engine speed (rpm) and load demand (0..1) on a fixed time grid.

    Parameters
    ----------
    name:
        The cycle's name.
    t, speed, load:
        Equal-length arrays; the setpoint is linear between points and held after the last.
    duration:
        Nominal length, s.
    description:
        What the cycle is and where its shape comes from.
    vehicle_speed:
        Vehicle speed in km/h on the same grid, when the cycle comes from one.
    """

    def __init__(self, name: str, t: np.ndarray, speed: np.ndarray, load: np.ndarray,
                 duration: float, description: str = "",
                 vehicle_speed: np.ndarray | None = None) -> None:
        t = np.asarray(t, dtype=float)
        if t.ndim != 1 or t.size == 0 or t[0] != 0.0 or np.any(np.diff(t) <= 0):
            raise ConfigError(f"duty cycle {name!r}: times must start at 0 and increase")
        self.name = name
        self.t = t
        self.speed = np.asarray(speed, dtype=float)
        self.load = np.asarray(load, dtype=float)
        self.duration = float(duration)
        self.description = description
        self.vehicle_speed = vehicle_speed
        self._dt = float(t[1] - t[0]) if t.size > 1 else 1.0
        self._uniform = t.size > 1 and bool(np.allclose(np.diff(t), self._dt))
        self._s = self.speed.tolist()
        self._l = self.load.tolist()

    def setpoint(self, t: float) -> tuple[float, float]:
        """Engine speed (rpm) and load demand (0..1) at time ``t``."""
        n = len(self._s)
        if n == 1 or t <= 0.0:
            return self._s[0], self._l[0]
        if self._uniform:
            x = t / self._dt
            i = int(x)
        else:
            i = int(np.searchsorted(self.t, t, side="right")) - 1
            x = i + (t - self.t[i]) / (self.t[min(i + 1, n - 1)] - self.t[i] or 1.0)
        if i >= n - 1:
            return self._s[-1], self._l[-1]
        f = x - i
        return (self._s[i] + f * (self._s[i + 1] - self._s[i]),
                self._l[i] + f * (self._l[i + 1] - self._l[i]))


#: FTP-75-shaped micro-trips of phase 1 (0-505 s): (idle s, peak km/h, cruise s).
_PHASE1 = ((20, 40, 14), (10, 91, 80), (12, 48, 25), (10, 55, 38), (10, 40, 15), (12, 52, 30),
           (14, 35, 10))
#: ... and of phase 2 (505-1369 s): stop-and-go under 55 km/h.
_PHASE2 = ((13, 40, 22), (10, 28, 10), (13, 48, 35), (16, 35, 15), (10, 54, 30), (14, 30, 10),
           (12, 45, 25), (18, 38, 18), (10, 52, 40), (12, 28, 8), (12, 46, 25), (16, 36, 14),
           (13, 50, 30), (14, 32, 10), (12, 42, 22), (18, 26, 6))
_ACCEL, _DECEL = 1.0, 1.1  # m/s², a brisk urban driver (the FTP's peaks are 1.5 and 1.5)


def _trips(trips, length: float, dt: float, phase: float) -> np.ndarray:
    """Vehicle speed (km/h) over ``length`` s from micro-trips, stretched or cut to fit."""
    out: list[float] = []
    for k, (idle, peak, cruise) in enumerate(trips):
        out += [0.0] * round(idle / dt)
        v = peak * KMH
        n_acc = round(v / _ACCEL / dt)
        out += [peak * (i + 1) / n_acc for i in range(n_acc)]
        n_cr = round(cruise / dt)
        # cruise with small speed variations (the driver's, ±0.8 km/h over 12 s)
        out += [peak + 0.8 * math.sin(2 * math.pi * i * dt / 12.0 + phase + k) for i in range(n_cr)]
        n_dec = round(v / _DECEL / dt)
        start = out[-1]
        out += [start * (1 - (i + 1) / n_dec) for i in range(n_dec)]
    n = round(length / dt)
    out = out[:n] + [0.0] * max(0, n - len(out))
    return np.asarray(out)


def vehicle_to_engine(v_kmh: np.ndarray, dt: float, vp: VehicleParams, ep: SIEngineParams
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Engine speed (rpm) and load demand (0..1) for a vehicle speed trace (km/h).

    Road load :math:`F = m a + c_{rr} m g + \\tfrac12 \\rho\\, c_d A\\, v^2`; the gear is the
    highest keeping the engine above ``min_speed`` (first gear slips down to idle). Load
    demand is the engine torque needed over the full-load torque at that speed, 0 when the
    car brakes (overrun), at least the idle load otherwise.
    """
    v = v_kmh * KMH
    a = np.gradient(v, dt)
    force = vp.mass * a + vp.crr * vp.mass * 9.81 * (v > 0.1) + 0.5 * vp.rho_air * vp.cda * v * v
    wheel_rpm = v / vp.wheel_radius * 60.0 / (2 * math.pi)
    speed = np.empty_like(v)
    ratio = np.empty_like(v)
    for i, w in enumerate(wheel_rpm):
        g = vp.gears[0]
        for r in vp.gears:
            if w * r * vp.final_drive >= vp.min_speed:
                g = r
        ratio[i] = g
        speed[i] = max(ep.idle_speed, w * g * vp.final_drive)
    torque = force * vp.wheel_radius / (ratio * vp.final_drive * vp.driveline_efficiency) + vp.aux_torque
    t_max = full_load_torque(speed, ep)
    load = np.where(force < -50.0, 0.0, np.clip(torque / t_max, ep.idle_load, 1.0))
    return speed, load


def full_load_torque(speed, ep: SIEngineParams):
    """Full-load torque, N·m: rising from 55 % at idle to the plateau at 1500 rpm, held to
    4500 rpm, then falling to rated power's torque at ``rated_speed``."""
    s = np.asarray(speed, dtype=float)
    low = ep.max_torque * (0.55 + 0.45 * np.clip((s - ep.idle_speed) / (1500.0 - ep.idle_speed), 0, 1))
    high = ep.max_torque * (1.0 - 0.18 * np.clip((s - 4500.0) / (ep.rated_speed - 4500.0), 0, 1))
    return np.minimum(low, high)


def ftp_cycle(vp: VehicleParams | None = None, ep: SIEngineParams | None = None) -> SICycle:
    """The FTP-75-shaped cycle (see the module notes), on a 0.1 s grid."""
    vp, ep = vp or VehicleParams(), ep or SIEngineParams()
    dt = 0.1
    p1 = _trips(_PHASE1, 505.0, dt, 0.0)
    p2 = _trips(_PHASE2, 864.0, dt, 1.0)
    v = np.concatenate([p1, p2, p1])
    t = np.arange(v.size) * dt
    speed, load = vehicle_to_engine(v, dt, vp, ep)
    return SICycle("ftp", t, speed, load, 1874.0, "FTP-75-shaped light-duty cycle (cold start, "
                   "stabilised, hot start), 1874 s", vehicle_speed=v)


def steady_cycle(speed: float = 2000.0, load: float = 0.4, duration: float = 600.0) -> SICycle:
    """Fixed speed and load demand."""
    return SICycle("steady", np.array([0.0]), np.array([speed]), np.array([load]), duration,
                   f"fixed {speed:g} rpm and load demand {load:g}")


def _holds(name: str, points: list[tuple[float, float]], hold: float, description: str,
           ramp: float = 0.02) -> SICycle:
    """Speed/load levels each held ``hold`` s, joined by ``ramp`` s steps."""
    t, speed, load = [0.0], [points[0][0]], [points[0][1]]
    for i, (s, ld) in enumerate(points):
        if i:
            t.append(i * hold + ramp)
            speed.append(s)
            load.append(ld)
        t.append((i + 1) * hold)
        speed.append(s)
        load.append(ld)
    return SICycle(name, np.array(t), np.array(speed), np.array(load), hold * len(points),
                   description)


#: Load levels of ``throttle-steps``: twelve steps up and down between 0.2 and 0.9 at 1800 rpm.
THROTTLE_STEP_LOADS = (0.25, 0.75, 0.35, 0.9, 0.5, 0.2, 0.65, 0.3, 0.85, 0.45, 0.7, 0.25, 0.6)
#: Grid of ``operating-points``: speeds (rpm) x load demands.
OPERATING_SPEEDS = (1000.0, 1500.0, 2000.0, 2500.0, 3000.0, 3500.0, 4000.0)
OPERATING_LOADS = (0.1, 0.3, 0.5, 0.7, 0.9)


def throttle_steps_cycle(hold: float = 8.0) -> SICycle:
    """Seed 003's Figures 1, 5 and 6: throttle (load-demand) steps at a constant 1800 rpm,
    each level held ``hold`` s (twelve step cases)."""
    return _holds("throttle-steps", [(1800.0, ld) for ld in THROTTLE_STEP_LOADS], hold,
                  "throttle steps at 1800 rpm (seed 003, Figures 1, 5, 6)")


def operating_points_cycle(hold: float = 10.0) -> SICycle:
    """Stationary operating points for the air-path observer's design (``testcell design
    airpath``): every speed x load of the grid, held ``hold`` s (the turbo settles slowly at
    low load: its slowest pole is near -0.2 /s, seed 003 §3.1.1)."""
    pts = [(s, ld) for s in OPERATING_SPEEDS for ld in OPERATING_LOADS]
    return _holds("operating-points", pts, hold,
                  "stationary speed x load grid for the air-path gain table (seed 003, §3.1)")


#: The SI duty cycles by name: name -> factory of an :class:`SICycle` (first is the default).
SI_CYCLES: dict[str, Callable[[], SICycle]] = {
    "ftp": ftp_cycle,
    "steady": steady_cycle,
    "throttle-steps": throttle_steps_cycle,
    "operating-points": operating_points_cycle,
}


def si_cycle(name: str) -> SICycle:
    try:
        return SI_CYCLES[name]()
    except KeyError:
        raise ConfigError(f"--duty {name!r} is not a duty cycle of si-turbo; choose one of: "
                          f"{', '.join(SI_CYCLES)}") from None


# -- the engine and its λ controller --------------------------------------------------------
class SIEngine(Plant):
    """Engine speed and load demand from the duty cycle, and engine-out λ from its control.

    λ control (a switching controller on the upstream sensor, as on most SI engines):
    the fuel correction ``c`` jumps by half of ``lambda_amplitude`` and then ramps at
    ``lambda_amplitude`` / delay towards rich while the sensed λ (delayed by the transport
    delay) is lean, and the other way while it is rich; with the delay this gives the limit
    cycle about λ = 1, ±2 % with a period of five delays (0.75 s at 2000 rpm, 2 s at idle).
    Engine-out λ is ``(1 + x_tr + c)``, where the transient
    ``x_tr`` follows ``-transient_gain`` x the rate of change of load (tip-in rich, tip-out
    lean) and decays with ``transient_tau``. On overrun above ``fuel_cut_speed`` the fuel
    is cut (λ = :data:`LAMBDA_FUEL_CUT`, ``FUEL_CUT_TRUE`` = 1); when it resumes, a rich
    purge at ``purge_lambda`` follows until ``purge_mass`` has passed, and the controller
    restarts. The upstream loop's target is ``lambda_target`` plus a slow downstream trim
    on the catalyst's outlet λ (input ``LAMBDA_MID_TRUE``, when the profile has a catalyst).
    """

    inputs = ("EXH_MASS_FLOW_TRUE", "LAMBDA_MID_TRUE")
    outputs = ("ENGINE_SPEED", "SI_LOAD_DEMAND", "LAMBDA_ENGINE_TRUE", "FUEL_CUT_TRUE")

    def __init__(self, cycle: str | SICycle = "ftp", params: SIEngineParams | None = None,
                 name: str = "engine") -> None:
        p = self.params = params or SIEngineParams()
        super().__init__(name, p.period)
        self.cycle = cycle if isinstance(cycle, SICycle) else si_cycle(cycle)
        self.speed, self.load = self.cycle.setpoint(0.0)
        self._prev_load = self.load
        self.corr = 0.0
        self.x_tr = 0.0
        self.rich = False  # the controller's present direction
        self.fuel_cut = False
        self._overrun = 0.0
        self._purge = 0.0  # purge mass still to go, kg
        self._purge_t = 0.0
        self.trim = 0.0
        self._a_tr = lag_factor(p.period, p.transient_tau)
        self._hist = [1.0] * 256  # engine-out λ history, for the transport delay
        self._hi = 0
        self.lam = 1.0
        self.safe = False  # safe state: idle, whatever the cycle says

    def set_safe(self, safe: bool) -> None:
        self.safe = safe

    def step(self, t: float, u: Mapping[str, float]) -> None:
        p = self.params
        dt = self.period
        self.speed, self.load = (p.idle_speed, p.idle_load) if self.safe else self.cycle.setpoint(t)
        dload = (self.load - self._prev_load) / dt
        self._prev_load = self.load
        self.x_tr += self._a_tr * (-p.transient_gain * p.transient_tau * dload - self.x_tr)
        # fuel cut on overrun
        if self.load <= 0.0 and self.speed > p.fuel_cut_speed:
            self._overrun += dt
        else:
            self._overrun = 0.0
        if self.fuel_cut:
            if self.load > 0.0 or self.speed < p.fuel_cut_resume_speed:
                self.fuel_cut = False
                self._purge = p.purge_mass
                self._purge_t = 0.0
                self.corr = 0.0
        elif self._overrun >= p.fuel_cut_delay:
            self.fuel_cut = True
        # the switching controller on the delayed λ
        n = len(self._hist)
        delay_s = min(p.transport_delay * 2000.0 / max(self.speed, 1.0), p.max_transport_delay)
        delay = max(1, min(n - 1, round(delay_s / dt)))
        sensed = self._hist[(self._hi - delay) % n]
        if self.fuel_cut:
            lam = LAMBDA_FUEL_CUT
        elif self._purge > 0.0:
            mdot = u.get("EXH_MASS_FLOW_TRUE")
            self._purge_t += dt
            if mdot is None or self._purge_t >= p.purge_time_max:
                self._purge = 0.0 if self._purge_t >= p.purge_time_max else self._purge
            else:
                self._purge -= mdot * (1.0 - p.purge_lambda) * dt
            lam = p.purge_lambda
        else:
            lam_mid = u.get("LAMBDA_MID_TRUE")
            if lam_mid is not None:  # the downstream trim
                self.trim += p.trim_gain * (1.0 - min(lam_mid, 1.5)) * dt
                self.trim = min(max(self.trim, -p.trim_limit), p.trim_limit)
            lean = sensed > p.lambda_target + self.trim
            if lean != self.rich:  # switch: the jump
                self.rich = lean
                jump = 0.5 * p.lambda_amplitude
                self.corr += -jump if lean else jump
            ramp = p.lambda_amplitude / (delay * dt)
            self.corr += (-ramp if self.rich else ramp) * dt
            self.corr = min(max(self.corr, -0.15), 0.15)
            lam = min(max(1.0 + self.x_tr + self.corr, 0.7), 1.4)
        self.lam = lam
        self._hi = (self._hi + 1) % n
        self._hist[self._hi] = lam

    def output(self) -> dict[str, float]:
        return {"ENGINE_SPEED": self.speed, "SI_LOAD_DEMAND": self.load,
                "LAMBDA_ENGINE_TRUE": self.lam, "FUEL_CUT_TRUE": 1.0 if self.fuel_cut else 0.0}


# -- breathing ------------------------------------------------------------------------------
@dataclass(frozen=True)
class BreathingParams:
    """A simple mean-value breathing model of the 2 L turbo SI engine."""

    period: float = 0.01
    displacement: float = 0.002
    """Swept volume, m³."""
    volumetric_efficiency: float = 0.9
    rho_amb: float = 1.184
    """Ambient air density, kg/m³."""
    charge_idle: float = 0.13
    """Relative cylinder charge (charge over swept volume at ambient density) at zero load
    demand: closed throttle."""
    charge_full: float = 1.8
    """Relative charge at full load demand: about 1.9 bar boost."""
    tau_charge: float = 0.3
    """Charge response to load demand, s: manifold filling and turbocharger spool together."""
    afr_stoich: float = 14.7
    """Stoichiometric air-fuel ratio of gasoline."""
    lhv: float = 43.0e6
    """Lower heating value of gasoline, J/kg."""
    indicated_efficiency: float = 0.36
    friction_torque: float = 12.0
    """Friction torque at zero speed, N·m..."""
    friction_per_rpm: float = 0.004
    """...plus this per rpm (fmep about 1 bar at 2000 rpm)."""
    fuel_density: float = 0.745
    """Gasoline density, kg/L."""
    tau_exh: float = 3.0
    """Exhaust temperature lag, s: manifold and turbine walls."""
    fuel_cut_lambda: float = 5.0
    """Above this λ the engine takes no fuel (fuel cut)."""


def steady_exhaust_temp(speed: float, charge: float, fuel_cut: bool) -> float:
    """Steady exhaust temperature at the catalyst inlet, °C: rising with speed and charge
    (350 °C at idle, 500 °C at 2000 rpm and half charge, 950 °C at rated); air only in fuel cut."""
    if fuel_cut:
        return 150.0 + 0.02 * speed
    return min(280.0 + 0.045 * speed + 230.0 * charge, 950.0)


class SIBreathing(Plant):
    """Air, fuel, torque and exhaust of the SI engine from speed, load demand and λ.

    The relative charge follows the load demand with ``tau_charge``; air mass flow is the
    four-stroke swept rate at that charge; fuel is air / (AFR_st λ) (none above
    ``fuel_cut_lambda``); brake torque is indicated (fuel power x ``indicated_efficiency``,
    x λ when rich: unburnt fuel) less friction; exhaust mass flow is air plus fuel; exhaust
    temperature follows :func:`steady_exhaust_temp` with ``tau_exh``.
    """

    inputs = ("ENGINE_SPEED", "SI_LOAD_DEMAND", "LAMBDA_ENGINE_TRUE")
    outputs = ("EXH_MASS_FLOW_TRUE", "T_EXH_TRUE", "ENGINE_TORQUE", "FUEL_RATE", "ENGINE_POWER")

    def __init__(self, params: BreathingParams | None = None, name: str = "breathing") -> None:
        p = self.params = params or BreathingParams()
        super().__init__(name, p.period)
        self._a_charge = lag_factor(p.period, p.tau_charge)
        self._a_exh = lag_factor(p.period, p.tau_exh)
        self.charge = p.charge_idle
        self.t_exh = 0.0
        self._calc(750.0, 1.0)

    def start(self, u: Mapping[str, float]) -> None:
        p = self.params
        load = u.get("SI_LOAD_DEMAND", 0.0)
        self.charge = p.charge_idle + (p.charge_full - p.charge_idle) * load
        speed, lam = u.get("ENGINE_SPEED", 750.0), u.get("LAMBDA_ENGINE_TRUE", 1.0)
        self._calc(speed, lam)
        self.t_exh = steady_exhaust_temp(speed, self.charge, lam >= p.fuel_cut_lambda)

    def _calc(self, speed: float, lam: float) -> None:
        p = self.params
        air = p.volumetric_efficiency * p.rho_amb * p.displacement * speed / 120.0 * self.charge
        fuel = 0.0 if lam >= p.fuel_cut_lambda else air / (p.afr_stoich * lam)
        omega = speed * math.pi / 30.0
        indicated = p.indicated_efficiency * fuel * p.lhv * min(lam, 1.0) / max(omega, 1.0)
        torque = indicated - p.friction_torque - p.friction_per_rpm * speed
        self.flow = air + fuel
        self.fuel = fuel
        self.torque = torque
        self.speed = speed

    def step(self, t: float, u: Mapping[str, float]) -> None:
        p = self.params
        speed, load, lam = u["ENGINE_SPEED"], u["SI_LOAD_DEMAND"], u["LAMBDA_ENGINE_TRUE"]
        target = p.charge_idle + (p.charge_full - p.charge_idle) * min(max(load, 0.0), 1.0)
        self.charge += self._a_charge * (target - self.charge)
        self._calc(speed, lam)
        t_ss = steady_exhaust_temp(speed, self.charge, lam >= p.fuel_cut_lambda)
        self.t_exh += self._a_exh * (t_ss - self.t_exh)

    def output(self) -> dict[str, float]:
        torque = max(self.torque, 0.0)
        return {"EXH_MASS_FLOW_TRUE": self.flow, "T_EXH_TRUE": self.t_exh,
                "ENGINE_TORQUE": torque, "FUEL_RATE": self.fuel * 3600.0 / self.params.fuel_density,
                "ENGINE_POWER": torque * self.speed * math.pi / 30.0 / 1000.0}
