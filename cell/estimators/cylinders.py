r"""Seed 001's two observers as runtime blocks: UEGO inversion and transmission-rod inversion.

Both consume a crank-angle sample stream (:mod:`cell.runtime.samples`) sample by sample, run a
:class:`~cell.estimators.periodic.PeriodicObserver` in the angle domain (6 deg per step),
and publish at the runtime's MED ticks. Both are blocks of family ``observer`` (tunable at
``/observers/{name}``, persisted in the tuning file).

**AFR (UEGO) inversion** (:class:`UegoInversion`, seed 001 "Air fuel ratio sensor
inversion"). The UEGO is two first-order lags in series (:math:`\tau_1`, :math:`\tau_2`).
In the angle domain a lag of time constant :math:`\tau` at engine speed :math:`\omega_e`
(rad/s) is :math:`A = -1/(\tau\omega_e)`, :math:`A_0 = 1/(\tau\omega_e)`, :math:`C = 1`. Two
full-measurement observers (eqs. 6-8, :math:`h` = 3, :math:`\tilde L = -4/\tau`,
:math:`\alpha_k^2 = 4/(k^2+1)`) in cascade (Figure 2): the first reconstructs the
intermediate variable from the sensor, the second the manifold AFR :math:`w` from it. The
gains are those of the 1 % speed band the engine runs in, held with hysteresis and designed
ahead by a background thread (:mod:`cell.estimators.speed_grid`). Outputs:

- ``AFR_MANIFOLD_EST``: :math:`\hat w` at the last sample;
- ``AFR_HARM_1..3``: :math:`E(k) = \sqrt{|c_k|^2 + |c_{-k}|^2} = \sqrt 2 |c_k|` (Figures 6, 8);
- ``AFR_CYL_1..4_EST``: the mean of :math:`\hat w` over each cylinder's exhaust phase
  (Figures 5, 7): 180 deg from the cylinder's exhaust-valve opening (``evo_deg`` after its
  firing TDC) plus the gas's delay to the sensor (``delay`` s, i.e. ``6 rpm delay`` deg),
  as the observer's model believes them;
- ``IMBALANCE_CYL``: a cylinder named only once a sequential test has confirmed it (0:
  none). At every closed exhaust phase, with :math:`d_i` the departure of cylinder
  :math:`i`'s AFR from the mean of the four, its evidence is
  :math:`g_i = |d_i| - \max_{j \ne i}|d_j|`: large only for a cylinder that departs by
  itself (one cylinder off by :math:`3x` leaves the other three at :math:`x`, so :math:`g`
  is :math:`2x` for it and negative for them; two cylinders about level give neither any). A one-sided CUSUM
  per cylinder, in units of the departures' own uncertainty: their standard deviation
  :math:`\sigma` (tracked from the phase-to-phase changes of :math:`d`, winsorised at
  :math:`3\sigma`, floored at ``sigma_floor``) combined with how far :math:`d` moved over the
  last engine cycle or :data:`MOVING_S`, whichever is longer, :math:`\Delta` (a departure
  still settling is not yet evidence),
  :math:`S_i \leftarrow \min(S_{max}, \max(0, S_i + \min((g_i - \delta)/\sqrt{\sigma^2 +
  \Delta^2} - k,\ \text{confirm}/\text{persist})))` with :math:`\delta` = ``threshold``
  (0.5 AFR, about 3.4 %) and :math:`k` = 0.5, names cylinder :math:`i` when :math:`S_i`
  reaches ``confirm`` (so after ``persist`` phases of evidence at least) and it has led
  for ``persist`` successive phases. A named cylinder stays named until its :math:`S_i`
  returns to 0, or another cylinder is confirmed. A pattern where no cylinder stands out
  alone (two opposite cylinders equally off: all four depart equally) is *suspect*, never
  a name. It is not yet known (the channel has no value, or is invalid after a reset)
  until ``settle_cycles`` engine cycles after a start or a reset, and after lost frames
  until every cylinder's exhaust phase has been seen whole again; the CUSUMs restart then.
- ``IMBALANCE_STATE`` (runtime channel, not on the bus): 0 none, 1 settling (not yet
  known), 2 suspect (evidence accumulating, or an imbalance with no single cylinder), 3
  confirmed (``IMBALANCE_CYL`` names the cylinder);
- ``IMBALANCE_CONF`` (runtime channel): the leading cylinder's evidence as a fraction of
  the confirmation threshold, :math:`\min(1, S_{max}/\text{confirm})`; 0 while settling.

The exhaust-phase windows start at ``evo_deg + 6 rpm delay`` deg after each firing TDC, or,
with a design (``testcell design imbalance``, :meth:`UegoInversion.load_design`), at the
design's identified phase at the present speed (interpolated between its speeds, held at
the ends), with the design's UEGO lags as ``tau1``/``tau2``.

**Transmission-rod inversion** (:class:`RodInversion`, seed 001 "Transmission rod dynamics
inversion"). :math:`A = [[0, 1], [-\bar\omega^2, -2\bar\xi\bar\omega]]`, :math:`A_0 = [0,
1]^T`, :math:`C = [1, 0]`, :math:`L = [2\bar\xi\bar\omega, 2\bar\omega^2]^T`, partial
measurement gains (eq. 9) with :math:`\epsilon` = 0.1, :math:`\beta^2` = 1, :math:`h` = 2
harmonics of the firing period (180 deg), one coefficient bank per cylinder (the
:math:`c_{k,i}` of the paper). The speed next to the cylinders is rebuilt from the
coefficients of :math:`w_0 = 2\bar\xi\bar\omega x_2' + \bar\omega^2 x_2`:
:math:`X_{2,k} = c_k / (\bar\omega^2 + i\,2\bar\xi\bar\omega k\omega_0)`. Outputs:

- ``N_CYL_EST``: :math:`\hat x_2` at the last sample (Figure 11);
- ``TORQUE_BALANCE_1..4``: :math:`V_i - \overline V`, :math:`V_i = \sum_{k\neq 0}
  |X_{2,k,i}|^2` (Figure 12), rpm².

**Lost frames.** The runtime reports a gap (:meth:`Block.gap`). Up to ``gap_skip`` lost
samples the observer *skips ahead*: its Fourier coefficients are referenced to the crank
angle and stay valid, so it continues at the new angle and only discards the exhaust phase
the gap fell in. A longer gap *resets* it (and the diagnosis waits ``settle_cycles``
again). Either is counted and the last few are listed in :meth:`state` (``events``).
"""

