"""Two exhaust banks with butterfly back-pressure valves, their sensors, and the protection.

Signal chain per bank (seed 004: back-pressure "noisy and erratic", +-200 mmH2O raw)::

    exhaust mass flow ─▶ Δp = m² (k_sys + k_valve / a(θ)²)
                     ─▶ gas-volume lag (tau_gas) ─▶ sensor-line delay ─▶ EXH_BP_x_TRUE
                     ─▶ + pulsation + Student-t + spikes ─▶ EXH_BP_x

The engine protection watches the noise-free back-pressure of both banks; above
``bp_limit`` it trips the engine (``ENGINE_STATE`` = 2, read by the engine, which runs
down). Seed 004's raw-signal loop "triggered an engine limit". A trip holds until the
operator resets it in two steps (``ENGINE_CMD``): a request carrying a challenge value
(``ENGINE_RESET_REQ`` = N), then within ``reset_window`` a confirm carrying the same value
(``ENGINE_RESET_CONFIRM`` = N). The confirm clears the trip only if its cause has cleared:
both banks' back-pressure below ``bp_limit - reset_margin``. A single frame never resets;
``RESET_STATE`` tells what the last step did. ``POST /engine/reset`` and
``/engine/reset/confirm`` send the two steps; so can ``testcell scenario``.

In the safe state (:meth:`ExhaustBanks.set_safe`: the command watchdog, or the simulator's
parent died) both valves run fully open, whatever the demand, as that lowers back-pressure.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from cell.core.errors import ConfigError
from cell.plant.base import Plant, lag_factor
from cell.plant.diesel import RUNNING, TRIPPED

BANKS = ("L", "R")
#: ``TRIP_REASON`` values (DBC ``VAL_ 259 TRIP_REASON``).
TRIP_NONE, TRIP_EXH_BP_LIMIT = 0, 1
#: ``RESET_STATE`` values (DBC ``VAL_ 264 RESET_STATE``).
(RESET_NONE, RESET_PENDING, RESET_DONE, RESET_REFUSED_CAUSE, RESET_REFUSED_NO_REQUEST,
 RESET_REFUSED_NOT_TRIPPED, RESET_REFUSED_BAD_FRAME) = range(7)
#: The two steps' signals (DBC ``ENGINE_CMD``).
RESET_REQUEST, RESET_CONFIRM = "ENGINE_RESET_REQ", "ENGINE_RESET_CONFIRM"
#: Valve opening of the safe state, %: fully open lowers back-pressure.
SAFE_VALVE = 100.0

_NOISE_BLOCK = 2048  # noise samples drawn per numpy call, per bank


@dataclass(frozen=True)
class ExhaustParams:
    """Every constant of the exhaust banks, valves, sensors and protection."""

    period: float = 0.01
    """Step period, s. 100 Hz: ten plant samples per 10 Hz logger sample (seed 004 logs
    at 10 Hz), and twice the runtime's fastest task (FAS, 50 Hz)."""

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

    reset_margin: float = 100.0
    """A reset clears a trip only when both banks' noise-free back-pressure is this far below
    ``bp_limit``, mmH2O: the cause has cleared, and the engine does not re-trip at once."""

    reset_window: float = 2.0
    """Longest time from a reset request to its confirm, s."""

    # -- measurement noise ------------------------------------------------------------
    cylinders_per_bank: int = 8
    """Cylinders per exhaust bank: a 60 L engine of this class is a V16. Sets the firing
    frequency of the exhaust pulsation."""

    rated_flow: float = 3.19
    """Total exhaust mass flow at rated, kg/s, the reference of the pulsation amplitude. The
    ``large-diesel`` profile sets it from the engine (:func:`~cell.plant.diesel.exhaust_flow`)."""

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


# -- equations ------------------------------------------------------------------------------
def valve_area(theta: float, leak: float) -> float:
    """Butterfly effective area relative to fully open: leak + (1 - leak)(1 - cos(π/2 θ/100))."""
    return leak + (1.0 - leak) * (1.0 - math.cos(math.pi / 2.0 * theta / 100.0))



