r"""Seed 003's air-path observer: a constant-gain EKF with a gain table over operating points.

The observer runs the default air-path model (:func:`~cell.plant.si_airpath.airpath_rhs`
with :data:`~cell.plant.si_airpath.MODEL_PARAMS`) with output feedback (seed 003, eq. 3):

.. math:: \dot{\hat x} = f(\hat x, u) + K_i\,(y_m - C\hat x)

where :math:`K_i` is the stationary Kalman gain of the operating point :math:`i` nearest to
the current (engine speed, :math:`\hat p_{im}`) (§3.4.2), computed offline by
``testcell design airpath`` (:mod:`cell.design.si_airpath`) from the model
linearised at that point, :math:`R_i` from the stationary measurement variance with a floor
(§3.3.1) and :math:`Q_i` from the stationary model error (§3.3.2). With ``augmentation`` on,
the state carries :math:`\Delta C_{\eta vol}` (§4.2, eq. 5), a constant that scales the
engine's pumping, so that the integral action the proportional feedback lacks removes the
stationary error of :math:`p_{im}` (§4.1).

Discretisation. The air path is stiff (poles from -0.2 to beyond -1000 /s, §3.1.1), too
stiff for an explicit step at the runtime's tick. The observer steps with the
linearly-implicit Euler method (a W-method):

.. math:: \hat x_{k|k-1} = \hat x + (I - \Delta t J)^{-1}\Delta t\, f(\hat x, u)

stable for the stiff poles, exact in its stationary points (:math:`f = 0`), and one model
evaluation per tick. :math:`J` is the model's Jacobian at a recent estimate and input,
recomputed (central differences) only when the throttle, the wastegate, the speed or the
pressures have moved since (:data:`REFRESH`): the fast poles belong to the throttle and
wastegate, and a Jacobian of a far-away point would slow a throttle step down. At a
stationary point :math:`J = A_i`, and :math:`F_i = I + (I - \Delta t A_i)^{-1}\Delta t A_i`
is what the Riccati equation is solved with (:func:`discrete_gain`), so the gains belong to
the discrete observer that actually runs.

The table (:class:`GainTable`, JSON) keeps, per point, the stationary state and input,
:math:`A_i`, :math:`Q_i` and :math:`R_i`; the gains of the default feedback set are stored
too, and any other set (tuning ``feedback``) or tick period is solved for when asked.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg

from cell.runtime.blocks import Param
from cell.core.errors import ConfigError, ParamError
from cell.estimators.contract import DESIGN_FORMAT, DesignError, Estimate, ObserverContract
from cell.estimators.core import numerical_jacobian
from cell.plant import airpath_parts as ap
from cell.plant.si_airpath import MODEL_PARAMS, RPM_PER_RAD_S, SIAirPathParams, airpath_rhs

FORMAT = "testcell-airpath-gains/1"
#: The shipped default table, designed from an ``operating-points`` log (see README).
DEFAULT_TABLE = Path(__file__).with_name("data") / "si_airpath_gains.json"

#: State names of the augmented model (the plain model is the first five).
STATES = ("p_ic", "p_im", "T_im", "p_em", "omega_tc", "dc_eta_vol")
#: Measurements the observer can feed back: channel -> (state index, SI per channel unit,
#: offset), so that ``state = channel * scale + offset``.
MEASUREMENTS: dict[str, tuple[int, float, float]] = {
    "P_IC": (0, 1000.0, 0.0),
    "P_IM": (1, 1000.0, 0.0),
    "T_IM": (2, 1.0, 273.15),
    "N_TC": (4, 1.0 / RPM_PER_RAD_S, 0.0),
}
#: Seed 003's feedback (§3.2.1): the two pressures of the intake side.
DEFAULT_FEEDBACK = ("P_IC", "P_IM")
#: Scale of each state in the Riccati solution (Pa, Pa, K, Pa, rad/s, -).
STATE_SCALE = np.array([1e4, 1e4, 10.0, 1e4, 1e3, 0.01])
#: Scales of the nearest-point distance: (engine speed rpm, p_im Pa).
SCHEDULE_SCALE = (500.0, 15_000.0)
#: Moves since the last Jacobian that refresh it: throttle deg, wastegate (0..1), speed rpm,
#: p_ic and p_im Pa.
REFRESH = (1.0, 0.03, 50.0, 3000.0, 3000.0)


def discrete_gain(A: np.ndarray, Q: np.ndarray, R: np.ndarray, rows: Sequence[int], dt: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    r"""Stationary Kalman gain of the W-method observer at one table point.

    :math:`F = I + (I - \Delta t A)^{-1}\Delta t A`, :math:`H` selects the measured states
    ``rows``; ``scipy.linalg.solve_discrete_are`` is solved in states scaled by
    :data:`STATE_SCALE` (Pa and rad/s against a fraction: a scaled problem is well
    conditioned) and the gain scaled back.

    Returns
    -------
    K, P:
        Gain ``(n, m)`` in SI units per SI unit, and the a-priori covariance ``(n, n)``.
    """
    n = A.shape[0]
    S = np.diag(STATE_SCALE[:n])
    Si = np.diag(1.0 / STATE_SCALE[:n])
    M = np.linalg.solve(np.eye(n) - dt * A, dt * np.eye(n))
    F = np.eye(n) + M @ A
    H = np.zeros((len(rows), n))
    for j, r in enumerate(rows):
        H[j, r] = 1.0
    Fs, Hs = Si @ F @ S, H @ S
    Qs = Si @ np.diag(Q) @ Si
    P = scipy.linalg.solve_discrete_are(Fs.T, Hs.T, Qs, np.diag(R))
    Ks = np.linalg.solve(Hs @ P @ Hs.T + np.diag(R), Hs @ P).T
    return S @ Ks, S @ P @ S


@dataclass
class TablePoint:
    """One operating point of the table: where it is and what the design found there."""

    speed: float
    """Engine speed, rpm."""
    load: float
    """Load demand of the stationary segment it was designed from."""
    u: list[float]
    """Stationary input (throttle deg, wastegate 0..1, speed rpm, λ)."""
    x: list[float]
    """Stationary state of the default model (augmented: ΔC_ηvol = 0)."""
    x_meas: dict[str, float]
    """Stationary measured values (channel units)."""
    A: list[list[float]]
    """Jacobian of the augmented model, 6 x 6."""
    Q: list[float]
    """State noise per state (SI units², per second): (x_meas - x_stat)² with floors."""
    R: dict[str, float]
    """Measurement noise per channel (SI units²): stationary variance with a floor."""
    K: dict[str, list[list[float]]] = field(default_factory=dict)
    """Gains of the default feedback set, ``"plain"`` (5 x m) and ``"augmented"`` (6 x m), at
    the table's ``dt``; ``"plain@0.02"`` etc. at other tick periods."""
    window: list[float] = field(default_factory=list)
    """Log times (s) of the stationary segment it was designed from."""

    @property
    def p_im(self) -> float:
        return self.x[1]