from __future__ import annotations

import collections
import functools
import logging
import math
from typing import Any

import numpy as np

from cell.runtime.blocks import Block, Param
from cell.plant.cylinders import N_CYL, STOICH_AFR
from cell.estimators.contract import DesignError, Estimate, ObserverContract
from cell.estimators.periodic import (
    LinearPeriodic,
    PeriodicObserver,
    cascade,
    design_full,
    design_partial,
)
from cell.estimators.speed_grid import SpeedGrid, shared_grid

log = logging.getLogger(__name__)

#: crank angle per sample, deg, and samples per engine cycle
SAMPLE_DEG = 6.0
CYCLE = int(720 / SAMPLE_DEG)
STEP = math.radians(SAMPLE_DEG)
FIRING_ORDER = (1, 3, 4, 2)

#: the diagnosis channels beside IMBALANCE_CYL (runtime channels, not on the bus)
DIAGNOSIS_CHANNELS = ("IMBALANCE_STATE", "IMBALANCE_CONF")
#: IMBALANCE_STATE values
NONE, SETTLING, SUSPECT, CONFIRMED = 0, 1, 2, 3
#: CUSUM allowance (standard deviations) and cap (times ``confirm``: a cylinder whose
#: evidence is gone is un-named within a bounded time)
CUSUM_K = 0.5
CUSUM_CAP = 2.0
#: weight of one exhaust phase in the departures' variance
VAR_WEIGHT = 0.1
#: how long the departures must have held still (and at least an engine cycle) before
#: they count fully as evidence, s: the estimate settles in time (the sensor, the λ
#: control), not in engine cycles
MOVING_S = 0.1


