"""PI back-pressure controller, one per exhaust bank (seed 004, "Practical application").

Seed 004 closes a PI loop on the exhaust butterfly valve, from 100 % open (open loop) to
680 mmH2O, with the raw signal, the moving average or the Kalman filter as feedback
(its Figure 10). :class:`PIController` is that loop as a native runtime block: it reads
the chosen feedback channel and writes ``VALVE_DEMAND_L``/``VALVE_DEMAND_R``, which are
DBC signals of the runtime's ``VALVE_DEMAND`` message, so the runtime puts the demand on
the bus to the simulator's valve.

Sign of the loop
----------------
The output is the valve **opening** demand in %. Closing the valve raises the
back-pressure, so the plant gain dΔp/dθ is negative (about -25 to -40 mmH2O per % near
40 % open). The controller is therefore *reverse acting*: it works on the error

.. math:: e = y - r

(measurement minus setpoint, the opposite of the usual :math:`r - y`), so that with
positive ``kp`` and ``ki`` a back-pressure above the setpoint opens the valve:

.. math::
    I_k = I_{k-1} + k_i e_k \\Delta t, \\qquad u_k = k_p e_k + I_k

followed by the output limits and the rate limit. ``kp`` is in % per mmH2O and ``ki`` in
% per (mmH2O·s).
"""

from __future__ import annotations

import functools
import math
from typing import Any, ClassVar

from cell.bus.dbc import load
from cell.core.errors import ConfigError, ParamError
from cell.core.options import Option, parse_bool
from cell.core.registry import BlockSet
from cell.runtime.blocks import Block, Param

#: Anti-windup schemes: ``clamp`` (conditional integration) or ``backcalc`` (back-calculation).
ANTIWINDUP = ("clamp", "backcalc")

#: Feedback shorthands accepted by :func:`controllers` (``{bank}`` is ``L`` or ``R``).
FEEDBACK = {
    "raw": "EXH_BP_{bank}",
    "maf": "EXH_BP_{bank}_MAF",
    "kalman": "EXH_BP_{bank}_Kalman",
    "adaptive": "EXH_BP_{bank}_Adaptive",
}

#: The valve opening that lowers the back-pressure most: fully open, %.
SAFE_OUTPUT = 100.0
#: Seconds a controller holds its last output while its feedback is bad, then goes safe.
HOLD_S = 1.0
#: The channel that says whether the engine runs (DBC ``ENGINE_STATUS``).
INTERLOCK = "ENGINE_STATE"


@functools.cache
def running_code(signal: str = INTERLOCK, name: str = "RUNNING") -> int:
    """The value of ``signal`` that the cell's DBC names ``name`` (``VAL_`` table)."""
    sig = load().message_for(signal).get_signal_by_name(signal)
    for value, label in (sig.choices or {}).items():
        if str(label) == name:
            return int(value)
    raise ConfigError(f"the DBC names no value of {signal} {name!r}")


#: Default gains; see :class:`PIController` for the reasoning.
DEFAULT_KP = 0.005
DEFAULT_KI = 0.013
DEFAULT_RATE = 5.0


def _channel_name(field: str, value: Any, allow_empty: bool = False) -> str:
    """Check a channel-name parameter: a non-empty string of printable, space-free text."""
    if not isinstance(value, str):
        raise ParamError(field, f"must be a channel name (a string), got {type(value).__name__} "
                                f"{value!r}")
    value = value.strip()
    if not value:
        if allow_empty:
            return ""
        raise ParamError(field, "must be a channel name, got an empty string")
    if len(value) > 128 or any(c.isspace() or not c.isprintable() for c in value):
        raise ParamError(field, f"must be a channel name without spaces, got {value!r}")
    return value