@dataclass
class GainTable:
    """The observer's gain table: operating points, their linear models, noises and gains."""

    dt: float
    points: list[TablePoint]
    feedback: tuple[str, ...] = DEFAULT_FEEDBACK
    source: str = ""
    notes: dict[str, Any] = field(default_factory=dict)

    # -- gains ---------------------------------------------------------------------------
    def gains(self, feedback: Sequence[str], augmented: bool, dt: float | None = None
              ) -> list[np.ndarray]:
        """The gain of every point for a feedback set, with or without ΔC_ηvol, at tick
        ``dt`` (default the table's): stored ones when they match, else solved now."""
        dt = self.dt if dt is None else dt
        key = "augmented" if augmented else "plain"
        if abs(dt - self.dt) >= 1e-9:
            key = f"{key}@{dt:g}"
        if tuple(feedback) == tuple(self.feedback) and all(key in pt.K for pt in self.points):
            return [np.array(pt.K[key]) for pt in self.points]
        return [self.solve(pt, feedback, augmented, dt)[0] for pt in self.points]

    def solve(self, pt: TablePoint, feedback: Sequence[str], augmented: bool, dt: float
              ) -> tuple[np.ndarray, np.ndarray]:
        n = 6 if augmented else 5
        A = np.array(pt.A)[:n, :n]
        Q = np.array(pt.Q[:n]) * dt  # continuous-time intensity -> per step
        missing = [m for m in feedback if m not in pt.R]
        if missing:
            raise ConfigError(f"the gain table has no measurement noise for {', '.join(missing)}")
        R = np.array([pt.R[m] for m in feedback])
        return discrete_gain(A, Q, R, [MEASUREMENTS[m][0] for m in feedback], dt)

    def fill_gains(self, also: Sequence[float] = (0.02,)) -> None:
        """Store the gains of the default feedback set at the table's ``dt`` (keys ``plain``,
        ``augmented``) and at the tick periods ``also`` (``plain@0.02``, ...: 0.02 s is the
        runtime's default FAS), so that the runtime solves nothing at start-up."""
        for pt in self.points:
            pt.K = {}
            for dt in (self.dt, *also):
                suffix = "" if abs(dt - self.dt) < 1e-9 else f"@{dt:g}"
                for key, aug in (("plain", False), ("augmented", True)):
                    pt.K[key + suffix] = self.solve(pt, self.feedback, aug, dt)[0].tolist()

    def nearest(self, speed: float, p_im: float) -> int:
        """Index of the point nearest to (engine speed rpm, p_im Pa) (seed 003, §3.4.2)."""
        s = self._sched
        d = ((s[:, 0] - speed) / SCHEDULE_SCALE[0]) ** 2 + ((s[:, 1] - p_im) / SCHEDULE_SCALE[1]) ** 2
        return int(np.argmin(d))

    def __post_init__(self) -> None:
        if not self.points:
            raise ConfigError("the gain table has no operating points")
        self._sched = np.array([[pt.speed, pt.p_im] for pt in self.points])

    # -- files ---------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        return {"format": FORMAT, "dt": self.dt, "feedback": list(self.feedback),
                "states": list(STATES), "schedule": ["ENGINE_SPEED rpm", "p_im Pa"],
                "source": self.source, "notes": self.notes,
                "points": [pt.__dict__ for pt in self.points]}

    def design(self, observer: str = "airpath") -> dict[str, Any]:
        """The table as the observer contract's design file (``observer``, ``table``)."""
        return {"format": DESIGN_FORMAT, "observer": observer, "table": self.to_json()}

    def save(self, path: str | Path) -> Path:
        """Write the table as a design file of the observer contract (JSON naming ``airpath``)."""
        path = Path(path)
        if path.suffix.lower() != ".json":
            raise ConfigError(f"--out {path}: the gain table is written as JSON (.json)")
        path.write_text(json.dumps(self.design(), indent=1))
        return path

    @classmethod
    def from_json(cls, data: Any, source: str = "gain table") -> GainTable:
        """A table from its JSON form: the table itself, or a design file holding it
        (``{"observer": "airpath", "table": {...}}``); refuses anything else, naming ``source``."""
        if isinstance(data, dict) and data.get("format") == DESIGN_FORMAT:
            if data.get("observer") != "airpath":
                raise DesignError(f"{source}: names observer {data.get('observer')!r}, not 'airpath'")
            data = data.get("table")
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise DesignError(f"{source}: not a gain table of format {FORMAT}")
        try:
            points = [TablePoint(**p) for p in data["points"]]
            return cls(float(data["dt"]), points, tuple(data["feedback"]), data.get("source", ""),
                       data.get("notes", {}))
        except (KeyError, TypeError, ValueError) as exc:
            raise DesignError(f"{source}: malformed gain table ({exc})") from None

    @classmethod
    def load(cls, path: str | Path = DEFAULT_TABLE) -> GainTable:
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise ConfigError(f"gain table not found: {path}") from None
        except json.JSONDecodeError as exc:
            raise ConfigError(f"{path}: not a JSON gain table ({exc})") from None
        return cls.from_json(data, str(path))