def back_pressure(p: ExhaustParams, bank_flow: float, theta: float) -> float:
    """Steady back-pressure of one bank, mmH2O: m² (k_sys + k_valve / a(θ)²)."""
    a = valve_area(theta, p.valve_leak)
    return bank_flow * bank_flow * (p.k_sys + p.k_valve / (a * a))


def valve_for_back_pressure(p: ExhaustParams, target: float, bank_flow: float) -> float:
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



def gas_rhs(t: float, x: float, u: Sequence[float], p: ExhaustParams) -> float:
    """d/dt of one bank's gas-volume pressure for u = (bank flow kg/s, valve opening %):
    a first-order lag with ``tau_gas`` towards the steady :func:`back_pressure`."""
    bank_flow, theta = u
    return (back_pressure(p, bank_flow, theta) - x) / p.tau_gas


# -- the plant ------------------------------------------------------------------------------
class Valve:
    """Butterfly actuator: rate limit, dead-band, resolution (positions are k x resolution)."""

    __slots__ = ("deadband", "demand", "moving", "rate_step", "res", "x")

    def __init__(self, position: float, p: ExhaustParams) -> None:
        self.res = p.valve_resolution
        self.x = self._quantise(position)
        self.demand = self.x
        self.moving = False
        self.rate_step = p.valve_rate * p.period
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



