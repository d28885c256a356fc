r"""The dual EKF of the three-way catalyst's oxygen storage (seed 000, section IV).

State, inputs and output (eq. 18):

.. math:: x = (\phi_1, \phi_2, \phi_3, OSC), \qquad u = (\dot m_{exh}, T_{cat}, \lambda_{pre}),
          \qquad y = \lambda_{mid}

with :math:`\dot\phi_i = (2 R_1^i - R_2^i) / OSC` and :math:`\dot{OSC} = 0` (eq. 21), the
rates and gas balances of eqs. 16-17 and the output of eq. 12
(:mod:`cell.plant.catalyst_model`, called with the observer's *own* :class:`TWCKinetics`). OSC
is carried normalised to the fresh catalyst's (``osc_fresh``), as the paper's figures
show it. The filter of eqs. 22-24 is :class:`~cell.estimators.core.KalmanCore`: predict
with :math:`\hat A = \partial f/\partial x` and update with
:math:`\hat C = \partial g/\partial x` (eq. 24), both analytic (:func:`model_f`,
:func:`model_g`); a test checks each against central differences.

"Dual": one filter estimates the fast states (SOX) and the slow parameter (OSC) together;
:math:`Q = \mathrm{diag}(Q_1 \dots Q_4)` (eq. 20), and :math:`Q_4` alone sets how fast the
OSC estimate moves (Figure 6); its default is the paper's 2e-5.

Discretisation
--------------
Between two ticks (``dt``, 0.1 s at MED) the model is integrated with explicit Euler in
sub-steps of at most ``max_step`` (0.01 s, the plant's own step: the storage saturates in a
fraction of a second in fuel cut), with the inputs held, and the transition Jacobian is the
product of the sub-steps' :math:`(I + h \hat A)`. Q and R are per tick (discrete).

Sensors
-------
The wide-band sensors lag (a first-order lag, ``tau_lambda``, 0.1 s as documented for
the cell's sensors). The observer undoes it on λ_pre (the lag inverted between two
samples, :math:`\lambda_{in} = m_{k-1} + (m_k - m_{k-1}) / a`, :math:`a = 1 - e^{-dt/\tau}`)
and applies it to its predicted λ_mid (:math:`\hat y_k = \hat y_{k-1} + a (g(\hat x_k) -
\hat y_{k-1})`, so :math:`\hat C` is scaled by :math:`a`), and it integrates over
:math:`[t_{k-1}, t_k]` with the inputs sampled at :math:`t_k`, which describe that interval
(``input_at_end``). Without these, an aged catalyst's OSC came out 10 % low: the rich
purge after each fuel cut, whose breakthrough tells OSC, was seen 0.1-0.5 s late.

Measurement scale
-----------------
λ_mid swings from 0.9 to 10 (fuel cut). The innovation is taken on a compressed scale,
:math:`s(\lambda) = 1 + w \tanh((\lambda - 1)/w)` with :math:`w` = 0.03, identical to λ
near 1, where the catalyst's state shows, and bounded beyond ±3 %: in fuel cut a saturated
catalyst passes air through whatever the model says, and the depth of a breakthrough
(λ_mid down to the purge's 0.93) depends on the sensor's lag more than on the state; its
timing is what tells OSC. (w = 0.1 and 0.02 gave a noisier OSC of an aged catalyst.)

Robustness
----------
- φ is clipped to [0, 1] and OSC to [``osc_min``, ``osc_max``] after every step (and
  inside the integration); :math:`P` is kept symmetric positive definite by the core's
  guard.
- Inputs that are not finite, or lie outside their plausible range
  (:data:`INPUT_RANGES`), are refused before anything changes: the tick's outputs are
  marked invalid with the reason, and the state stays.
- Inputs gone stale (a silent frame) stop the block (the runtime does not step it: its
  outputs go stale). When they return after more than ``max_gap``, the state is not
  predicted over the gap with inputs nobody saw; :math:`P` grows by :math:`Q` per missed
  tick instead.
- An innovation larger than ``innovation_limit`` standard deviations is taken with a
  larger R (so that it counts as that many), and a large one is taken with an iterated
  update (``iterations`` Gauss-Newton steps, relinearised at the corrected state): a
  breakthrough that the prior linearisation put far off would otherwise throw φ across the
  catalyst, the wrong way.
- Below ``adapt_temp`` (350 °C of T_CAT) the storage is limited by the kinetics, where OSC
  and the rate constants cannot be told apart: OSC is held (its gain is zero) and only φ
  is corrected.
- During fuel cut and ``blank_hold`` after it (λ above ``blank_lambda``) only the
  prediction runs: the saturated catalyst passes air whatever its state.
- Divergence (non-finite numbers, or the NIS above its gate for ``nis_window`` updates in
  a row) resets the filter to its initial state; ``state()`` shows the reset count and
  reason.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from cell.core.options import Option
from cell.core.registry import BlockSet
from cell.runtime.blocks import Param
from cell.plant.catalyst_model import (
    TWCKinetics,
    feed_gas,
    gas_concentration,
    rate_constants,
    residence_time,
)
from cell.estimators.contract import DesignError, Estimate, ObserverContract
from cell.estimators.core import KalmanCore
from cell.estimators.observer import core_state

KELVIN = 273.15

#: The observer's model: the plant's equations with its own, deliberately imperfect,
#: parameters (an observer on a real catalyst knows its kinetics only roughly): both
#: reaction rates 10 % off, in opposite directions, and the carbon fraction 2 % high.
#: The fresh capacity (the normalisation of OSC) is the catalyst's specification, shared.
MODEL_KINETICS = TWCKinetics().scaled(A1=0.9, A2=1.1, y_c=1.02)

#: Plausible range of each input; a value outside is refused (the sensor or frame is bad).
INPUT_RANGES: dict[str, tuple[float, float]] = {
    "EXH_MASS_FLOW": (0.0, 0.6),
    "T_CAT": (-50.0, 1200.0),
    "LAMBDA_PRE": (0.5, 16.0),
    "LAMBDA_MID": (0.5, 16.0),
}

#: Paper's default of the OSC process noise (section V: "Q4 = 0.00002").
Q4_DEFAULT = 2e-5
DEFAULT_Q = (1e-4, 1e-4, 1e-4, Q4_DEFAULT)
DEFAULT_R = 1e-4
SCALE_W = 0.03
#: What the λ sensors' lag may act on (the plant's ``--lambda-sensor``).
LAMBDA_LAGS = ("lambda", "composition")
#: A design's sensor model and kinetics: key -> (lo, hi) for the numbers.
DESIGN_RANGES: dict[str, tuple[float, float]] = {
    "tau_lambda": (0.0, 1.0), "dead_time": (0.0, 0.5), "kinetics_scale": (0.1, 10.0)}


# -- the model: f, g and their Jacobians ------------------------------------------------------
class Operating:
    """What the inputs fix for one tick: c₀, τ, the feed gas and the rate constants."""

    __slots__ = ("c0", "carbon", "co_in", "k", "o2_in", "rates", "tau")

    def __init__(self, u: tuple[float, float, float], k: TWCKinetics) -> None:
        mdot, T_cat, lam_pre = u
        T = T_cat + KELVIN
        self.k = k
        self.c0 = gas_concentration(T, k)
        self.tau = residence_time(mdot, self.c0, k)
        self.o2_in, self.co_in, self.carbon = feed_gas(lam_pre, self.c0, k)
        self.rates = rate_constants(T, k)


def _cells(x: list[float], op: Operating, jac: bool):
    """f₁..f₃ (eq. 21) and, with ``jac``, their gradients and those of the outlet [O₂],
    [CO] with respect to x = (φ₁, φ₂, φ₃, OSC normalised)."""
    k1f, k1b, k2f, k2b = op.rates
    tau, c0, C = op.tau, op.c0, op.carbon
    F = op.k.osc_fresh
    oscn = x[3]
    osc = oscn * F
    o2_in, co_in = op.o2_in, op.co_in
    g_o2_in = [0.0] * 4
    g_co_in = [0.0] * 4
    f = [0.0, 0.0, 0.0]
    A = [[0.0] * 4 for _ in range(3)] if jac else None
    for i in range(3):
        phi = x[i]
        ce3 = (1.0 - phi) * osc
        ce4 = phi * osc
        a1 = k1f * ce3 * ce3
        b1 = k1b * c0 * ce4 * ce4
        d1 = 1.0 + tau * a1
        o2 = (o2_in + tau * b1) / d1
        a2 = k2f * ce4 + k2b * ce3
        b2 = k2b * C * ce3
        d2 = 1.0 + tau * a2
        co = (co_in + tau * b2) / d2
        n = 2.0 * (o2_in - o2) - (co_in - co)
        fi = n / (tau * osc)
        f[i] = fi
        if jac:
            do2_da1, do2_db1 = -tau * o2 / d1, tau / d1
            dco_da2, dco_db2 = -tau * co / d2, tau / d2
            # partial derivatives of a1, b1, a2, b2 by phi_i and by OSC (normalised)
            da1_p, da1_o = -2.0 * k1f * ce3 * osc, 2.0 * k1f * ce3 * (1.0 - phi) * F
            db1_p, db1_o = 2.0 * k1b * c0 * ce4 * osc, 2.0 * k1b * c0 * ce4 * phi * F
            da2_p, da2_o = (k2f - k2b) * osc, (k2f * phi + k2b * (1.0 - phi)) * F
            db2_p, db2_o = -k2b * C * osc, k2b * C * (1.0 - phi) * F
            g_o2 = [g / d1 for g in g_o2_in]
            g_co = [g / d2 for g in g_co_in]
            g_o2[i] += do2_da1 * da1_p + do2_db1 * db1_p
            g_o2[3] += do2_da1 * da1_o + do2_db1 * db1_o
            g_co[i] += dco_da2 * da2_p + dco_db2 * db2_p
            g_co[3] += dco_da2 * da2_o + dco_db2 * db2_o
            s = 1.0 / (tau * osc)
            row = A[i]
            for j in range(4):
                row[j] = (2.0 * (g_o2_in[j] - g_o2[j]) - (g_co_in[j] - g_co[j])) * s
            row[3] -= fi / oscn
            g_o2_in, g_co_in = g_o2, g_co
        o2_in, co_in = o2, co
    return f, A, o2_in, co_in, g_o2_in, g_co_in


def model_f(x, u, k: TWCKinetics = MODEL_KINETICS) -> np.ndarray:
    """dx/dt of eq. 21 at state ``x`` and inputs ``u`` = (ṁ_exh kg/s, T_cat °C, λ_pre)."""
    f, *_ = _cells([float(v) for v in x], Operating(tuple(map(float, u)), k), False)
    return np.array([*f, 0.0])


def model_A(x, u, k: TWCKinetics = MODEL_KINETICS) -> np.ndarray:
    """Â = ∂f/∂x (eq. 24), analytic, 4 x 4 (the OSC row is zero)."""
    _, A, *_ = _cells([float(v) for v in x], Operating(tuple(map(float, u)), k), True)
    return np.array([*A, [0.0] * 4])


def model_g(x, u, k: TWCKinetics = MODEL_KINETICS) -> float:
    """Predicted λ_mid, eq. 12 at the outlet of cell 3 (eq. 21's output)."""
    op = Operating(tuple(map(float, u)), k)
    _, _, o2, co, *_ = _cells([float(v) for v in x], op, False)
    return (2.0 * o2 + 2.0 * op.carbon - co) / (2.0 * op.carbon)


def model_C(x, u, k: TWCKinetics = MODEL_KINETICS) -> np.ndarray:
    """Ĉ = ∂g/∂x (eq. 24), analytic, 1 x 4: ∂λ/∂[O₂] = 1/C, ∂λ/∂[CO] = -1/(2C) (eq. 12)."""
    op = Operating(tuple(map(float, u)), k)
    _, _, _, _, g_o2, g_co = _cells([float(v) for v in x], op, True)
    C = op.carbon
    return np.array([[g_o2[j] / C - g_co[j] / (2.0 * C) for j in range(4)]])


def carbon_share(lam: float, k: TWCKinetics) -> float:
    """D = 2 x the carbon mole fraction of feed gas of λ: the denominator of eq. 12 per mole
    of gas (the numerator is λ D), for the lag on composition."""
    return 2.0 * feed_gas(lam, 1.0, k)[2]


def undo_composition_lag(m: float, Np: float, Dp: float, a: float, k: TWCKinetics
                         ) -> tuple[float, float, float]:
    r"""The feed λ that moved a composition-lagged sensor from ``(Np, Dp)`` to read ``m``, and
    the sensor's new ``(N, D)``.

    The sensor reads :math:`N_s / D_s` with :math:`N_s \leftarrow N_p + a(\lambda D(\lambda)
    - N_p)` and likewise :math:`D_s`, so :math:`a D(\lambda)(\lambda - m) = (1 - a)(m D_p -
    N_p)`; D is constant when rich and :math:`2 y_C / (1 + c(\lambda - 1))` when lean (module
    :mod:`cell.plant.catalyst_model`), which gives λ in closed form on either side.
    """
    r = (1.0 - a) * (m * Dp - Np) / (a * 2.0 * k.y_c)
    lam = m + r
    if lam > 1.0:
        c = k.y_c / k.y_o2_air
        den = 1.0 - r * c
        lam = (m + r * (1.0 - c)) / den if den > 1e-9 else 16.0
    lam = min(max(lam, 0.5), 16.0)
    D = carbon_share(lam, k)
    return lam, Np + a * (lam * D - Np), Dp + a * (D - Dp)


def scale(lam: float) -> tuple[float, float]:
    """The measurement scale s(λ) and its slope (module notes)."""
    th = math.tanh((lam - 1.0) / SCALE_W)
    return 1.0 + SCALE_W * th, 1.0 - th * th


def predict(x: list[float], op: Operating, dt: float, max_step: float, bounds: tuple[float, float]
            ) -> tuple[list[float], list[list[float]]]:
    """State after ``dt`` with the inputs held (Euler sub-steps) and the transition
    Jacobian Φ = Π (I + h Â), as nested lists.

    A sub-step is at most ``max_step`` and at most 1 / max|Â_ii| (explicit Euler stays
    monotone on the stiffest cell: a small OSC at high flow fills in milliseconds), with at
    most 1000 sub-steps per call.
    """
    lo, hi = bounds
    x = list(x)
    Phi = [[1.0 if i == j else 0.0 for j in range(4)] for i in range(4)]
    left = dt
    h_min = dt / 1000.0
    while left > 1e-12:
        f, A, *_ = _cells(x, op, True)
        stiff = max(abs(A[0][0]), abs(A[1][1]), abs(A[2][2]))
        h = min(max_step, left, max(1.0 / stiff if stiff > 0 else left, h_min))
        if left - h < 1e-9:
            h = left
        # Phi <- (I + h A) Phi. A cell depends only on the cells upstream and on OSC, so the
        # φ block of A and Phi is lower triangular, and OSC's row stays e4
        (a00, _, _, a03), (a10, a11, _, a13), (a20, a21, a22, a23) = A
        (p00, _, _, p03), (p10, p11, _, p13), (p20, p21, p22, p23) = Phi[0], Phi[1], Phi[2]
        Phi = [
            [p00 + h * a00 * p00, 0.0, 0.0, p03 + h * (a00 * p03 + a03)],
            [p10 + h * (a10 * p00 + a11 * p10), p11 + h * a11 * p11, 0.0,
             p13 + h * (a10 * p03 + a11 * p13 + a13)],
            [p20 + h * (a20 * p00 + a21 * p10 + a22 * p20), p21 + h * (a21 * p11 + a22 * p21),
             p22 + h * a22 * p22, p23 + h * (a20 * p03 + a21 * p13 + a22 * p23 + a23)],
            Phi[3],
        ]
        for i in range(3):
            x[i] = min(max(x[i] + h * f[i], 0.0), 1.0)
        x[3] = min(max(x[3], lo), hi)
        left -= h
    return x, Phi


# -- the block ----------------------------------------------------------------------------------
class TWCObserver(ObserverContract):
    """The dual EKF of seed 000 as a runtime block (family ``observer``).

    Inputs: ``EXH_MASS_FLOW``, ``T_CAT``, ``LAMBDA_PRE`` (u, eq. 18) and ``LAMBDA_MID``
    (y). Outputs: ``SOX_EST`` (mean of φ, the paper's φ̂), ``PHI_1_EST`` .. ``PHI_3_EST``,
    ``OSC_EST`` (normalised to fresh) and ``LAMBDA_MID_EST``, the predicted output
    :math:`\\hat y(k) = g(\\hat x(k|k-1), u(k))` (eq. 22).

    Parameters
    ----------
    name:
        Block name (``twc``).
    kinetics:
        The observer model's own constants (default :data:`MODEL_KINETICS`).
    Q, R, P0:
        Process noise (4 variances per tick), measurement noise (λ_mid, per tick) and
        initial covariance (diagonals).
    osc_init:
        Initial OSC guess, normalised (default 1: a fresh catalyst).
    phi_init:
        Initial φ of every cell.
    max_step, max_gap:
        Longest integration sub-step, and longest gap between ticks predicted over, s.
    osc_bounds:
        OSC is kept within these (normalised).
    nis_gate, nis_window:
        Reset after ``nis_window`` consecutive updates above the ``nis_gate`` quantile.
    blank_lambda, blank_hold:
        No update while λ_pre or λ_mid is above ``blank_lambda`` (fuel cut) and for
        ``blank_hold`` s after.
    adapt_temp:
        Below this T_CAT (°C), OSC is held.
    tau_lambda, lead, input_at_end:
        The λ sensors' time constant, s (0: none); whether λ_pre's lag is undone; whether a
        tick's inputs drive the interval before it (see the module notes).
    innovation_limit, iterations:
        The robust update's bound, in standard deviations (0: none), and the iterations of
        the iterated update (1: a plain EKF update).

    Tunable (``PATCH /observers/twc``, all or nothing): ``Q``, ``R``, ``P0``, ``osc_init``,
    ``phi_init``, ``nis_gate``, ``nis_window``. New Q/R act at the next tick and keep the
    estimate; a new ``osc_init`` or ``phi_init`` restarts the filter from it at once;
    ``P0`` acts at the next reset.
    """

    VOLATILE = ("osc_init",)
    INPUTS = ("EXH_MASS_FLOW", "T_CAT", "LAMBDA_PRE", "LAMBDA_MID")
    OUTPUTS = ("SOX_EST", "PHI_1_EST", "PHI_2_EST", "PHI_3_EST", "OSC_EST", "LAMBDA_MID_EST",
               "SOX_EST_SD")
    #: The confidence bands beside the estimates: runtime channels, not on the bus.
    BANDS = ("OSC_EST_SD", "SOX_EST_SD")
    state_names = STATES = ("PHI_1", "PHI_2", "PHI_3", "OSC")

    def __init__(self, name: str = "twc", *, kinetics: TWCKinetics | None = None,
                 Q: Any = DEFAULT_Q, R: Any = DEFAULT_R, P0: Any = (0.1, 0.1, 0.1, 1e-3),
                 osc_init: float = 1.0, phi_init: float = 0.5, rate: str = "MED",
                 max_step: float = 0.01, max_gap: float = 1.0, osc_bounds=(0.05, 4.0),
                 nis_gate: float = 0.9999, nis_window: int = 100, blank_lambda: float = 1.1,
                 blank_hold: float = 0.5, adapt_temp: float = 350.0, tau_lambda: float = 0.1,
                 lead: bool = True, innovation_limit: float = 3.0, iterations: int = 4,
                 input_at_end: bool = True, lambda_lag: str = "lambda",
                 dead_time: float = 0.0) -> None:
        super().__init__(name, list(self.INPUTS), list(self.OUTPUTS), rate,
                         units={"OSC_EST_SD": "1", "SOX_EST_SD": "1"})
        self.declare(ranges=INPUT_RANGES, sd={3: "OSC_EST_SD"}, gap_ticks=10)
        self.base_kinetics = kinetics or MODEL_KINETICS
        self.kinetics = self.base_kinetics
        self.kinetics_scale = 1.0
        self.lambda_lag = str(lambda_lag)
        self.dead_time = float(dead_time)
        self.designed: dict[str, Any] | None = None
        self._history: list[tuple[float, float, float]] = []
        self.max_step = float(max_step)
        self.max_gap = float(max_gap)
        self.blank_lambda = float(blank_lambda)
        self.blank_hold = float(blank_hold)
        self.adapt_temp = float(adapt_temp)
        self.tau_lambda = float(tau_lambda)
        self.lead = bool(lead)
        self.innovation_limit = float(innovation_limit)
        self.limited = 0
        self.iterations = int(iterations)
        self.input_at_end = bool(input_at_end)
        self.iterated = 0
        self._pre_prev: float | None = None
        self._y_sensor: float | None = None
        self.frozen = 0
        self._blank_until = -math.inf
        self.blanked = 0
        self.osc_bounds = (float(osc_bounds[0]), float(osc_bounds[1]))
        lo, hi = self.osc_bounds
        self.PARAMS = {
            "Q": Param("Q", float, "process noise per tick: φ1, φ2, φ3, OSC (eq. 20)",
                       shape="diag", size=4, pd=True),
            "R": Param("R", float, "measurement noise of λ_mid per tick", shape="diag", size=1,
                       pd=True),
            "P0": Param("P0", float, "initial covariance (diagonal), taken at the next reset",
                        shape="diag", size=4, pd=True),
            "osc_init": Param("osc_init", float, "initial OSC guess, normalised to fresh; "
                              "restarts the filter from it", gt=lo, le=hi),
            "phi_init": Param("phi_init", float, "initial φ of every cell; restarts the filter",
                              ge=0.0, le=1.0),
            "nis_gate": Param("nis_gate", float, "chi-square probability of the NIS gate",
                              ge=0.5, le=1.0 - 1e-12),
            "nis_window": Param("nis_window", int,
                                "consecutive updates above the NIS gate that reset (0: off)",
                                ge=0, le=1_000_000),
        }
        checked = self.validate({"Q": Q, "R": R, "P0": P0, "osc_init": osc_init,
                                 "phi_init": phi_init, "nis_gate": nis_gate,
                                 "nis_window": nis_window})
        for key, value in checked.items():
            setattr(self, key, value)
        self.core = KalmanCore(self._x0(), np.diag(self.P0), np.diag(self.Q), np.diag(self.R),
                               constraint=self._constrain, nis_gate=self.nis_gate,
                               nis_window=self.nis_window, name=name)
        self._t: float | None = None
        self._u: tuple[float, float, float] | None = None
        self.skipped_gaps = 0

    # -- parameters ---------------------------------------------------------------------------
    def _x0(self) -> np.ndarray:
        return np.array([self.phi_init] * 3 + [self.osc_init], dtype=float)

    def _constrain(self, x: np.ndarray) -> np.ndarray:
        lo, hi = self.osc_bounds
        return np.array([min(max(x[0], 0.0), 1.0), min(max(x[1], 0.0), 1.0),
                         min(max(x[2], 0.0), 1.0), min(max(x[3], lo), hi)])

    def _apply(self, checked: dict[str, Any]) -> None:
        super()._apply(checked)
        core = self.core
        core.Q, core.R = np.diag(self.Q), np.diag(self.R)
        core.P0 = np.diag(self.P0)
        core.nis_gate, core.nis_window = self.nis_gate, self.nis_window
        core.x0 = self._x0()
        restart = [k for k in ("osc_init", "phi_init") if k in checked]
        if restart:
            what = ", ".join(f"{k} = {getattr(self, k):g}" for k in restart)
            self._reset_estimate(f"restarted: {what}")

    def reset(self) -> None:
        """Restart from the initial state at the next tick (counted as a reset)."""
        self._reset_estimate("reset requested")

    # -- the contract's hooks -------------------------------------------------------------------
    def estimate(self) -> Estimate | None:
        core = self.core
        return Estimate(core.x, core.P, core.y, core.nis, 1) if self._t is not None else None

    def _restart(self, reason: str) -> None:
        """Forget the estimate. After a gap in the inputs only φ and its covariance restart:
        OSC is the slow parameter a second's silence cannot change, so it is kept, with its
        variance grown by Q₄ per tick missed (no prediction over inputs nobody saw)."""
        core = self.core
        gap = reason.startswith("resumed after a gap") and self._t is not None
        osc, p_osc = float(core.x[3]), float(core.P[3, 3])
        core.reset(reason)
        if gap:
            self.skipped_gaps += 1
            missed = max(float(reason.split("gap of ")[1].split(" s")[0]) / self.max_gap, 1.0)
            x = core.x.copy()
            x[3] = osc
            P = core.P.copy()
            P[3, 3] = p_osc + core.Q[3, 3] * missed
            core.x, core.P = x, P
        self._t = self._u = self._pre_prev = self._y_sensor = None
        self._history = []

    def _state(self) -> dict[str, Any]:
        return {
            "t": self._t,
            "states": list(self.STATES),
            **core_state(self.core),
            "skipped_gaps": self.skipped_gaps,
            "blanked": self.blanked,
            "osc_frozen": self.frozen,
            "innovations_limited": self.limited,
            "iterated_updates": self.iterated,
            "sensor_model": self.sensor_model(),
            "design": None if self.designed is None else self.designed.get("source"),
        }

    # -- designs ------------------------------------------------------------------------------------
    def sensor_model(self) -> dict[str, Any]:
        """The λ sensors and kinetics the observer assumes (what ``testcell design twc``
        identifies)."""
        return {"lambda_lag": self.lambda_lag, "tau_lambda": self.tau_lambda,
                "dead_time": self.dead_time, "kinetics_scale": self.kinetics_scale}

    def _design_payload(self) -> dict[str, Any]:
        return {"identified": self.sensor_model()}

    def _check_design(self, design: Mapping[str, Any]) -> dict[str, Any]:
        got = design.get("identified")
        if got is None:
            return {}
        if not isinstance(got, Mapping):
            raise DesignError("field 'identified' must be an object")
        known = ("lambda_lag", *DESIGN_RANGES)
        for key in got:
            if key not in known:
                raise DesignError(f"identified.{key}: unknown; known: {', '.join(known)}")
        out: dict[str, Any] = {}
        if "lambda_lag" in got:
            if got["lambda_lag"] not in LAMBDA_LAGS:
                raise DesignError(f"identified.lambda_lag: must be one of {', '.join(LAMBDA_LAGS)}, "
                                  f"got {got['lambda_lag']!r}")
            out["lambda_lag"] = got["lambda_lag"]
        for key, (lo, hi) in DESIGN_RANGES.items():
            if key in got:
                v = got[key]
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not (
                        math.isfinite(v) and lo <= v <= hi):
                    raise DesignError(f"identified.{key}: must be a number in [{lo:g}, {hi:g}], "
                                      f"got {v!r}")
                out[key] = float(v)
        if out.get("kinetics_scale", 1.0) <= 0:
            raise DesignError("identified.kinetics_scale: must be > 0")
        return out

    def _use_design(self, checked: dict[str, Any]) -> None:
        if "lambda_lag" in checked:
            self.lambda_lag = checked["lambda_lag"]
        if "tau_lambda" in checked:
            self.tau_lambda = checked["tau_lambda"]
        if "dead_time" in checked:
            self.dead_time = checked["dead_time"]
        if "kinetics_scale" in checked:
            f = self.kinetics_scale = checked["kinetics_scale"]
            self.kinetics = self.base_kinetics.scaled(A1=f, A2=f)
        self.designed = dict(checked)

    def load_design(self, design: Any, source: str = "design") -> None:
        super().load_design(design, source)
        if self.designed is not None:
            self.designed["source"] = source

    # -- stepping -------------------------------------------------------------------------------
    def _delayed(self, t: float, mdot: float, T_cat: float) -> tuple[float, float]:
        """ṁ and T_CAT at ``t - dead_time`` (linear between ticks): what the gas the λ sensors
        show at ``t`` went through."""
        h = self._history
        h.append((t, mdot, T_cat))
        td = t - self.dead_time
        while len(h) > 2 and h[1][0] <= td:
            h.pop(0)
        if len(h) < 2 or td <= h[0][0]:
            return h[0][1], h[0][2]
        (t0, m0, T0), (t1, m1, T1) = h[0], h[1]
        w = 0.0 if t1 <= t0 else min((td - t0) / (t1 - t0), 1.0)
        return m0 + w * (m1 - m0), T0 + w * (T1 - T0)

    def _observe(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        mdot, T_cat = float(inputs["EXH_MASS_FLOW"]), float(inputs["T_CAT"])
        lam_pre, lam_mid = float(inputs["LAMBDA_PRE"]), float(inputs["LAMBDA_MID"])
        if self.dead_time > 0:
            mdot, T_cat = self._delayed(t, mdot, T_cat)
        composition = self.lambda_lag == "composition"
        k = self.kinetics
        core = self.core
        t_prev, u_prev = self._t, self._u
        a = 1.0
        if t_prev is not None and self.tau_lambda > 0 and 0 < t - t_prev <= self.max_gap:
            a = -math.expm1(-(t - t_prev) / self.tau_lambda)
        lam_in = lam_pre
        pre_prev = self._pre_prev
        if composition:
            # the sensor's lagged (N, D) of eq. 12: undone to the feed gas's λ
            if self.lead and a < 1.0 and pre_prev is not None:
                lam_in, Np, Dp = undo_composition_lag(lam_pre, *pre_prev, a, k)
            else:
                Dp = carbon_share(lam_pre, k)
                Np = lam_pre * Dp
            self._pre_prev = (Np, Dp)
        else:
            self._pre_prev = lam_pre
            if self.lead and a < 1.0 and pre_prev is not None:
                lam_in = min(max(pre_prev + (lam_pre - pre_prev) / a, 0.5), 16.0)
        u = (mdot, T_cat, lam_in)
        self._t, self._u = t, u
        if t_prev is not None and t > t_prev:
            dt = t - t_prev
            if dt > self.max_gap:
                # no prediction over inputs nobody saw: the uncertainty grows instead
                self.skipped_gaps += 1
                ticks = dt / self.max_gap
                core.predict(F=np.eye(4), Q=core.Q * ticks)
            else:
                op = Operating(u if self.input_at_end else u_prev, k)
                x_new, Phi = predict(core.x.tolist(), op, dt, self.max_step, self.osc_bounds)
                core.predict(u_prev, F=np.array(Phi), f=lambda x, _u: np.array(x_new))
        op = Operating(u, k)
        m = self._y_sensor if a < 1.0 else None
        if m is not None and composition != isinstance(m, tuple):
            m = None

        def measure(xv: list[float]) -> tuple[Any, float, float, np.ndarray]:
            """λ_mid as the sensor shows it (and the sensor's state), on the measurement
            scale, and its gradient."""
            _, _, o2, co, g_o2, g_co = _cells(xv, op, True)
            C = op.carbon
            if composition:
                # the sensor lags the outlet's N = 2[O2] + 2C - [CO] and D = 2C (per mole)
                c0 = op.c0
                N, D = (2.0 * o2 + 2.0 * C - co) / c0, 2.0 * C / c0
                if m is not None:
                    N, D = m[0] + a * (N - m[0]), m[1] + a * (D - m[1])
                y = N / D
                sv, slope = scale(y)
                slope *= (1.0 if m is None else a) / (D * c0)
                return (N, D), y, sv, np.array([[slope * (2.0 * g_o2[j] - g_co[j])
                                                 for j in range(4)]])
            g = (2.0 * o2 + 2.0 * C - co) / (2.0 * C)
            y = g if m is None else m + a * (g - m)
            sv, slope = scale(y)
            slope *= 1.0 if m is None else a
            return y, y, sv, np.array([[slope * (g_o2[j] / C - g_co[j] / (2.0 * C))
                                        for j in range(4)]])

        x_prior = core.x.copy()
        self._y_sensor, y_hat, s_hat, H = measure(x_prior.tolist())
        if max(lam_pre, lam_mid) > self.blank_lambda:
            self._blank_until = t + self.blank_hold
        if t < self._blank_until:
            self.blanked += 1  # fuel cut and its tail: predict only
        else:
            freeze = T_cat < self.adapt_temp
            if freeze:
                # a cold catalyst's storage is limited by its kinetics, where OSC and the
                # rate constants cannot be told apart: OSC is held (its gain is zero)
                self.frozen += 1
                H[0, 3] = 0.0
                P = core.P.copy()
                P[3, :3] = P[:3, 3] = 0.0
                core.P = P
            z = scale(lam_mid)[0]
            P, Rm = core.P, core.R
            R = None
            c = self.innovation_limit
            y2 = (z - s_hat) ** 2
            hph = float((H @ P @ H.T)[0, 0])
            if c > 0 and y2 > c * c * (hph + Rm[0, 0]):
                # an innovation the model cannot explain (more than c standard deviations)
                # is taken with a larger R, so that it counts as c (robust update)
                R = np.array([[y2 / (c * c) - hph]])
                self.limited += 1
            h_lin = s_hat
            if y2 > (hph + Rm[0, 0]) and self.iterations > 1:
                # iterated update (Gauss-Newton on the measurement): relinearise at the
                # corrected state, so that a breakthrough the prior put far off does not
                # throw the state the wrong way across the catalyst
                Rk = Rm if R is None else R
                xi = x_prior
                for _ in range(self.iterations - 1):
                    K = (P @ H.T) / float((H @ P @ H.T)[0, 0] + Rk[0, 0])
                    x_next = self._constrain(x_prior + (K * (z - s_hat - float(
                        (H @ (x_prior - xi))[0]))).ravel())
                    if np.max(np.abs(x_next - xi)) < 1e-6:
                        break
                    xi = x_next
                    _, _, s_hat, H = measure(xi.tolist())
                    if freeze:
                        H[0, 3] = 0.0
                self.iterated += 1
                h_lin = s_hat + float((H @ (x_prior - xi))[0])
            core.update([z], H=H, R=R, h=lambda x, v=h_lin: np.array([v]))
        x, P = core.x, core.P
        # the band of the mean φ: sqrt(1ᵀ P_φφ 1) / 3
        sox_var = float(P[0, 0] + P[1, 1] + P[2, 2] + 2.0 * (P[0, 1] + P[0, 2] + P[1, 2])) / 9.0
        return {"SOX_EST": float(x[0] + x[1] + x[2]) / 3.0, "PHI_1_EST": float(x[0]),
                "PHI_2_EST": float(x[1]), "PHI_3_EST": float(x[2]), "OSC_EST": float(x[3]),
                "LAMBDA_MID_EST": y_hat, "SOX_EST_SD": math.sqrt(max(sox_var, 0.0))}


def twc_observers(osc_init: float | None = None) -> list[TWCObserver]:
    """The runtime's catalyst observer (``twc``), with ``--osc-init`` when given."""
    return [TWCObserver("twc", osc_init=1.0 if osc_init is None else osc_init)]


def _osc_init_check(v: float) -> str | None:
    if not (math.isfinite(v) and 0.05 < v <= 4.0):
        return f"must be in (0.05, 4] (normalised to the fresh catalyst), got {v}"
    return None


#: seed 000's dual EKF in the runtime of si-turbo, with its own option ``--osc-init``.
CATALYST_BLOCKS = BlockSet(
    "seed000-twc", lambda run: twc_observers(run.blocks.get("osc_init")), engines=("si-turbo",),
    options=(Option("osc_init", "--osc-init", float, metavar="X", check=_osc_init_check,
                    help="initial OSC guess of the catalyst observer twc, normalised to fresh "
                         "(default 1)"),))


__all__ = ["DEFAULT_Q", "DEFAULT_R", "INPUT_RANGES", "MODEL_KINETICS", "Q4_DEFAULT", "TWCObserver",
           "model_A", "model_C", "model_f", "model_g", "predict", "twc_observers", "CATALYST_BLOCKS"]
