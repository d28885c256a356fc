"""The plant: a 60 L diesel on a water-brake dynamometer, two exhaust banks, two butterflies.

Pure numerics: no bus, no wall clock. The plant integrates at ``dt`` = 0.01 s (100 Hz) and
publishes every DBC signal whose sender is ``SIM``: the noisy back-pressure the cell's
filters work on, and the ``*_TRUE`` answer key the simulator alone knows.

The engine is modelled on the one of seed 004 ("Practical application": a 60 L engine at
rated speed and load, back-pressure closed-loop to 680 mmH2O starting from the valve 100 %
open; "Introduction": raw noise of +-200 mmH2O, "noisy and erratic"). Figure 9's two columns
become the ``rated`` and ``warmup`` duty cycles; ``transient`` adds speed/load steps with long
steady holds for filter-quality checks.

Signal chain per bank::

    speed, torque ─▶ exhaust mass flow ─▶ Δp = m² (k_sys + k_valve / a(θ)²)
                     ─▶ gas-volume lag (tau_gas) ─▶ sensor-line delay ─▶ EXH_BP_x_TRUE
                     ─▶ + pulsation + Student-t + spikes ─▶ EXH_BP_x
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace

import can
import numpy as np

from ..dbc import CellDatabase
from ..errors import ConfigError

BANKS = ("L", "R")
CYCLES = ("rated", "warmup", "transient")

#: ``ENGINE_STATE`` values (DBC ``VAL_ 259 ENGINE_STATE``).
STOPPED, RUNNING, TRIPPED = 0, 1, 2
#: ``TRIP_REASON`` values (DBC ``VAL_ 259 TRIP_REASON``).
TRIP_NONE, TRIP_EXH_BP_LIMIT = 0, 1

_NOISE_BLOCK = 2048  # noise samples drawn per numpy call, per bank


@dataclass
class PlantParams:
    """Every constant of the plant, each with the reasoning behind its value.

    The closed-loop experiment (seed 004, "Practical application", Figure 10) depends on
    these numbers, so they follow from stated physics and the paper's figures, not from
    tuning the loop. Units are in the names or the docstrings.
    """

    dt: float = 0.01
    """Integration step, s. 100 Hz: ten plant samples per 10 Hz logger sample (seed 004 logs
    at 10 Hz), and twice the runtime's fastest task (FAS, 50 Hz)."""

    # -- engine and dynamometer -------------------------------------------------------
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

    # -- exhaust back-pressure --------------------------------------------------------
    k_sys: float = 90.2
    """Fixed exhaust-system restriction per bank, mmH2O/(kg/s)². With ``k_valve`` and
    ``valve_leak`` the solution of three anchors at rated bank flow 1.60 kg/s:
    Δp(100 %) = 250 mmH2O (the open-valve floor the paper's loop starts from),
    Δp(40 %) = 680 mmH2O (the paper's target near 40 % open) and Δp(30 %) = 1400 mmH2O
    (a butterfly's steep last third). Solved: leak 0.0243, k_valve 7.83, k_sys 90.24;
    rounded here."""

    k_valve: float = 7.9
    """Restriction of the fully open butterfly per bank, mmH2O/(kg/s)², scaled by 1/a(θ)².
    The open valve is 8 % of the open-valve Δp: a butterfly's open-disc loss is small."""

    valve_leak: float = 0.025
    """Effective area of the closed butterfly relative to fully open (disc clearance);
    2.5 % is a typical leak of an unsealed exhaust butterfly."""

    tau_gas: float = 0.4
    """Gas-volume time constant, s: filling of the manifold, ducting and silencer volume
    (several m³ in a test cell), as a first-order lag."""

    sensor_delay: float = 0.15
    """Transport delay to the sensor, s: a long pneumatic line from the exhaust to the
    transducer, plus acquisition. A multiple of ``dt``."""

    # -- valve actuator ---------------------------------------------------------------
    valve_rate: float = 5.0
    """Actuator rate limit, %/s: an electric quarter-turn actuator needs ~20 s for full
    travel; fully open to the 680 target (60 % travel) takes 12 s."""

    valve_deadband: float = 0.5
    """Positioner dead-band, %: the motor starts only when |demand - position| exceeds it,
    then runs to the demand. About 20 mmH2O near 40 % open at rated, so an integrating loop
    cannot settle (seed 004, "Practical application": the dead-band "prevents the actuator
    from stabilising")."""

    valve_resolution: float = 0.2
    """Position resolution, %: the valve takes only multiples of this (1000 steps for
    full travel, plus gear backlash); ~8 mmH2O near 40 % open at rated."""

    # -- engine protection ------------------------------------------------------------
    bp_limit: float = 1200.0
    """Engine-protection limit on either bank's noise-free back-pressure, mmH2O. Seed 004's
    raw-signal loop "triggered an engine limit"; 1200 sits well above the 680 target and the
    noise (+-200), below the 30 %-open value (~1400)."""

    stop_speed: float = 1.0
    """Below this speed, rpm, a tripped engine is taken as stopped (speed and flow 0)."""

    # -- measurement noise ------------------------------------------------------------
    pulsation_amplitude: float = 60.0
    """Exhaust pulsation amplitude at rated flow, mmH2O; scales with exhaust flow. Sampled
    at 100 Hz the firing frequency (8 cylinders per bank: 120 Hz at rated) aliases; with
    the phase jitter below it is a smeared, zero-mean, non-Gaussian (arcsine) component."""

    pulsation_phase_diffusion: float = 10.0
    """Phase random walk of the pulsation, rad/sqrt(s): cycle-to-cycle variation, plus
    sampling jitter against a 120 Hz wave. Correlation decays as exp(-D² τ / 2):
    0.6 at 10 ms, 0.007 at 100 ms, so the noise is white at the runtime's 10 Hz sampling."""

    t_noise_df: float = 5.0
    """Degrees of freedom of the Student-t sensor noise: heavy tails (kurtosis 9) with a
    finite variance, for the "erratic" raw signal of seed 004."""

    t_noise_scale: float = 42.0
    """Scale of the Student-t sensor noise, mmH2O (std = scale x sqrt(5/3) = 54)."""

    t_noise_clip: float = 300.0
    """Clip of the Student-t component, mmH2O (~7 scales): a t(5) draw exceeds it about once
    in 10^5 samples, and unclipped such draws (+-1000 and more) would swamp a 3 s average
    on their own; the transducer's own electronics bound it in the same way."""

    spike_probability: float = 0.01
    """Probability of a spike per 100 Hz sample (about one per second): electrical pick-up
    and flow slugs."""

    spike_min: float = 150.0
    """Smallest spike, mmH2O."""

    spike_max: float = 400.0
    """Largest spike, mmH2O. With pulsation and t-noise, the overall std at rated is
    ~75 mmH2O and peaks pass the paper's +-200."""

    sensor_min: float = -500.0
    """Sensor range floor, mmH2O (DBC ``EXH_BP_L`` minimum)."""

    sensor_max: float = 20000.0
    """Sensor range ceiling, mmH2O (DBC ``EXH_BP_L`` maximum)."""

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