class ExhaustBanks(Plant):
    """Exhaust banks L and R: back-pressure, butterfly valves, sensors, noise, protection.

    Parameters
    ----------
    params:
        :class:`ExhaustParams`.
    seed:
        Seeds the numpy Generator of the measurement noise (one stream per bank); same
        seed, same run.
    initial_valve:
        Valve opening in % held until a ``VALVE_DEMAND_*`` input arrives.

    The banks start in steady state at the engine's initial flow.
    """

    inputs = ("ENGINE_SPEED", "EXH_FLOW_TRUE", "VALVE_DEMAND_L", "VALVE_DEMAND_R")
    commands = (RESET_REQUEST, RESET_CONFIRM)
    outputs = ("EXH_BP_L", "EXH_BP_R", "VALVE_POS_L", "VALVE_POS_R", "ENGINE_STATE",
               "TRIP_REASON", "RESET_STATE", "EXH_BP_LIMIT", "EXH_BP_L_TRUE", "EXH_BP_R_TRUE",
               "VALVE_POS_L_TRUE", "VALVE_POS_R_TRUE")

    def __init__(self, params: ExhaustParams | None = None, seed: int = 0,
                 initial_valve: float = 100.0, name: str = "exhaust") -> None:
        p = self.params = params if params is not None else ExhaustParams()
        super().__init__(name, p.period)
        initial_valve = float(initial_valve)
        if not 0.0 <= initial_valve <= 100.0 or math.isnan(initial_valve):
            raise ConfigError(f"initial valve opening must be 0..100 %, got {initial_valve}")
        self.seed = seed
        self.bp_limit = float(p.bp_limit)
        self.state = RUNNING
        self.trip_reason = TRIP_NONE
        self.trip_bank: str | None = None  # bank whose back-pressure tripped the engine
        self.trip_time: float | None = None  # simulation time of the trip, s
        self.reset_state = RESET_NONE
        self._reset_request: tuple[int, float] | None = None  # (challenge, time) pending
        self.safe = False
        self._a_gas = lag_factor(p.period, p.tau_gas)
        self._n_delay = max(0, round(p.sensor_delay / p.period))
        self.valves = {b: Valve(initial_valve, p) for b in BANKS}
        self.speed = 0.0
        self.flow = 0.0

    def start(self, u: Mapping[str, float]) -> None:
        self.speed = u["ENGINE_SPEED"]
        self.flow = u["EXH_FLOW_TRUE"]
        self.p_gas: dict[str, float] = {}
        self._delay: dict[str, list[float]] = {}
        self._delay_i = 0
        for b in BANKS:
            dp = self._dp_ss(b)
            self.p_gas[b] = dp
            self._delay[b] = [dp] * max(1, self._n_delay)
        self.truth = {b: self.p_gas[b] for b in BANKS}
        children = np.random.SeedSequence(self.seed).spawn(len(BANKS))
        self._rng = {
            b: np.random.Generator(np.random.PCG64(s)) for b, s in zip(BANKS, children, strict=True)
        }
        self._phase = {b: float(self._rng[b].uniform(0.0, 2.0 * math.pi)) for b in BANKS}
        self._noise_buf: dict[str, tuple[list[float], list[float]]] = {}
        self._noise_i = _NOISE_BLOCK
        self._draw_noise()
        self.noise = {b: 0.0 for b in BANKS}
        self._update_noise()

    def _dp_ss(self, bank: str) -> float:
        return back_pressure(self.params, 0.5 * self.flow, self.valves[bank].position)

    def _draw_noise(self) -> None:
        p = self.params
        n = _NOISE_BLOCK
        for b in BANKS:
            rng = self._rng[b]
            walk = rng.standard_normal(n) * (p.pulsation_phase_diffusion * math.sqrt(p.period))
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
        # firing frequency of one bank (one firing per cylinder per 2 revolutions)
        w = 2.0 * math.pi * p.cylinders_per_bank * self.speed / 120.0 * self.period
        amp = p.pulsation_amplitude * self.flow / p.rated_flow
        for b in BANKS:
            walk, white = self._noise_buf[b]
            ph = (self._phase[b] + w + walk[i]) % (2.0 * math.pi)
            self._phase[b] = ph
            self.noise[b] = amp * math.sin(ph) + white[i]

    def step(self, t: float, u: Mapping[str, float]) -> None:
        self.speed = u["ENGINE_SPEED"]
        self.flow = u["EXH_FLOW_TRUE"]
        for b in BANKS:
            demand = SAFE_VALVE if self.safe else u.get(f"VALVE_DEMAND_{b}")
            if demand is not None:
                self.valves[b].demand = min(max(demand, 0.0), 100.0)
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
                    self.trip_time = t
                    break
        self._update_noise()

    def set_safe(self, safe: bool) -> None:
        self.safe = safe

    def cause_cleared(self) -> bool:
        """Whether both banks' back-pressure is ``reset_margin`` below the trip level."""
        level = self.bp_limit - self.params.reset_margin
        return all(self.p_gas[b] < level for b in BANKS)

    def command(self, values: Mapping[str, float], t: float) -> None:
        """One ``ENGINE_CMD`` frame: a reset request, or its confirm (see the module notes)."""
        request = int(values.get(RESET_REQUEST, 0))
        confirm = int(values.get(RESET_CONFIRM, 0))
        if request and confirm:
            self.reset_state = RESET_REFUSED_BAD_FRAME  # one frame is never both steps
            self._reset_request = None
        elif request:
            self._reset_request = (request, t)
            self.reset_state = RESET_PENDING
        elif confirm:
            pending, self._reset_request = self._reset_request, None
            if pending is None or pending[0] != confirm \
                    or t - pending[1] > self.params.reset_window + 1e-9:
                self.reset_state = RESET_REFUSED_NO_REQUEST
            elif self.state != TRIPPED:
                self.reset_state = RESET_REFUSED_NOT_TRIPPED
            elif not self.cause_cleared():
                self.reset_state = RESET_REFUSED_CAUSE
            else:
                self.state = RUNNING
                self.trip_reason = TRIP_NONE
                self.trip_bank = self.trip_time = None
                self.reset_state = RESET_DONE

    def raw(self, bank: str) -> float:
        """The noisy sensor value of one bank, clamped to the sensor range, mmH2O."""
        p = self.params
        return min(max(self.truth[bank] + self.noise[bank], p.sensor_min), p.sensor_max)

    def output(self) -> dict[str, float]:
        vl, vr = self.valves["L"].position, self.valves["R"].position
        return {
            "EXH_BP_L": self.raw("L"),
            "EXH_BP_R": self.raw("R"),
            "VALVE_POS_L": vl,
            "VALVE_POS_R": vr,
            "ENGINE_STATE": float(self.state),
            "TRIP_REASON": float(self.trip_reason),
            "RESET_STATE": float(self.reset_state),
            "EXH_BP_LIMIT": self.bp_limit,
            "EXH_BP_L_TRUE": self.truth["L"],
            "EXH_BP_R_TRUE": self.truth["R"],
            "VALVE_POS_L_TRUE": vl,
            "VALVE_POS_R_TRUE": vr,
        }