# -- the runtime block ---------------------------------------------------------------------------
@dataclass(frozen=True)
class NamesParam(Param):
    """A tunable list of names out of ``choices`` (non-empty, no repeats)."""

    choices: tuple[str, ...] = ()

    def check(self, value: Any) -> tuple[str, ...]:
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, (list, tuple)) or not value or not all(
                isinstance(v, str) for v in value):
            raise ParamError(self.name, f"must be a non-empty list of measurement names out of "
                                        f"{', '.join(self.choices)}, got {value!r}")
        bad = [v for v in value if v not in self.choices]
        if bad:
            raise ParamError(self.name, f"{', '.join(bad)} is not a measurement the observer can "
                                        f"feed back; choose from {', '.join(self.choices)}")
        if len(set(value)) != len(value):
            raise ParamError(self.name, f"names a measurement twice: {value!r}")
        return tuple(value)

    def dump(self, value: Any) -> Any:
        return list(value)


#: Output channels (``dbc/si_airpath.dbc``, frames AIRPATH_EST_1/2).
OUTPUTS = ("P_IC_EST", "P_IM_EST", "T_IM_EST", "P_EM_EST", "N_TC_EST", "CAC_EST",
           "DC_ETA_VOL_EST", "AIRPATH_POINT")
#: Plausible ranges of the inputs (the contract refuses a tick outside them): the actuators'
#: and sensors' DBC ranges, with absolute pressures below 5 kPa an unplugged sensor.
RANGES = {"THROTTLE": (-10.0, 100.0), "WASTEGATE": (-10.0, 110.0), "ENGINE_SPEED": (0.0, 8000.0),
          "P_IC": (5.0, 650.0), "P_IM": (5.0, 650.0), "T_IM": (-40.0, 300.0),
          "N_TC": (0.0, 260000.0)}