# -- closed-form relations (also used by the tests' independent checks) ---------------------
def valve_area(theta: float, leak: float) -> float:
    """Butterfly effective area relative to fully open: leak + (1 - leak)(1 - cos(π/2 θ/100))."""
    return leak + (1.0 - leak) * (1.0 - math.cos(math.pi / 2.0 * theta / 100.0))


def fuel_rate_kgph(p: PlantParams, speed: float, power_kw: float) -> float:
    """Willans line: friction fuel proportional to speed plus marginal BSFC x power, kg/h."""
    return p.idle_fuel_kgph * speed / p.idle_speed + p.marginal_bsfc * max(power_kw, 0.0) / 1000.0


def exhaust_flow(
    p: PlantParams, speed: float, load: float, fuel_kgph: float | None = None
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


def back_pressure(p: PlantParams, bank_flow: float, theta: float) -> float:
    """Steady back-pressure of one bank, mmH2O: m² (k_sys + k_valve / a(θ)²)."""
    a = valve_area(theta, p.valve_leak)
    return bank_flow * bank_flow * (p.k_sys + p.k_valve / (a * a))


def valve_for_back_pressure(p: PlantParams, target: float, bank_flow: float) -> float:
    """Opening θ in % that gives ``target`` mmH2O at ``bank_flow`` (inverse of back_pressure).

    Returns 100 when even the open valve exceeds the target, 0 when the closed valve cannot
    reach it.
    """
    need = target / (bank_flow * bank_flow) - p.k_sys
    if need <= p.k_valve:
        return 100.0
    a = math.sqrt(p.k_valve / need)
    if a <= p.valve_leak:
        return 0.0
    c = 1.0 - (a - p.valve_leak) / (1.0 - p.valve_leak)
    return 200.0 / math.pi * math.acos(min(max(c, -1.0), 1.0))


def rated_bank_flow(p: PlantParams) -> float:
    """Exhaust mass flow of one bank at rated speed and full load, kg/s."""
    return exhaust_flow(p, p.rated_speed, 1.0) / 2.0


# -- duty cycles ------------------------------------------------------------------------
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


def duty_cycle(name: str, p: PlantParams | None = None) -> DutyCycle:
    """The named duty cycle: ``rated``, ``warmup`` or ``transient``.

    - ``rated``: idle 20 s, ramp 60 s, rated held (seed 004, Figure 9 left column: "ramp
      cycle ... starting from idle", then steady state);
    - ``warmup``: idle 30 s, then 5 s ramps to four part-load holds of 45 s and rated
      (Figure 9 right column: PUMA data "from an engine warm-up condition");
    - ``transient``: eight speed/load steps every 35 s from 1800 rpm at 25 % load, valve at a
      fixed opening. At the default valve each step moves the back-pressure by at least
      150 mmH2O, and each 35 s hold has 27 s of true steady state.
    """
    p = p or PlantParams()
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
    raise ConfigError(f"unknown duty cycle {name!r}; choose one of: {', '.join(CYCLES)}")


# -- the plant --------------------------------------------------------------------------
class _Valve:
    """Butterfly actuator: rate limit, dead-band, resolution (positions are k x resolution)."""

    __slots__ = ("deadband", "demand", "moving", "rate_step", "res", "x")

    def __init__(self, position: float, p: PlantParams) -> None:
        self.res = p.valve_resolution
        self.x = self._quantise(position)
        self.demand = self.x
        self.moving = False
        self.rate_step = p.valve_rate * p.dt
        self.deadband = p.valve_deadband

    def _quantise(self, v: float) -> float:
        v = min(max(v, 0.0), 100.0)
        return round(v / self.res) * self.res if self.res > 0 else v

    @property
    def position(self) -> float:
        return self._quantise(self.x)

    def step(self) -> None:
        target = self._quantise(self.demand)
        err = target - self.x
        if not self.moving:
            if abs(self.demand - self.position) <= self.deadband:
                return
            self.moving = True
        if abs(err) <= self.rate_step:
            self.x = target
            self.moving = False
        else:
            self.x += self.rate_step if err > 0 else -self.rate_step


class Plant:
    """Engine, dynamometer, exhaust banks L and R with butterfly valves, sensors and noise.

    Parameters
    ----------
    cycle:
        ``"rated"``, ``"warmup"``, ``"transient"`` or a :class:`DutyCycle`.
    seed:
        Seeds the numpy Generator of the measurement noise; same seed, same run.
    params:
        Plant constants (:class:`PlantParams`).
    initial_valve:
        Valve opening in % held until a demand arrives. ``None``: the opening that gives
        680 mmH2O at rated (seed 004's target), so a run without a controller shows the
        paper's operating point. The closed-loop experiment passes 100 (fully open).

    The plant starts in steady state at the cycle's first setpoint.
    """

    def __init__(
        self,
        cycle: str | DutyCycle = "rated",
        seed: int = 0,
        params: PlantParams | None = None,
        initial_valve: float | None = None,
    ) -> None:
        p = self.params = params if params is not None else PlantParams()
        self.schedule = cycle if isinstance(cycle, DutyCycle) else duty_cycle(cycle, p)
        self.seed = seed
        self.dt = p.dt
        self.k = 0
        self.bp_limit = float(p.bp_limit)
        self.state = RUNNING
        self.trip_reason = TRIP_NONE
        self.trip_bank: str | None = None  # bank whose back-pressure tripped the engine
        self.trip_time: float | None = None  # simulation time of the trip, s
        self._T_rated = p.rated_torque
        self._flow_rated = exhaust_flow(p, p.rated_speed, 1.0)
        self._a_speed = 1.0 - math.exp(-p.dt / p.tau_speed)
        self._a_torque = 1.0 - math.exp(-p.dt / p.tau_torque)
        self._a_gas = 1.0 - math.exp(-p.dt / p.tau_gas)
        self._n_delay = max(0, round(p.sensor_delay / p.dt))
        self._air_k = p.displacement / 120.0 * p.volumetric_efficiency * p.ambient_density
        self._boost = p.charge_density_ratio_rated - 1.0
        self._fuel_speed = p.idle_fuel_kgph / p.idle_speed
        self._fuel_power = p.marginal_bsfc / 1000.0

        if initial_valve is None:
            initial_valve = valve_for_back_pressure(p, 680.0, rated_bank_flow(p))
        if not 0.0 <= float(initial_valve) <= 100.0 or math.isnan(float(initial_valve)):
            raise ConfigError(f"initial valve opening must be 0..100 %, got {initial_valve}")
        self.valves = {b: _Valve(float(initial_valve), p) for b in BANKS}

        speed, load = self.schedule.setpoint(0.0)
        self.speed = speed
        self.torque = load * self._T_rated
        self._update_flow()
        self.p_gas: dict[str, float] = {}
        self._delay: dict[str, list[float]] = {}
        self._delay_i = 0
        for b in BANKS:
            dp = self._dp_ss(b)
            self.p_gas[b] = dp
            self._delay[b] = [dp] * max(1, self._n_delay)
        self.truth = {b: self.p_gas[b] for b in BANKS}

        # noise: one independent stream per bank
        children = np.random.SeedSequence(seed).spawn(len(BANKS))
        self._rng = {
            b: np.random.Generator(np.random.PCG64(s)) for b, s in zip(BANKS, children, strict=True)
        }
        self._phase = {b: float(self._rng[b].uniform(0.0, 2.0 * math.pi)) for b in BANKS}
        self._noise_buf: dict[str, tuple[list[float], list[float]]] = {}
        self._noise_i = _NOISE_BLOCK
        self._draw_noise()
        self.noise = {b: 0.0 for b in BANKS}
        self._update_noise()

        self._messages: list[tuple[str, int, tuple[str, ...]]] | None = None
        self._messages_db: CellDatabase | None = None

    # -- time ---------------------------------------------------------------------------
    @property
    def t(self) -> float:
        """Simulation time in s (``k x dt``)."""
        return self.k * self.dt

    # -- inputs -------------------------------------------------------------------------
    def set_demand(self, bank: str, percent: float) -> None:
        """Set the valve demand of bank ``"L"`` or ``"R"`` in % open (clamped to 0..100)."""
        if bank not in self.valves:
            raise ConfigError(f"unknown bank {bank!r}; use 'L' or 'R'")
        percent = float(percent)
        if math.isnan(percent):
            raise ConfigError(f"valve demand for bank {bank} is NaN")
        self.valves[bank].demand = min(max(percent, 0.0), 100.0)

    # -- internals ----------------------------------------------------------------------
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

    def _dp_ss(self, bank: str) -> float:
        p = self.params
        m = 0.5 * self.flow
        a = valve_area(self.valves[bank].position, p.valve_leak)
        return m * m * (p.k_sys + p.k_valve / (a * a))

    def _draw_noise(self) -> None:
        p = self.params
        n = _NOISE_BLOCK
        for b in BANKS:
            rng = self._rng[b]
            walk = rng.standard_normal(n) * (p.pulsation_phase_diffusion * math.sqrt(p.dt))
            white = np.clip(
                rng.standard_t(p.t_noise_df, n) * p.t_noise_scale, -p.t_noise_clip, p.t_noise_clip
            )
            spike = rng.random(n) < p.spike_probability
            mag = rng.uniform(p.spike_min, p.spike_max, n) * np.where(
                rng.random(n) < 0.5, -1.0, 1.0
            )
            white = white + np.where(spike, mag, 0.0)
            self._noise_buf[b] = (walk.tolist(), white.tolist())
        self._noise_i = 0

    def _update_noise(self) -> None:
        if self._noise_i >= _NOISE_BLOCK:
            self._draw_noise()
        i = self._noise_i
        self._noise_i += 1
        p = self.params
        # firing frequency of one bank (cylinders/2 per bank, one firing per 2 revolutions)
        w = 2.0 * math.pi * (p.cylinders / 2) * self.speed / 120.0 * self.dt
        amp = p.pulsation_amplitude * self.flow / self._flow_rated
        for b in BANKS:
            walk, white = self._noise_buf[b]
            ph = (self._phase[b] + w + walk[i]) % (2.0 * math.pi)
            self._phase[b] = ph
            self.noise[b] = amp * math.sin(ph) + white[i]

    # -- stepping -----------------------------------------------------------------------
    def step(self) -> None:
        """Advance the plant by ``dt``."""
        p = self.params
        self.k += 1
        if self.state == RUNNING:
            sp_speed, sp_load = self.schedule.setpoint(self.k * self.dt)
            self.speed += self._a_speed * (sp_speed - self.speed)
            self.torque += self._a_torque * (sp_load * self._T_rated - self.torque)
        else:
            self.speed -= self._a_speed * self.speed
            self.torque -= self._a_torque * self.torque
            if self.speed < p.stop_speed:
                self.speed = 0.0
                self.torque = 0.0
        self._update_flow()
        a_gas = self._a_gas
        n = len(self._delay["L"])
        j = self._delay_i
        for b in BANKS:
            self.valves[b].step()
            pg = self.p_gas[b] + a_gas * (self._dp_ss(b) - self.p_gas[b])
            self.p_gas[b] = pg
            if self._n_delay:
                buf = self._delay[b]
                self.truth[b] = buf[j]  # the value written n_delay steps ago
                buf[j] = pg
            else:
                self.truth[b] = pg
        self._delay_i = (j + 1) % n
        if self.state == RUNNING:
            for b in BANKS:
                if self.p_gas[b] > self.bp_limit:
                    self.state = TRIPPED
                    self.trip_reason = TRIP_EXH_BP_LIMIT
                    self.trip_bank = b
                    self.trip_time = self.t
                    break
        self._update_noise()

    def run(self, seconds: float) -> None:
        """Step the plant for ``seconds`` of simulation time."""
        for _ in range(round(seconds / self.dt)):
            self.step()

    # -- outputs ------------------------------------------------------------------------
    def raw(self, bank: str) -> float:
        """The noisy sensor value of one bank, clamped to the sensor range, mmH2O."""
        p = self.params
        return min(max(self.truth[bank] + self.noise[bank], p.sensor_min), p.sensor_max)

    def signals(self) -> dict[str, float]:
        """Every DBC signal the SIM node sends, at the current time."""
        vl, vr = self.valves["L"].position, self.valves["R"].position
        return {
            "ENGINE_SPEED": self.speed,
            "ENGINE_TORQUE": max(self.torque, 0.0),
            "FUEL_RATE": self.fuel_kgph / self.params.fuel_density,
            "ENGINE_POWER": max(self.power_kw, 0.0),
            "EXH_BP_L": self.raw("L"),
            "EXH_BP_R": self.raw("R"),
            "VALVE_POS_L": vl,
            "VALVE_POS_R": vr,
            "ENGINE_STATE": float(self.state),
            "TRIP_REASON": float(self.trip_reason),
            "EXH_BP_LIMIT": self.bp_limit,
            "ENGINE_LOAD": min(max(100.0 * self.torque / self._T_rated, 0.0), 110.0),
            "EXH_BP_L_TRUE": self.truth["L"],
            "EXH_BP_R_TRUE": self.truth["R"],
            "EXH_FLOW_TRUE": self.flow,
            "VALVE_POS_L_TRUE": vl,
            "VALVE_POS_R_TRUE": vr,
        }

    def _sim_messages(self, db: CellDatabase) -> list[tuple[str, int, tuple[str, ...]]]:
        if self._messages is None or self._messages_db is not db:
            out = []
            for m in db.db.messages:
                if "SIM" not in (m.senders or []):
                    continue
                if not m.cycle_time:
                    raise ConfigError(f"{db.path.name}: SIM message {m.name} has no cycle time")
                period = max(1, round(m.cycle_time / 1000.0 / self.dt))
                out.append((m.name, period, tuple(s.name for s in m.signals)))
            self._messages = out
            self._messages_db = db
        return self._messages

    def frames(self, db: CellDatabase, t0: float = 0.0) -> list[can.Message]:
        """DBC-encoded frames due at the current step, stamped ``t0 + t``.

        A message with cycle time ``c`` is due when ``t`` is a multiple of ``c`` (so every
        message is sent at ``t`` = 0). Call once per step, before :meth:`step`.
        """
        due = [
            (name, sigs) for name, period, sigs in self._sim_messages(db) if self.k % period == 0
        ]
        if not due:
            return []
        values = self.signals()
        ts = t0 + self.t
        return [db.encode(name, {s: values[s] for s in sigs}, ts) for name, sigs in due]


def simulate(
    db: CellDatabase,
    cycle: str | DutyCycle = "rated",
    seed: int = 0,
    duration: float | None = None,
    t0: float = 0.0,
    initial_valve: float | None = None,
    params: PlantParams | None = None,
    bp_limit: float | None = None,
) -> Iterator[can.Message]:
    """Frames of an open-loop run, in time order, in lockstep with the plant (no wall clock).

    Frames are stamped ``t0 + t`` for ``t`` = 0, dt, ... up to (not including) ``duration``
    (default: the duty cycle's nominal length). Every SIM message of the DBC is sent at its
    cycle time; VALVE_DEMAND is the runtime's and is not sent.
    """
    if bp_limit is not None:
        params = replace(params or PlantParams(), bp_limit=float(bp_limit))
    plant = Plant(cycle, seed=seed, params=params, initial_valve=initial_valve)
    if duration is None:
        duration = plant.schedule.duration
    n = round(duration / plant.dt)
    for _ in range(n):
        yield from plant.frames(db, t0)
        plant.step()