class PIController(Block):
    r"""PI controller of one bank's exhaust back-pressure (seed 004, Figure 10).

    Parameters
    ----------
    bank:
        ``"L"`` or ``"R"``; the block is named ``PI_<bank>`` unless ``name`` is given and
        writes ``VALVE_DEMAND_<bank>``.
    feedback:
        Channel read as the measurement: raw ``EXH_BP_R``, ``EXH_BP_R_MAF``,
        ``EXH_BP_R_Kalman``, ``EXH_BP_R_Adaptive`` or any other channel.
    setpoint:
        Target back-pressure, mmH2O (seed 004: 680).
    kp, ki:
        Proportional gain, %/mmH2O, and integral gain, %/(mmH2O·s); both >= 0.
    antiwindup:
        ``"clamp"`` (conditional integration: the integrator stops while the output sits
        at a limit or at the rate limit and the error pushes further into it) or
        ``"backcalc"`` (back-calculation with gain ``kt``, 1/s).
    out_min, out_max:
        Output limits, % open.
    rate_limit:
        Largest output change, %/s (0: none).
    enable:
        ``False`` is open loop (manual): the output tracks the valve position read from
        ``track`` (or holds ``manual`` when ``track`` is empty), so switching to ``True`` is
        bumpless: the integrator starts at the last output.
    track:
        Channel of the actual valve position followed while disabled (default
        ``VALVE_POS_<bank>``); ``""`` holds ``manual`` instead.
    manual:
        Opening held while disabled when ``track`` is empty, % (seed 004 starts 100 % open).
    safe_output:
        Opening while the engine is not running and after the feedback has been bad for
        ``hold_s``, % (default 100: fully open, which lowers the back-pressure most).
    hold_s:
        Seconds the last output is held, integrator frozen, while the feedback (or another
        input) is invalid or stale, before going to ``safe_output`` (default 1).
    interlock, running_state:
        The channel that says whether the engine runs (default ``ENGINE_STATE``; ``""``:
        none) and its value while it runs (default: the DBC's ``RUNNING``). Any other value
        (tripped, stopped) puts the output at ``safe_output`` with the integrator reset to
        it, so there is no wind-up during a trip: after the reset the loop starts from the
        open valve, bumplessly.
    rate:
        Runtime task, default ``MED`` (10 Hz, the rate of seed 004's filters).

    Notes
    -----
    Default gains, ``kp`` = 0.005 %/mmH2O, ``ki`` = 0.013 %/(mmH2O·s), rate limit 5 %/s,
    follow from the plant (seed 004's loop, as emulated in :mod:`cell.plant`):

    - near the 680 mmH2O operating point (40 % open at rated) the plant gain is
      g ≈ -38 mmH2O/% (-23 at 45 %, -67 at 35 %, -124 at 30 %);
    - ``kp`` is set by noise, not speed: the demand noise ``kp`` x (feedback error) must
      stay well inside the valve's 0.5 % dead-band with a filtered feedback. With the
      Kalman filter's ~15 mmH2O steady error that is 0.075 %; raw feedback (std ~75
      mmH2O, spikes to 400) gives 0.4 % std and 2 % spikes, so the valve hunts;
    - ``ki`` is chosen for a 60° phase margin (a usual, robust choice when the process gain
      varies by 3x over the approach) of the loop *with the Kalman filter* at 40 % open:
      with C(s) = kp + ki/s and |g| = 38 the crossover is ω_c ≈ 0.50 rad/s; the phase
      there is -79° (PI) - 11° (gas lag 0.4 s) - 6° (sensor delay 0.15 s plus the 10 Hz
      sample-and-hold, 0.05 s) - 26° (Kalman filter, K = 0.095 at 10 Hz: a first-order
      lag of ~0.95 s), a margin of 58°. The same gains leave the 30-sample moving average
      (a pure delay of 1.45 s: -42°) a margin of 42°, and less on the steep side of the
      operating point: its loop is the lightly damped one, as in seed 004's Figure 10;
    - the rate limit equals the actuator's 5 %/s, so the demand never runs ahead of the
      valve (the limit also stops the integrator through the anti-windup).

    The gain map of ``testcell experiment closed-loop --gain-map`` shows how much of the
    Kalman filter's advantage is due to this choice: at lower ``ki`` (the moving
    average's own best gains) the two filters settle alike.
    """

    kind = "pi"
    family = "controller"
    PARAMS: ClassVar[dict[str, Param]] = {
        "setpoint": Param("setpoint", float, "target back-pressure, mmH2O", ge=-500.0, le=20000.0),
        "kp": Param("kp", float, "proportional gain, % per mmH2O", ge=0.0, le=100.0),
        "ki": Param("ki", float, "integral gain, % per mmH2O·s", ge=0.0, le=100.0),
        "kt": Param("kt", float, "back-calculation gain, 1/s (antiwindup=backcalc)", ge=0.0,
                    le=1000.0),
        "out_min": Param("out_min", float, "lowest output, % open", ge=0.0, le=100.0),
        "out_max": Param("out_max", float, "highest output, % open", ge=0.0, le=100.0),
        "rate_limit": Param("rate_limit", float, "largest output change, %/s (0: none)",
                            ge=0.0, le=1000.0),
        "manual": Param("manual", float, "opening held while disabled without track, %",
                        ge=0.0, le=100.0),
        "safe_output": Param("safe_output", float, "opening while the engine is not running, or "
                             "the feedback is bad for longer than hold_s, % (100: fully open, "
                             "the lowest back-pressure)", ge=0.0, le=100.0),
        "hold_s": Param("hold_s", float, "how long the last output is held while the feedback "
                        "is invalid or stale before going to safe_output, s", ge=0.0, le=60.0),
        "running_state": Param("running_state", int, "value of the interlock channel while the "
                               "engine runs (DBC: ENGINE_STATE = RUNNING)", ge=0, le=255),
    }
    #: parameters that are not numbers; checked in :meth:`validate`
    TEXT_PARAMS: ClassVar[tuple[str, ...]] = ("feedback", "track", "interlock", "antiwindup")
    #: the channel parameters and the unit each channel must have (the runtime checks them)
    CHANNEL_PARAMS: ClassVar[dict[str, str]] = {"feedback": "mmH2O", "track": "%", "interlock": ""}
    FLAG_PARAMS: ClassVar[tuple[str, ...]] = ("enable",)

    def __init__(
        self,
        bank: str = "R",
        feedback: str | None = None,
        *,
        name: str | None = None,
        setpoint: float = 680.0,
        kp: float = DEFAULT_KP,
        ki: float = DEFAULT_KI,
        antiwindup: str = "clamp",
        kt: float = 1.0,
        out_min: float = 0.0,
        out_max: float = 100.0,
        rate_limit: float = DEFAULT_RATE,
        enable: bool = False,
        track: str | None = None,
        manual: float = 100.0,
        safe_output: float = SAFE_OUTPUT,
        hold_s: float = HOLD_S,
        interlock: str = INTERLOCK,
        running_state: int | None = None,
        rate: str = "MED",
    ) -> None:
        if bank not in ("L", "R"):
            raise ParamError("bank", f"must be 'L' or 'R', got {bank!r}")
        self.bank = bank
        output = f"VALVE_DEMAND_{bank}"
        super().__init__(name or f"PI_{bank}", [], [output], rate)
        self.output = output
        # defaults for every field, then one validated pass over all of them
        self.feedback = f"EXH_BP_{bank}_Kalman"
        self.track = f"VALVE_POS_{bank}"
        self.antiwindup = "clamp"
        self.interlock = INTERLOCK
        self.enable = False
        self._starting = False
        #: what the output follows: ``manual``, ``auto``, or why it holds or is safe
        self.mode = "manual"
        #: bus time since which the feedback has been bad (``None``: it is ok)
        self._bad_since: float | None = None
        #: last output, %; None before the first tick
        self.u: float | None = None
        for key in self.PARAMS:
            setattr(self, key, 0.0)
        self.out_max = 100.0
        initial = {
            "feedback": feedback if feedback is not None else f"EXH_BP_{bank}_Kalman",
            "track": track if track is not None else f"VALVE_POS_{bank}",
            "antiwindup": antiwindup, "enable": enable, "setpoint": setpoint, "kp": kp,
            "ki": ki, "kt": kt, "out_min": out_min, "out_max": out_max,
            "rate_limit": rate_limit, "manual": manual, "safe_output": safe_output,
            "hold_s": hold_s, "interlock": interlock,
            "running_state": running_code() if running_state is None else running_state,
        }
        #: integrator state, %
        self.integral = 0.0
        self.error: float | None = None
        self.saturated = False
        self._t_last: float | None = None
        self._apply(self.validate(initial))

    # -- parameters -----------------------------------------------------------------
    def params(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "feedback": self.feedback, "enable": self.enable, "antiwindup": self.antiwindup,
            "track": self.track, "interlock": self.interlock,
        }
        out.update({p: getattr(self, p) for p in self.PARAMS})
        return out

    def _known(self) -> str:
        return ", ".join([*self.TEXT_PARAMS, *self.FLAG_PARAMS, *self.PARAMS])

    def validate(self, changes: dict[str, Any]) -> dict[str, Any]:
        """Check a change as a whole, the numeric fields through :class:`Param`, the
        channel names, the anti-windup scheme and ``enable`` here; then the limits
        against each other (``out_min`` <= ``out_max``, with unchanged fields as they are).
        """
        if not isinstance(changes, dict):
            raise ParamError("body", f"must be an object of parameters, got "
                                     f"{type(changes).__name__}")
        if not changes:
            return super().validate(changes)  # raises: names no parameter
        checked: dict[str, Any] = {}
        numeric: dict[str, Any] = {}
        for key, value in changes.items():
            if key == "feedback":
                checked[key] = _channel_name(key, value)
            elif key in ("track", "interlock"):
                checked[key] = _channel_name(key, value, allow_empty=True)
            elif key == "antiwindup":
                if value not in ANTIWINDUP:
                    raise ParamError(key, f"must be one of {', '.join(ANTIWINDUP)}, got {value!r}")
                checked[key] = value
            elif key == "enable":
                if not isinstance(value, bool):
                    raise ParamError(key, f"must be true or false, got {value!r}")
                checked[key] = value
            else:
                numeric[key] = value
        if numeric:
            checked.update(super().validate(numeric))
        lo = checked.get("out_min", self.out_min)
        hi = checked.get("out_max", self.out_max)
        if lo > hi:
            field = "out_min" if "out_min" in checked else "out_max"
            raise ParamError(field, f"out_min ({lo:g}) must not exceed out_max ({hi:g})")
        if checked.get("feedback") is not None and checked["feedback"] in self.outputs:
            raise ParamError("feedback", f"cannot be the controller's own output {self.output}")
        return checked

    def _apply(self, checked: dict[str, Any]) -> None:
        was_enabled = self.enable
        super()._apply(checked)
        self.inputs = list(dict.fromkeys(
            [self.feedback] + [c for c in (self.track, self.interlock) if c]))
        if self.enable and not was_enabled:
            self._starting = True

    # -- stepping -------------------------------------------------------------------
    #: a restarted cell never drives the valve until someone enables the loop again
    VOLATILE = ("enable",)

    def safe_unsaved(self, changes: dict[str, Any]) -> bool:
        """Switching the loop off is a safety action: it never waits for the disk."""
        return isinstance(changes, dict) and changes.get("enable") is False

    @property
    def on_bus(self) -> bool:  # type: ignore[override]
        """A disabled controller keeps its demand off the bus (the valve holds its opening)
        unless another bank's enabled controller sends their shared frame: then the frame
        carries this one's manual output (the tracked valve position, or ``manual``), or its
        safe output while an input is bad."""
        return bool(self.enable)

    def _step(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        dt = 0.0 if self._t_last is None else max(t - self._t_last, 0.0)
        self._t_last = t
        y = inputs[self.feedback]
        if not math.isfinite(y):
            raise ArithmeticError(f"feedback {self.feedback} is {y}")
        self._bad_since = None
        self.error = e = y - self.setpoint  # reverse acting: above the setpoint opens
        if not self.enable:
            held = inputs[self.track] if self.track else self.manual
            self.u = min(max(held, self.out_min), self.out_max)
            self.integral = self.u
            self.saturated = False
            self.mode = "manual"
            return {self.output: self.u}
        if self.interlock:
            state = inputs.get(self.interlock)
            if state != self.running_state:  # tripped or stopped: no loop to close
                return self._safe(f"{self.interlock} = {state:g}, not {self.running_state} "
                                  f"(running)" if state is not None else
                                  f"{self.interlock} has no value")
        self.mode = "auto"
        if self.u is None:  # enabled from the first tick: start from the manual opening
            self.u = self.manual
            self._starting = True
        if self._starting:
            # bumpless transfer: choose the integrator so that this tick's output is the
            # last one (u = kp e + I with I = u_last - kp e)
            # and hold it for this tick (no integration, no rate step)
            self._starting = False
            self.integral = self.u - self.kp * e
            self.saturated = False
            return {self.output: self.u}
        lo, hi = self.out_min, self.out_max
        i_new = self.integral + self.ki * e * dt
        u_want = self.kp * e + i_new
        u_lim = min(max(u_want, lo), hi)
        step_max = self.rate_limit * dt if self.rate_limit > 0 else math.inf
        u_out = self.u + min(max(u_lim - self.u, -step_max), step_max)
        self.saturated = u_out != u_want
        if self.antiwindup == "backcalc":
            self.integral = i_new + self.kt * (u_out - u_want) * dt
        elif not (self.saturated and (u_want - u_out) * e > 0):
            # conditional integration: integrate unless the output is held back by a limit
            # and the error would drive the integrator further into it
            self.integral = i_new
        self.u = u_out
        return {self.output: u_out}

    def _safe(self, why: str) -> dict[str, float]:
        """Go to the safe output with the integrator reset to it: when the loop may run
        again it starts bumplessly from there (no wind-up while it could not act)."""
        self.u = self.integral = min(max(self.safe_output, self.out_min), self.out_max)
        self.saturated = False
        self._starting = True
        self.mode = f"safe: {why}"
        return {self.output: self.u}

    def fallback(self, t: float, reason: str) -> dict[str, float] | None:
        """While an input is invalid or stale: hold the last output (integrator frozen) for
        ``hold_s``, then go to the safe output. A disabled controller goes to the safe
        output at once (it has no loop to hold): when the other bank's controller keeps
        their shared demand frame on the bus, this bank's valve gets its safe opening."""
        if not self.enable:
            self.u = self.integral = min(max(self.safe_output, self.out_min), self.out_max)
            self.saturated = False
            self.mode = f"manual, safe: {reason}"
            return {self.output: self.u}
        self._t_last = t
        if self._bad_since is None:
            self._bad_since = t
        if self.u is not None and not self.mode.startswith("safe") and \
                t - self._bad_since < self.hold_s:
            self.saturated = False
            self.mode = f"hold: {reason}"
            return {self.output: self.u}
        return self._safe(reason)

    def state(self) -> dict[str, Any]:
        return {"integral": self.integral, "output": self.u, "error": self.error,
                "saturated": self.saturated, "mode": self.mode}


def controllers(
    feedback: str = "kalman", banks: tuple[str, ...] = ("L", "R"), **settings: Any
) -> list[PIController]:
    """One :class:`PIController` per bank.

    Parameters
    ----------
    feedback:
        ``raw``, ``maf``, ``kalman``, ``adaptive`` (the bank's ``EXH_BP_<bank>...`` channel)
        or a channel-name pattern with ``{bank}``, e.g. ``"EXH_BP_{bank}_MAF"``.
    settings:
        Further :class:`PIController` keywords (``kp``, ``ki``, ``enable``...).
    """
    pattern = FEEDBACK.get(feedback, feedback)
    return [PIController(b, pattern.format(bank=b), **settings) for b in banks]


#: seed 004's PI controllers on the Kalman-filtered back-pressure; they start disabled and keep
#: off the bus until enabled over HTTP. ``--no-controllers`` leaves them out (e.g. to drive the
#: valve from a script).
BACKPRESSURE_CONTROLLERS = BlockSet(
    "seed004-controllers",
    lambda run: [] if run.blocks.get("no_controllers") else controllers("kalman"),
    engines=("large-diesel",),
    options=(Option("no_controllers", "--no-controllers", parse_bool, switch=True,
                    help="no native PI controllers (e.g. to drive the valve from a script)"),))