#: Bounds of the states (Pa, Pa, K, Pa, rad/s, -) beyond which the estimate has diverged.
STATE_BOUNDS = ((0.0, 1e6), (0.0, 1e6), (200.0, 600.0), (0.0, 2e6), (-1.0, 3e4), (-0.5, 0.5))


class AirPathObserver(ObserverContract):
    """Seed 003's constant-gain EKF of the SI air path, as a runtime block (family observer).

    Inputs: ``THROTTLE`` (deg), ``WASTEGATE`` (%), ``ENGINE_SPEED`` (rpm) and the measured
    ``P_IC``, ``P_IM``, ``T_IM``, ``N_TC``; λ is taken as 1 (the λ controller's set point;
    its ±2 % limit cycle is a model error like any other). Outputs :data:`OUTPUTS`:
    the estimates, the cylinder air charge (mg per cylinder and cycle), ΔC_ηvol and the
    index of the active table point.

    Tunable (``GET``/``PATCH /observers/airpath``): ``augmentation`` (0/1, ΔC_ηvol on or off;
    switching restarts the estimate at the next tick) and ``feedback`` (the measurements fed
    back, a list out of P_IC, P_IM, T_IM, N_TC; the gains of a new set are solved from the
    table's A_i, Q_i, R_i at once). ``T_IM`` is compared with the state directly: the
    thermocouple's lag is not modelled (seed 003 §3.2 suggests adding a sensor state), so it
    is left out of the default set, as in the paper.

    Parameters
    ----------
    table:
        The :class:`GainTable` (default: the shipped :data:`DEFAULT_TABLE`).
    params:
        The model's parameters (default :data:`~cell.plant.si_airpath.MODEL_PARAMS`).
    rate:
        Tick rate (FAS by default: the table is designed for 100 Hz; another tick period
        gets its gains solved for it).
    """

    kind = "observer"
    family = "observer"

    def __init__(self, name: str = "airpath", table: GainTable | None = None,
                 params: SIAirPathParams = MODEL_PARAMS, *, augmentation: bool = True,
                 feedback: Sequence[str] = DEFAULT_FEEDBACK, rate: str = "FAS") -> None:
        self.table = table if table is not None else GainTable.load()
        self.model = params
        ins = ["THROTTLE", "WASTEGATE", "ENGINE_SPEED", *MEASUREMENTS]
        super().__init__(name, ins, list(OUTPUTS), rate)
        self.state_names = STATES
        self.declare(ranges=RANGES, state_bounds=STATE_BOUNDS)
        self._y: np.ndarray | None = None
        self.PARAMS = {
            "augmentation": Param("augmentation", int, "1: estimate ΔC_ηvol (seed 003 §4.2); 0: off",
                                  ge=0, le=1),
            "feedback": NamesParam("feedback", str, "measurements fed back", shape="vector",
                                   choices=tuple(MEASUREMENTS)),
        }
        self._cache: dict[tuple, tuple[list[np.ndarray], list[np.ndarray]]] = {}
        self._J_at: tuple | None = None
        self._near: tuple[float, float, int] | None = None
        self._J_dt, self._J_n, self.refreshes = 0.0, 0, 0
        self._apply(self.validate({"augmentation": int(augmentation), "feedback": list(feedback)}))

    # -- parameters -----------------------------------------------------------------------------
    def _apply(self, checked: dict[str, Any]) -> None:
        old = (getattr(self, "augmentation", None), getattr(self, "feedback", None))
        new = (checked.get("augmentation", old[0]), checked.get("feedback", old[1]))
        self._matrices(self.table.dt, bool(new[0]), new[1])  # solve before anything changes
        super()._apply(checked)
        self._rows = [MEASUREMENTS[m] for m in self.feedback]
        if new[0] != old[0]:
            self.x: np.ndarray | None = None  # restart with the new state dimension
        self._t = None

    def _matrices(self, dt: float, augmented: bool, feedback: Sequence[str]
                  ) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Per point: the W-method step matrix :math:`(I - \\Delta t A_i)^{-1}\\Delta t` and the gain."""
        key = (round(dt, 9), augmented, tuple(feedback))
        hit = self._cache.get(key)
        if hit is None:
            n = 6 if augmented else 5
            try:
                K = self.table.gains(feedback, augmented, dt)
            except (np.linalg.LinAlgError, ValueError) as exc:
                raise ParamError("feedback", f"no stationary gain for {', '.join(feedback)}: {exc}"
                                 ) from None
            M = [np.linalg.solve(np.eye(n) - dt * np.array(pt.A)[:n, :n], dt * np.eye(n))
                 for pt in self.table.points]
            hit = self._cache[key] = (M, K)
        return hit

    def reset(self) -> None:
        self.x = None
        self._t = None

    def _restart(self, reason: str) -> None:
        self.reset()

    # -- designs: the gain table ---------------------------------------------------------------
    def _design_payload(self) -> dict[str, Any]:
        return {"table": self.table.to_json()}

    def _check_design(self, design: Any) -> Any:
        if "table" not in design:
            return None
        table = GainTable.from_json(design["table"], "table")
        feedback = design.get("params", {}).get("feedback", self.feedback)
        augmentation = design.get("params", {}).get("augmentation", self.augmentation)
        old, self.table, cache = self.table, table, self._cache
        self._cache = {}
        try:  # the new table must give gains for the feedback set in use
            self._matrices(table.dt, bool(augmentation), tuple(feedback))
        except (ParamError, ConfigError) as exc:
            raise DesignError(f"table: {exc}") from None
        finally:
            new_cache, self.table, self._cache = self._cache, old, cache
        return table, new_cache

    def _use_design(self, checked: Any) -> None:
        if checked is not None:
            self.table, self._cache = checked
            self._near = self._J_at = None

    def estimate(self) -> Estimate | None:
        if self.x is None:
            return None
        return Estimate(self.x, None, self._y, None, len(self.feedback))

    def _nearest(self, speed: float, p_im: float) -> int:
        """The table point nearest to (speed, p_im), looked up again only when either has moved
        by more than a twentieth of its scheduling scale since the last look-up."""
        last = self._near
        if (last is None or abs(speed - last[0]) > SCHEDULE_SCALE[0] / 20
                or abs(p_im - last[1]) > SCHEDULE_SCALE[1] / 20):
            last = self._near = (speed, p_im, self.table.nearest(speed, p_im))
        return last[2]

    def _w_step(self, t: float, dt: float) -> np.ndarray:
        r""":math:`(I - \Delta t J)^{-1}\Delta t`, with :math:`J` refreshed when the point moved."""
        x, u = self.x, self._u
        here = (u[0], u[1], u[2], x[0], x[1])
        ref = self._J_at
        if (ref is None or self._J_dt != dt or len(x) != self._J_n
                or any(abs(a - b) > tol for a, b, tol in zip(here, ref, REFRESH))):
            J = numerical_jacobian(lambda v: airpath_rhs(t, v, u, self.model), x)
            n = len(x)
            self._W = np.linalg.solve(np.eye(n) - dt * J, dt * np.eye(n))
            self._J_at, self._J_dt, self._J_n = here, dt, n
            self.refreshes += 1
        return self._W

    # -- stepping -------------------------------------------------------------------------------
    def _start(self, u: list[float], z: dict[str, float]) -> np.ndarray:
        """The nearest table point's stationary state, with the measured states put in."""
        i = self.table.nearest(u[2], z["P_IM"] * 1000.0)
        x = np.array(self.table.points[i].x[:5] + ([0.0] if self.augmentation else []))
        for name, (row, scale, offset) in MEASUREMENTS.items():
            if name != "T_IM":  # the thermocouple lags: keep the model's temperature
                x[row] = z[name] * scale + offset
        return x

    def _observe(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        u = [inputs["THROTTLE"], inputs["WASTEGATE"] / 100.0, inputs["ENGINE_SPEED"], 1.0]
        p = self.model
        if self.x is None or self._t is None or not t > self._t:
            if self.x is None:
                self.x = self._start(u, inputs)
            dt = None
        else:
            dt = round(t - self._t, 9)  # tick periods from bus times differ in the last bits
        i = self._nearest(u[2], float(self.x[1]))
        if dt is not None:  # predict over the tick with the previous input held
            self.x = self.x + self._w_step(t, dt) @ np.array(airpath_rhs(t, self.x, self._u, p))
        _, K = self._matrices(self.table.dt if dt is None else dt, bool(self.augmentation),
                              self.feedback)
        y = np.array([inputs[m] * scale + offset - self.x[row]
                      for m, (row, scale, offset) in zip(self.feedback, self._rows)])
        self._y = y
        x = self.x + K[i] @ y
        x[0] = max(x[0], 20_000.0)
        x[1] = max(x[1], 5_000.0)
        x[2] = min(max(x[2], 230.0), 500.0)
        x[3] = max(x[3], 50_000.0)
        x[4] = max(x[4], 0.0)
        if self.augmentation:
            x[5] = min(max(x[5], -0.3), 0.3)
        if not np.isfinite(x).all():
            self.x = None
            raise ArithmeticError("the air-path observer's state became non-finite; restarting")
        self.x, self._t, self._u, self.point = x, t, u, i
        dc = float(x[5]) if self.augmentation else 0.0
        eta = ap.volumetric_efficiency(p.c_eta_vol + dc, x[1], x[3], p.r_c, p.gamma_e,
                                       u[2] / 60.0, p.eta_vol_speed_ref, p.eta_vol_speed_shape)
        cac = ap.cylinder_air_charge(eta, x[1], x[2], p.v_cyl, 1.0, p.afr_s, p.c1)
        return {"P_IC_EST": x[0] / 1000.0, "P_IM_EST": x[1] / 1000.0, "T_IM_EST": x[2] - 273.15,
                "P_EM_EST": x[3] / 1000.0, "N_TC_EST": x[4] * RPM_PER_RAD_S, "CAC_EST": cac * 1e6,
                "DC_ETA_VOL_EST": dc, "AIRPATH_POINT": float(i)}

    def _state(self) -> dict[str, Any]:
        pt = getattr(self, "point", None)
        return {"t": self._t, "states": list(STATES[: 6 if self.augmentation else 5]),
                "x": None if self.x is None else self.x.tolist(), "point": pt,
                "point_at": None if pt is None else {"speed": self.table.points[pt].speed,
                                                     "p_im_kPa": self.table.points[pt].p_im / 1000.0},
                "table_points": len(self.table.points), "table_dt": self.table.dt,
                "jacobian_refreshes": self.refreshes}


__all__ = ["DEFAULT_FEEDBACK", "DEFAULT_TABLE", "MEASUREMENTS", "OUTPUTS", "AirPathObserver",
           "GainTable", "TablePoint", "discrete_gain"]