def check_design(design: Any, name: str = "afr_inversion"
                 ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[float, float]]:
    """The phase table (speeds, deg) and UEGO lags (s) of an imbalance design; ValueError
    naming what is wrong."""
    if not isinstance(design, dict):
        raise ValueError("an imbalance design is a JSON object")
    if design.get("observer") != name:
        raise ValueError(f"the design is for observer {design.get('observer')!r}, not {name!r}")
    ident = design.get("identified")
    points = ident.get("points") if isinstance(ident, dict) else None
    if not isinstance(points, list) or not points:
        raise ValueError("the design has no identified.points (speed, phase_deg per speed)")
    try:
        rows = sorted((float(p["rpm"]), float(p["phase_deg"])) for p in points)
        lags = (float(ident["tau1"]), float(ident["tau2"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"the design's identified part is incomplete or not numbers: {exc}") from None
    vals = [v for r in rows for v in r] + list(lags)
    if not all(math.isfinite(v) for v in vals):
        raise ValueError("the design's identified values must be finite")
    if not all(0.0 < t <= 1.0 for t in lags):
        raise ValueError(f"the design's UEGO lags must be in (0, 1] s, got {lags}")
    if any(r <= 0.0 for r, _ in rows):
        raise ValueError("the design's speeds must be positive rpm")
    speeds = np.array([r for r, _ in rows])
    if len(np.unique(speeds)) != len(speeds):
        raise ValueError("the design names a speed twice")
    return (speeds, np.array([p for _, p in rows])), lags


#: Plausible UEGO samples (the frame's range, AFR) and engine speeds (rpm) of afr_inversion
AFR_SAMPLE_RANGE = (5.0, 40.0)
SPEED_RANGE = (0.0, 12000.0)
#: Plausible crank speeds of the rod observer's samples, rpm
ROD_SAMPLE_RANGE = (0.0, 12000.0)


def _firing_deg(order: tuple[int, ...] = FIRING_ORDER) -> np.ndarray:
    deg = np.zeros(N_CYL)
    for pos, cyl in enumerate(order):
        deg[cyl - 1] = pos * 720.0 / N_CYL
    return deg


def uego_design(tau1: float, tau2: float, h: int, ltilde: float, alpha: float, rpm: float
                ) -> tuple[LinearPeriodic, tuple[PeriodicObserver, PeriodicObserver]]:
    """The UEGO cascade's gains at ``rpm`` (a band of the speed grid): the lags in radians
    of crank angle; the cascade and its two stages (sensor side first, Figure 2)."""
    omega_e = rpm * math.pi / 30.0
    stages = []
    for tau in (tau2, tau1):
        ta = tau * omega_e
        A, A0, C = [[-1.0 / ta]], [[1.0 / ta]], [[1.0]]
        g = design_full(A, A0, C, [[-ltilde / ta]], [alpha / (k * k + 1) for k in range(h + 1)])
        stages.append(PeriodicObserver(A, A0, C, h, 0.5, g, STEP))
    return cascade(stages[0], stages[1]), (stages[0], stages[1])


class _StreamObserver(Block):
    """What both observers share: gap handling, events, the settle count and a trace."""

    kind = "observer"
    family = "observer"

    def __init__(self, name: str, stream: str, inputs: list[str], outputs: list[str],
                 units: dict[str, str], record: bool) -> None:
        super().__init__(name, inputs, outputs, "MED", units=units)
        self.streams = (stream,)
        self.z: np.ndarray | None = None
        self.samples_seen = 0
        self.cycles_since_reset = 0
        self.skips = 0
        self.resets = 0
        self.events: collections.deque[dict[str, Any]] = collections.deque(maxlen=20)
        #: per-sample record (t, angle index, measured, estimate...), when ``record``
        self.trace: list[np.ndarray] | None = [] if record else None

    def gap(self, stream: str, lost: int, index: int, t: float) -> None:
        if lost <= self.gap_skip:
            self.skips += 1
            what = "skip"
            self._skip()
        else:
            self.resets += 1
            what = "reset"
            self._reset()
        event = {"t": t, "what": what, "lost_samples": lost, "at_index": index}
        self.events.append(event)
        log.info("%s %s: %d samples of %s lost before angle %g deg, %s", self.kind, self.name,
                 lost, stream, index * SAMPLE_DEG, "skipping ahead" if what == "skip" else "reset")

    def _skip(self) -> None:
        pass

    def _reset(self) -> None:
        self.z = None
        self.cycles_since_reset = 0

    def _apply(self, checked: dict[str, Any]) -> None:
        super()._apply(checked)
        self._redesign()

    def _redesign(self) -> None:
        raise NotImplementedError

    def _common_state(self) -> dict[str, Any]:
        return {"samples": self.samples_seen, "cycles_since_reset": self.cycles_since_reset,
                "skips": self.skips, "resets": self.resets, "events": list(self.events)}


class UegoInversion(ObserverContract, _StreamObserver):
    """AFR inversion of the UEGO sensor (module docstring). Stream ``AFR_UEGO``, on the
    observer contract (:mod:`cell.estimators.contract`): UEGO samples outside
    :data:`AFR_SAMPLE_RANGE` and engine speeds outside :data:`SPEED_RANGE` are refused,
    ticks without samples turn the outputs stale; a design (``testcell design imbalance``)
    is loaded with :meth:`load_design`."""

    def __init__(self, name: str = "afr_inversion", *, tau1: float = 0.025, tau2: float = 0.020,
                 h: int = 3, ltilde: float = 4.0, alpha: float = 4.0, threshold: float = 0.5,
                 persist: int = 4, settle_cycles: int = 10, evo_deg: float = 140.0,
                 delay: float = 0.007, confirm: float = 20.0, sigma_floor: float = 0.05,
                 gap_skip: int = 24, record: bool = False,
                 design: dict[str, Any] | None = None) -> None:
        outs = (["AFR_MANIFOLD_EST"] + [f"AFR_HARM_{k}" for k in (1, 2, 3)]
                + [f"AFR_CYL_{i}_EST" for i in range(1, N_CYL + 1)] + ["IMBALANCE_CYL",
                                                                        *DIAGNOSIS_CHANNELS])
        super().__init__(name, "AFR_UEGO", ["ENGINE_SPEED"], outs,
                         {o: "AFR" for o in outs if o.startswith("AFR")}, record)
        self.PARAMS = {
            "tau1": Param("tau1", float, "UEGO first time constant of the model, s", gt=0.0, le=1.0),
            "tau2": Param("tau2", float, "UEGO second time constant of the model, s", gt=0.0, le=1.0),
            "h": Param("h", int, "harmonics of the engine cycle estimated (3 publishes AFR_HARM_1..3)",
                       ge=1, le=12),
            "ltilde": Param("ltilde", float, "error dynamics Ltilde = -ltilde / tau (eq. 6)",
                            gt=1.0, le=100.0),
            "alpha": Param("alpha", float, "alpha_k^2 = alpha / (k^2 + 1) (eq. 7)", gt=0.0, le=100.0),
            "threshold": Param("threshold", float,
                               "AFR departure of one cylinder's exhaust phase from the mean that "
                               "names it in IMBALANCE_CYL", gt=0.0, le=10.0),
            "persist": Param("persist", int, "successive exhaust phases a cylinder must lead "
                             "before it is confirmed", ge=1, le=100),
            "confirm": Param("confirm", float, "CUSUM level (in standard deviations of the "
                             "departures) that confirms a cylinder", gt=0.0, le=1000.0),
            "sigma_floor": Param("sigma_floor", float, "floor of the departures' standard "
                                 "deviation, AFR", gt=0.0, le=5.0),
            "settle_cycles": Param("settle_cycles", int, "engine cycles before the first diagnosis "
                                   "after a start or reset", ge=1, le=1000),
            "evo_deg": Param("evo_deg", float, "exhaust-valve opening after firing TDC, deg",
                             ge=0.0, le=720.0),
            "delay": Param("delay", float, "delay of the exhaust gas from the valve to the "
                           "sensor, s", ge=0.0, le=0.2),
            "gap_skip": Param("gap_skip", int, "lost samples skipped over; more reset the observer",
                              ge=0, le=10_000),
        }
        checked = self.validate({"tau1": tau1, "tau2": tau2, "h": h, "ltilde": ltilde, "alpha": alpha,
                                 "threshold": threshold, "persist": persist,
                                 "settle_cycles": settle_cycles, "evo_deg": evo_deg,
                                 "delay": delay, "confirm": confirm, "sigma_floor": sigma_floor,
                                 "gap_skip": gap_skip})
        for key, value in checked.items():
            setattr(self, key, value)
        self.rpm: float | None = None
        self._grid: SpeedGrid | None = None
        self._lp = None
        self._obs: PeriodicObserver | None = None
        self._first: PeriodicObserver | None = None
        self._bucket: int | None = None
        self._w_last = math.nan
        self._t_samples = 0.0
        #: the loaded design's phase per speed (rpm, deg), or None: the model's evo + delay
        self._phase_table: tuple[np.ndarray, np.ndarray] | None = None
        self.loaded_design: dict[str, Any] | None = None
        self._reset_windows()
        self._announce_reset = False
        self._reset_reason = "observer reset after lost frames"
        self.declare(ranges={"ENGINE_SPEED": SPEED_RANGE}, sample_ranges={"AFR_UEGO": AFR_SAMPLE_RANGE})
        self._redesign()
        if design is not None:
            self.load_design(design)

    # -- design -------------------------------------------------------------------------
    def _redesign(self) -> None:
        self._bucket = None
        key = (self.tau1, self.tau2, self.h, self.ltilde, self.alpha)
        self._grid = shared_grid(key, functools.partial(uego_design, *key))
        if self.z is not None and self._first is not None and self._first.h != self.h:
            self._reset()  # a new number of harmonics: a new state
        if self.rpm is not None:
            self._design_for(self.rpm)

    def _design_for(self, rpm: float) -> None:
        """Gains of the 1 % speed band at ``rpm`` (the lags in radians of crank angle), held
        with hysteresis and designed off the hot path (:mod:`cell.estimators.speed_grid`)."""
        bucket = self._grid.select(rpm, self._bucket)
        if bucket == self._bucket:
            return
        self._lp, (self._first, self._obs) = self._grid.design(bucket)
        self._bucket = bucket
        self._owner_of = self._owners()

    # -- windows and diagnosis ----------------------------------------------------------
    def _reset_windows(self) -> None:
        self._win_sum = [0.0, 0.0]  # estimate, measured
        self._win_n = 0
        self._win_cyl: int | None = None
        self._win_clean = False
        self.cyl_est = np.full(N_CYL, math.nan)
        self.cyl_meas = np.full(N_CYL, math.nan)
        self._fresh: set[int] = set()
        self._candidate = (0, 0)
        self.diagnosis = math.nan
        self._cusum = np.zeros(N_CYL)
        self._cusum_any = 0.0
        self._d_prev: np.ndarray | None = None
        self._d_hist: collections.deque[tuple[float, np.ndarray]] = collections.deque()
        self._var: float | None = None
        self.diag_state = SETTLING
        self.confidence = 0.0

    def _reset(self) -> None:
        super()._reset()
        self._reset_windows()
        self._announce_reset = True

    def _skip(self) -> None:
        self._win_clean = False  # the exhaust phase the gap fell in is not used...
        self._fresh.clear()  # ...and no diagnosis until every cylinder's phase is new again

    def _owners(self) -> list[int]:
        """The cylinder (1..4) whose exhaust phase each angle index of the cycle belongs to,
        at the present speed band."""
        start = self.window_start(1.01**self._bucket)
        pos = (((np.arange(2 * CYCLE) * SAMPLE_DEG - start) % 720.0) // (720.0 / N_CYL)).astype(int)
        return np.asarray(FIRING_ORDER)[pos].tolist()  # two cycles: a frame may wrap

    def _close_window(self) -> None:
        cyl = self._win_cyl
        if cyl is not None and self._win_clean and self._win_n >= 0.8 * CYCLE / N_CYL:
            self.cyl_est[cyl - 1] = self._win_sum[0] / self._win_n
            self.cyl_meas[cyl - 1] = self._win_sum[1] / self._win_n
            self._fresh.add(cyl)
            if cyl == FIRING_ORDER[-1]:
                self.cycles_since_reset += 1
            self._diagnose()
        self._win_sum = [0.0, 0.0]
        self._win_n = 0
        self._win_clean = True

    def _diagnose(self) -> None:
        if (self.cycles_since_reset < self.settle_cycles or not np.isfinite(self.cyl_est).all()
                or len(self._fresh) < N_CYL):
            if np.isfinite(self.cyl_est).all():
                self._track_variance(self.cyl_est - self.cyl_est.mean(), robust=False)
            return
        d = self.cyl_est - self.cyl_est.mean()
        sigma = self._track_variance(d, robust=True)
        # a departure still moving is not yet evidence: its change over the last engine cycle
        # (every window measured once since) widens the uncertainty it is judged against
        t = self._t_samples
        self._d_hist.append((t, d.copy()))
        while len(self._d_hist) > N_CYL + 1 and self._d_hist[0][0] < t - MOVING_S:
            self._d_hist.popleft()
        moving = float(max(np.max(np.abs(d - old)) for _, old in self._d_hist))
        a = np.abs(d)
        top = int(np.argmax(a))
        others = np.full(N_CYL, a[top])
        others[top] = np.max(np.delete(a, top))  # the largest of the others
        g = np.minimum(a, a - others)
        step = np.minimum((g - self.threshold) / math.hypot(sigma, moving) - CUSUM_K,
                          self.confirm / self.persist)
        self._cusum = np.clip(self._cusum + step, 0.0, CUSUM_CAP * self.confirm)
        self._cusum_any = min(max(0.0, self._cusum_any + (a.max() - self.threshold) / sigma
                                  - CUSUM_K), CUSUM_CAP * self.confirm)
        lead = int(np.argmax(self._cusum))
        lead_cyl = lead + 1 if self._cusum[lead] > 0.0 else 0
        prev, count = self._candidate
        count = count + 1 if lead_cyl == prev else 1
        self._candidate = (lead_cyl, count)
        named = int(self.diagnosis) if np.isfinite(self.diagnosis) else 0
        if lead_cyl and self._cusum[lead] >= self.confirm and count >= self.persist:
            named = lead_cyl  # confirmed (or another cylinder confirmed over the one named)
        elif named and self._cusum[named - 1] <= 0.0:
            named = 0  # the named cylinder's evidence is gone
        self.diagnosis = float(named)
        self.confidence = float(min(1.0, self._cusum.max() / self.confirm))
        if named:
            self.diag_state = CONFIRMED
        elif self._cusum.max() > 0.0 or self._cusum_any > 0.0:
            self.diag_state = SUSPECT
        else:
            self.diag_state = NONE

    def _track_variance(self, d: np.ndarray, robust: bool) -> float:
        """The departures' standard deviation from their phase-to-phase changes (half the mean
        square change per cylinder, exponentially weighted; winsorised at 3 sigma once settled)."""
        if self._d_prev is not None:
            sq = float(np.mean((d - self._d_prev) ** 2)) / 2.0
            if self._var is None:
                self._var = sq
            else:
                if robust:
                    sq = min(sq, 9.0 * self._var)
                self._var += VAR_WEIGHT * (sq - self._var)
        self._d_prev = d.copy()
        return max(math.sqrt(self._var) if self._var is not None else math.inf, self.sigma_floor)

    # -- phase and design ---------------------------------------------------------------
    def window_start(self, rpm: float) -> float:
        """Crank angle after each cylinder's firing TDC where its gas begins at the sensor,
        deg: the design's phase at ``rpm`` when one is loaded, else ``evo_deg + 6 rpm delay``."""
        if self._phase_table is not None:
            speeds, phases = self._phase_table
            return float(np.interp(rpm, speeds, phases))
        return self.evo_deg + 6.0 * rpm * self.delay

    def _check_design(self, design: Any) -> Any:
        """The phase table and lags of an imbalance design (``identified``), or ``None`` for
        a design of the parameters alone (the windows then follow ``evo_deg`` and ``delay``)."""
        if "identified" not in design:
            return None
        try:
            return check_design(design, self.name), design["identified"]
        except ValueError as exc:
            raise DesignError(str(exc)) from None

    def _use_design(self, checked: Any) -> None:
        if checked is None:
            self._phase_table, self.loaded_design = None, None
        else:
            (phases, lags), ident = checked
            self._phase_table = phases
            self.tau1, self.tau2 = lags
            self.loaded_design = {"identified": ident}
        self._redesign()

    def _design_payload(self) -> dict[str, Any]:
        return {} if self.loaded_design is None else {"identified": self.loaded_design["identified"]}

    def _restart(self, reason: str) -> None:
        self._reset_reason = reason
        self._reset()
        self._w_last = math.nan

    def estimate(self) -> Estimate | None:
        return None if self.z is None else Estimate(self.z)

    # -- samples and ticks --------------------------------------------------------------
    def _samples(self, stream: str, index: int, values: np.ndarray, t: float) -> None:
        if self.rpm is None:
            return  # no engine speed yet: the angle-domain model is unknown
        self._design_for(self.rpm)
        if self.z is None:
            self.z = np.concatenate([self._first.initial(values[0]), self._obs.initial(values[0])])
            self._reset_windows()
        self.z, out = self._lp.run(self.z, index, values)
        w = out[:, 0].tolist()
        last = w[-1]
        if not math.isfinite(last):  # a non-finite state reaches the output within a frame
            self._reset()
            raise ArithmeticError("the AFR observer diverged; reset")
        vals = values.tolist()
        n = len(vals)
        self._t_samples = t
        self.samples_seen += n
        self._w_last = last
        owners = self._owner_of[index:index + n]
        if owners[0] == owners[-1] == self._win_cyl:  # the frame lies in one exhaust phase
            self._win_sum[0] += sum(w)
            self._win_sum[1] += sum(vals)
            self._win_n += n
        else:
            for k in range(n):
                if owners[k] != self._win_cyl:
                    self._close_window()
                    self._win_cyl = owners[k]
                self._win_sum[0] += w[k]
                self._win_sum[1] += vals[k]
                self._win_n += 1
        if self.trace is not None:
            idx = (index + np.arange(n)) % CYCLE
            self.trace.append(np.column_stack([np.full(n, t), idx, values, out[:, 0]]))

    def harmonics(self) -> np.ndarray:
        """:math:`E(k)` for k = 1..h of the reconstructed manifold AFR (nan before any sample)."""
        if self.z is None or self._obs is None:
            return np.full(self.h, math.nan)
        c = self._obs.coefficients(self.z[-self._obs.d:])[:, 0]
        return math.sqrt(2.0) * np.abs(c[1:])

    def _observe(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        rpm = inputs["ENGINE_SPEED"]
        self.rpm = rpm if math.isfinite(rpm) and rpm > 100.0 else None
        e = self.harmonics()
        out = {"AFR_MANIFOLD_EST": self._w_last}
        for k in (1, 2, 3):
            out[f"AFR_HARM_{k}"] = float(e[k - 1]) if k <= len(e) else 0.0
        for i in range(N_CYL):
            out[f"AFR_CYL_{i + 1}_EST"] = float(self.cyl_est[i])
        out["IMBALANCE_CYL"] = self.diagnosis
        # what is not known yet keeps its channel's state (no value yet, or the reset's mark)
        out = {o: v for o, v in out.items() if math.isfinite(v)}
        known = math.isfinite(self.diagnosis)
        out["IMBALANCE_STATE"] = float(self.diag_state if known else SETTLING)
        out["IMBALANCE_CONF"] = self.confidence if known else 0.0
        self.errors = {}
        if self._announce_reset:
            self._announce_reset = False
            out["IMBALANCE_CYL"] = math.nan
            self.errors["IMBALANCE_CYL"] = (f"{self._reset_reason}: settling for "
                                            f"{self.settle_cycles} engine cycles")
            self._reset_reason = "observer reset after lost frames"
        return out

    def _state(self) -> dict[str, Any]:
        return _json_safe(self._own_state())

    def _own_state(self) -> dict[str, Any]:
        return {**self._common_state(), "rpm": self.rpm,
                "afr_cyl_est": self.cyl_est.tolist(), "afr_cyl_measured": self.cyl_meas.tolist(),
                "harmonics": self.harmonics().tolist(), "diagnosis": self.diagnosis,
                "candidate": list(self._candidate), "diagnosis_state": self.diag_state,
                "confidence": self.confidence, "cusum": self._cusum.tolist(),
                "sigma": (math.sqrt(self._var) if self._var is not None else None),
                "window_start_deg": (self.window_start(self.rpm) if self.rpm else None),
                "design": self.loaded_design}


def _json_safe(v: Any) -> Any:
    """``v`` with every non-finite number as ``None`` (a state is JSON)."""
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


class RodInversion(ObserverContract, _StreamObserver):
    """Transmission-rod inversion (module docstring). Stream ``N_CRANK``, on the observer
    contract (:mod:`cell.estimators.contract`): crank-speed samples outside
    :data:`ROD_SAMPLE_RANGE` are refused, ticks without samples turn the outputs stale."""

    def __init__(self, name: str = "rod_inversion", *, omega_bar: float = 3.1, xi: float = 0.15,
                 h: int = 2, eps: float = 0.1, beta2: float = 1.0, gap_skip: int = 24,
                 record: bool = False) -> None:
        outs = ["N_CYL_EST"] + [f"TORQUE_BALANCE_{i}" for i in range(1, N_CYL + 1)]
        units = {"N_CYL_EST": "rpm", **{o: "rpm^2" for o in outs[1:]}}
        super().__init__(name, "N_CRANK", [], outs, units, record)
        self.PARAMS = {
            "omega_bar": Param("omega_bar", float, "natural frequency of the rod, per radian of "
                               "crank angle", gt=0.1, le=100.0),
            "xi": Param("xi", float, "damping of the rod", gt=0.0, le=2.0),
            "h": Param("h", int, "harmonics of the firing period estimated", ge=1, le=8),
            "eps": Param("eps", float, "adaptation gain epsilon (eq. 9)", gt=0.0, le=1.0),
            "beta2": Param("beta2", float, "beta^2 (eq. 9)", gt=0.0, le=100.0),
            "gap_skip": Param("gap_skip", int, "lost samples skipped over; more reset the observer",
                              ge=0, le=10_000),
        }
        checked = self.validate({"omega_bar": omega_bar, "xi": xi, "h": h, "eps": eps,
                                 "beta2": beta2, "gap_skip": gap_skip})
        for key, value in checked.items():
            setattr(self, key, value)
        self._n_last = math.nan
        self.declare(sample_ranges={"N_CRANK": ROD_SAMPLE_RANGE})
        self._redesign()

    def _restart(self, reason: str) -> None:
        self._reset()
        self._n_last = math.nan

    def estimate(self) -> Estimate | None:
        return None if self.z is None else Estimate(self.z)

    def _redesign(self) -> None:
        wb, xi = self.omega_bar, self.xi
        A = [[0.0, 1.0], [-wb**2, -2.0 * xi * wb]]
        A0, C = [[0.0], [1.0]], [[1.0, 0.0]]
        L = [[2.0 * xi * wb], [2.0 * wb**2]]
        omega0 = 2.0 * math.pi / math.pi  # the firing period, 180 deg
        g = design_partial(A, A0, C, L, omega0, self.h, self.eps, self.beta2)
        per = CYCLE // N_CYL
        order = FIRING_ORDER
        self._obs = obs = PeriodicObserver(A, A0, C, self.h, omega0, g, STEP, banks=N_CYL,
                                           bank=lambda j: order[j // per] - 1, cycle=CYCLE)
        self._D = np.array([wb**2 + 2j * xi * wb * k * omega0 for k in range(self.h + 1)])
        O = np.zeros((CYCLE, 2, obs.d))  # noqa: E741  rows: x2 estimate, C x
        for j in range(CYCLE):
            off = obs.n + obs.bank_of(j) * obs.nc_bank
            a = obs.angle(j)
            O[j, 0, off] = 1.0 / wb**2
            for k in range(1, self.h + 1):
                gk = 1.0 / self._D[k]
                c, s = math.cos(k * omega0 * a), math.sin(k * omega0 * a)
                base = off + 2 * k - 1
                O[j, 0, base] = 2.0 * (gk.real * c - gk.imag * s)
                O[j, 0, base + 1] = -2.0 * (gk.imag * c + gk.real * s)
            O[j, 1, :obs.n] = obs.C[0]
        self._lp = LinearPeriodic(obs._M, obs._N, O, np.zeros((CYCLE, 2, 1)))
        if self.z is not None and len(self.z) != obs.d:
            self._reset()  # a new number of harmonics: a new state

    def _samples(self, stream: str, index: int, values: np.ndarray, t: float) -> None:
        if self.z is None:
            self.z = self._obs.initial(values[0])
        self.z, out = self._lp.run(self.z, index, values)
        if not np.isfinite(self.z).all():
            self._reset()
            raise ArithmeticError("the rod observer diverged; reset")
        n0 = self.samples_seen
        self.samples_seen += len(values)
        self.cycles_since_reset += (self.samples_seen // CYCLE) - (n0 // CYCLE)
        self._n_last = float(out[-1, 0])
        if self.trace is not None:
            idx = (index + np.arange(len(values))) % CYCLE
            self.trace.append(np.column_stack([np.full(len(values), t), idx, values, out[:, 0]]))

    def balance(self) -> np.ndarray:
        """:math:`V_i` of each cylinder (rpm²) from its coefficient bank (Figure 12)."""
        if self.z is None:
            return np.full(N_CYL, math.nan)
        v = np.zeros(N_CYL)
        for cyl in range(N_CYL):
            c = self._obs.coefficients(self.z, bank=cyl)[:, 0]
            x2 = c[1:] / self._D[1:]
            v[cyl] = float(np.sum(2.0 * np.abs(x2) ** 2))
        return v

    def _observe(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        v = self.balance()
        out = {"N_CYL_EST": self._n_last}
        for i in range(N_CYL):
            out[f"TORQUE_BALANCE_{i + 1}"] = float(v[i] - v.mean())
        return {o: val for o, val in out.items() if math.isfinite(val)}

    def _state(self) -> dict[str, Any]:
        return {**self._common_state(),  # no estimate yet (after a reset): None, not NaN
                "balance_energy": [v if math.isfinite(v) else None for v in self.balance().tolist()]}


def imbalance_observers(record: bool = False) -> list[Block]:
    """Both seed-001 observers with their default tuning."""
    return [UegoInversion(record=record), RodInversion(record=record)]


__all__ = ["RodInversion", "UegoInversion", "imbalance_observers", "STOICH_AFR"]
