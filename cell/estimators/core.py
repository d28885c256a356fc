r"""One discrete Kalman / extended Kalman filter core for every model-based observer.

The core runs the two steps of the discrete filter separately, for a linear model
(matrices) or a nonlinear one (functions and their Jacobians):

Predict (time update)

.. math::
    \hat x_{k|k-1} = F \hat x_{k-1|k-1} + B u \quad\text{or}\quad f(\hat x_{k-1|k-1}, u),
    \qquad P_{k|k-1} = F P_{k-1|k-1} F^\top + Q

with :math:`F = \partial f/\partial x` at :math:`\hat x_{k-1|k-1}` in the extended case.

Update (measurement update), with :math:`H = \partial h/\partial x` at :math:`\hat x_{k|k-1}`
in the extended case

.. math::
    y_k = z_k - h(\hat x_{k|k-1}), \quad S_k = H P_{k|k-1} H^\top + R, \quad
    K_k = P_{k|k-1} H^\top S_k^{-1}, \quad \hat x_{k|k} = \hat x_{k|k-1} + K_k y_k

and the covariance in Joseph form, valid for any gain (so also for a constant one):

.. math:: P_{k|k} = (I - K_k H) P_{k|k-1} (I - K_k H)^\top + K_k R K_k^\top

The normalised innovation squared :math:`\mathrm{NIS}_k = y_k^\top S_k^{-1} y_k` is
:math:`\chi^2_m`-distributed for a consistent filter with :math:`m` measurements, and the
log-likelihood of the update is
:math:`\ell_k = -\tfrac12 (\mathrm{NIS}_k + \log\det(2\pi S_k))`.

Names follow filterpy (``x``, ``P``, ``K``, ``y``, ``S``, ``log_likelihood``) plus ``nis``.

Besides the textbook filter the core has what an observer on a test bed needs:

- a constant-gain mode (:math:`K` fixed, :math:`P` not propagated: the constant-gain EKF
  of seed 003) and a scheduled-gain mode (:class:`GainSchedule`: :math:`K` interpolated over
  operating points, seed 003's look-up table);
- a state-constraint hook applied after each step (:func:`bounds`, e.g. the oxygen
  storage fractions :math:`\phi_i \in [0, 1]` of seed 000);
- a guard that keeps :math:`P` symmetric positive definite, and divergence detection
  (non-finite values, or a NIS above a chi-square gate for several updates in a row)
  that resets to :math:`x_0, P_0` and raises :class:`Diverged`.

:class:`Model` describes a nonlinear model in python-control's style, ``f(t, x, u, params)``
and ``h(t, x, u, params)``, continuous or discrete, and turns it into the closures the
core's extended steps take.
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg
import scipy.stats

log = logging.getLogger(__name__)

#: Relative eigenvalue floor of the covariance guard: an eigenvalue of P below
#: ``EIG_FLOOR_REL`` times the largest one is lifted to it. 1000 machine epsilons leaves
#: the rebuilt matrix positive definite despite its own rounding.
EIG_FLOOR_REL = 1e3 * np.finfo(float).eps

Matrix = np.ndarray | Callable[..., Any] | None


class Diverged(ArithmeticError):
    """The filter diverged and was reset to its initial state; the message says why."""


def numerical_jacobian(fun: Callable[[np.ndarray], Any], x: Any, rel_step: float | None = None
                       ) -> np.ndarray:
    r"""Jacobian of ``fun`` at ``x`` by central differences.

    .. math:: J_{:,j} = \frac{f(x + h_j e_j) - f(x - h_j e_j)}{2 h_j}, \qquad
              h_j = \epsilon \max(1, |x_j|)

    with :math:`\epsilon = \epsilon_\text{mach}^{1/3}` (about 6e-6) by default, which
    balances the :math:`O(h^2)` truncation against rounding.

    Returns
    -------
    numpy.ndarray
        Shape ``(len(fun(x)), len(x))``.
    """
    x = np.asarray(x, dtype=float)
    steps = (rel_step or np.finfo(float).eps ** (1 / 3)) * np.maximum(1.0, np.abs(x))
    cols = []
    for j, hj in enumerate(steps):
        e = np.zeros_like(x)
        e[j] = hj
        hi, lo = x + e, x - e
        diff = np.atleast_1d(np.asarray(fun(hi), dtype=float) - np.asarray(fun(lo), dtype=float))
        cols.append(diff / (hi[j] - lo[j]))
    return np.column_stack(cols)


def steady_state_gain(F: Any, H: Any, Q: Any, R: Any) -> tuple[np.ndarray, np.ndarray]:
    r"""Stationary gain of the discrete filter from the discrete algebraic Riccati equation.

    :math:`P` (the a-priori covariance) solves

    .. math:: P = F P F^\top - F P H^\top (H P H^\top + R)^{-1} H P F^\top + Q

    (``scipy.linalg.solve_discrete_are`` with ``a = F'``, ``b = H'``), and
    :math:`K = P H^\top (H P H^\top + R)^{-1}`, the gain :meth:`KalmanCore.update` converges to.

    Returns
    -------
    K, P:
        Gain, shape ``(n, m)``, and stationary a-priori covariance, shape ``(n, n)``.
    """
    F, H = np.atleast_2d(F).astype(float), np.atleast_2d(H).astype(float)
    Q, R = np.atleast_2d(Q).astype(float), np.atleast_2d(R).astype(float)
    P = scipy.linalg.solve_discrete_are(F.T, H.T, Q, R)
    K = np.linalg.solve(H @ P @ H.T + R, H @ P).T  # P H' S^-1 with S, P symmetric
    return K, P


def bounds(lo: Any = -np.inf, hi: Any = np.inf) -> Callable[[np.ndarray], np.ndarray]:
    """A state constraint that clips each state into ``[lo, hi]`` (scalars or per state)."""
    lo_a, hi_a = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    return lambda x: np.clip(x, lo_a, hi_a)


class GainSchedule:
    r"""A gain table over a grid of scheduling variables, interpolated (multi)linearly.

    Seed 003 stores stationary Kalman gains computed at the operating points of the
    engine map and switches between them. Here the gain is interpolated between grid
    points, linearly on a 1-D grid and bilinearly on a 2-D one (e.g. engine speed x
    load), and clamped at the edges of the grid:

    .. math:: K(s) = \sum_{c \in \{0,1\}^d} \prod_{a=1}^{d} w_a^{c_a} (1 - w_a)^{1 - c_a}\,
              K_{i_1 + c_1, \dots, i_d + c_d}, \quad
              w_a = \mathrm{clip}\Big(\frac{s_a - g_{a,i_a}}{g_{a,i_a+1} - g_{a,i_a}}, 0, 1\Big)

    Parameters
    ----------
    grid:
        One strictly increasing 1-D sequence per scheduling variable (a single sequence
        is one variable).
    table:
        Gains, shape ``(*grid lengths, n, m)``.
    """

    def __init__(self, grid: Sequence[Any], table: Any) -> None:
        if np.ndim(grid[0]) == 0:
            grid = (grid,)
        self.grid = tuple(np.asarray(g, dtype=float) for g in grid)
        self.table = np.asarray(table, dtype=float)
        lens = tuple(len(g) for g in self.grid)
        if self.table.ndim != len(lens) + 2 or self.table.shape[: len(lens)] != lens:
            raise ValueError(f"gain table has shape {self.table.shape}; a grid of {lens} points "
                             f"needs shape {lens} + (n, m)")
        for g in self.grid:
            if g.ndim != 1 or not np.all(np.isfinite(g)) or np.any(np.diff(g) <= 0):
                raise ValueError(f"grid axis {g.tolist()} must be finite and strictly increasing")
        if not np.all(np.isfinite(self.table)):
            raise ValueError("gain table has non-finite entries")

    @property
    def shape(self) -> tuple[int, int]:
        """Shape ``(n, m)`` of one gain."""
        return self.table.shape[-2:]  # type: ignore[return-value]

    def __call__(self, *s: float) -> np.ndarray:
        """The gain at the scheduling point ``s`` (one value per grid axis)."""
        if len(s) != len(self.grid):
            raise ValueError(f"gain schedule takes {len(self.grid)} scheduling values, got {len(s)}")
        cells = []
        for g, v in zip(self.grid, s):
            if not math.isfinite(v):
                raise ArithmeticError(f"scheduling variable is {v}")
            i = int(np.clip(np.searchsorted(g, v, side="right") - 1, 0, max(len(g) - 2, 0)))
            w = float(np.clip((v - g[i]) / (g[i + 1] - g[i]), 0.0, 1.0)) if len(g) > 1 else 0.0
            cells.append((i, w, len(g) - 1))
        K = np.zeros(self.shape)
        for corner in itertools.product((0, 1), repeat=len(cells)):
            weight = math.prod(w if c else 1.0 - w for c, (_, w, _) in zip(corner, cells))
            if weight:
                K += weight * self.table[tuple(min(i + c, last) for c, (i, _, last) in zip(corner, cells))]
        return K


@functools.lru_cache(maxsize=64)
def _chi2_quantile(p: float, dof: int) -> float:
    return float(scipy.stats.chi2.ppf(p, dof))


def _cov(value: Any, n: int, name: str) -> np.ndarray:
    """A covariance from a number (times the identity), a diagonal or an ``n`` x ``n`` array."""
    a = np.asarray(value, dtype=float)
    if a.ndim == 0:
        a = a * np.eye(n)
    elif a.ndim == 1:
        a = np.diag(a)
    if a.shape != (n, n):
        raise ValueError(f"{name} must be {n}x{n}, got shape {a.shape}")
    return a


def _mat(value: Any, shape: tuple[int, int], name: str) -> np.ndarray:
    a = np.atleast_2d(np.asarray(value, dtype=float))
    if a.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
    return a


class KalmanCore:
    r"""Discrete Kalman / extended Kalman filter with Joseph-form update and guards.

    Parameters
    ----------
    x0, P0:
        Initial state (length ``n``) and covariance; also what a reset returns to.
    Q, R:
        Process and measurement noise covariances (``n`` x ``n``, ``m`` x ``m``; a number
        or a 1-D diagonal is accepted too).
    F, B, H:
        Matrices of a linear model (defaults of :meth:`predict`/:meth:`update`).
    gain:
        ``None``: the full filter. An ``n`` x ``m`` array: constant gain (seed 003's
        constant-gain EKF); :math:`P` is then not propagated and stays ``P0``, which should
        be the stationary a-priori covariance (:func:`steady_state_gain`) so that ``S``,
        the NIS and the log-likelihood keep their meaning. A :class:`GainSchedule`: the
        gain interpolated at the scheduling point passed to :meth:`update`.
    constraint:
        ``x -> x``, applied to the state after every predict and update (e.g.
        :func:`bounds`).
    nis_gate, nis_window:
        Divergence by consistency: reset when the NIS exceeds the ``nis_gate`` quantile
        of :math:`\chi^2_m` in ``nis_window`` consecutive updates (0 disables).
    eig_floor:
        Absolute floor of the eigenvalues of ``P`` (the relative floor is
        :data:`EIG_FLOOR_REL`).
    name:
        Shown in log messages.

    Attributes
    ----------
    x, P:
        Current estimate and covariance (a posteriori after :meth:`update`, a priori
        after :meth:`predict`).
    K, y, S, nis, log_likelihood:
        Gain, innovation, innovation covariance, NIS and log-likelihood of the last update
        (``nis`` and ``log_likelihood`` are ``None`` before the first one).
    guard_count:
        How often the covariance guard had to lift an eigenvalue.
    resets, last_reset_reason:
        Number of resets (divergences and calls of :meth:`reset`) and the last reason.

    Notes
    -----
    A step that diverges (a model function raises :class:`ArithmeticError`, ``S`` is
    singular, ``x`` or ``P`` is not finite, or the NIS gate trips) resets the filter,
    logs the reason (a warning when the reason changes, then at debug level) and raises
    :class:`Diverged`, an :class:`ArithmeticError`, so that the runtime marks that tick's
    outputs invalid.
    """

    def __init__(
        self,
        x0: Any,
        P0: Any,
        Q: Any,
        R: Any,
        F: Any = None,
        B: Any = None,
        H: Any = None,
        *,
        gain: Any = None,
        constraint: Callable[[np.ndarray], np.ndarray] | None = None,
        nis_gate: float = 0.9999,
        nis_window: int = 0,
        eig_floor: float = 0.0,
        name: str = "kalman",
    ) -> None:
        self.x0 = np.atleast_1d(np.asarray(x0, dtype=float)).copy()
        n = self.dim_x = self.x0.size
        self.P0 = _cov(P0, n, "P0")
        self.Q = _cov(Q, n, "Q")
        self.R = np.atleast_2d(np.asarray(R, dtype=float))
        m = self.dim_z = self.R.shape[0]
        self.R = _cov(self.R, m, "R")
        self.F = None if F is None else _mat(F, (n, n), "F")
        self.B = None if B is None else np.atleast_2d(np.asarray(B, dtype=float))
        self.H = None if H is None else _mat(H, (m, n), "H")
        if isinstance(gain, GainSchedule):
            if gain.shape != (n, m):
                raise ValueError(f"scheduled gains have shape {gain.shape}, the model needs {(n, m)}")
            self.gain: np.ndarray | GainSchedule | None = gain
        else:
            self.gain = None if gain is None else _mat(gain, (n, m), "gain")
        self.constraint = constraint
        self.nis_gate = nis_gate
        self.nis_window = nis_window
        self.eig_floor = eig_floor
        self.name = name
        self._I = np.eye(n)
        self.resets = 0
        self.last_reset_reason: str | None = None
        self._last_kind: str | None = None
        self.guard_count = 0
        self.updates = 0
        self._start()

    def _start(self) -> None:
        self.x = self.x0.copy()
        self.P = self.P0.copy()
        self.K = np.zeros((self.dim_x, self.dim_z))
        self.y = np.zeros(self.dim_z)
        self.S = np.zeros((self.dim_z, self.dim_z))
        self.nis: float | None = None
        self._log_likelihood: float | None = None
        self._nis_run = 0
        #: true from a (re)start until the first step is accepted
        self.fresh = True

    @property
    def mode(self) -> str:
        """``"full"``, ``"constant"`` (fixed gain) or ``"scheduled"``."""
        if self.gain is None:
            return "full"
        return "scheduled" if isinstance(self.gain, GainSchedule) else "constant"

    @property
    def nis_threshold(self) -> float:
        """The NIS gate: the ``nis_gate`` quantile of the chi-square law with ``m`` degrees."""
        return _chi2_quantile(self.nis_gate, self.dim_z)

    @property
    def log_likelihood(self) -> float | None:
        r""":math:`-\tfrac12(\mathrm{NIS} + \log\det(2\pi S))` of the last update."""
        if self._log_likelihood is None and self.nis is not None:
            sign, logdet = np.linalg.slogdet(2.0 * np.pi * self.S)
            self._log_likelihood = -0.5 * (self.nis + logdet) if sign > 0 else -math.inf
        return self._log_likelihood

    # -- the two steps -----------------------------------------------------------------
    def predict(self, u: Any = None, F: Matrix = None, B: Any = None, Q: Any = None, *,
                f: Callable[[np.ndarray, Any], Any] | None = None) -> np.ndarray:
        r"""Time update; returns the a-priori state.

        Linear (``f`` is ``None``): :math:`x \leftarrow F x + B u` with ``F``/``B`` defaulting
        to the constructor's (``B u`` is skipped without ``u`` or ``B``). Extended:
        :math:`x \leftarrow f(x, u)` and ``F`` is the Jacobian of ``f`` at the old ``x``:
        a matrix, a function ``F(x, u)``, or ``None`` for :func:`numerical_jacobian`.
        Then :math:`P \leftarrow F P F^\top + Q` (not in a constant-gain mode). ``Q``
        overrides the noise covariance for this step.
        """
        with np.errstate(all="ignore"):
            try:
                x, P = self.x, self.P
                if f is None:
                    Fk = self.F if F is None else F
                    if Fk is None:
                        raise ValueError("predict needs F (a matrix) or f (a function)")
                    x_new = Fk @ x
                    B = self.B if B is None else np.atleast_2d(B)
                    if B is not None and u is not None:
                        x_new = x_new + B @ np.atleast_1d(u)
                else:
                    x_new = np.atleast_1d(np.asarray(f(x, u), dtype=float))
                if self.gain is None:
                    if f is not None:
                        Fk = (F(x, u) if callable(F) else numerical_jacobian(lambda v: f(v, u), x)
                              if F is None else F)
                    Qk = self.Q if Q is None else _cov(Q, self.dim_x, "Q")
                    P = Fk @ P @ Fk.T + Qk
            except ArithmeticError as exc:
                self.diverge("model", f"predict raised {type(exc).__name__}: {exc}")
            self._accept(x_new, P, "predict")
        return self.x

    def update(self, z: Any, H: Matrix = None, R: Any = None, *,
               h: Callable[[np.ndarray], Any] | None = None, s: Sequence[float] | float | None = None
               ) -> np.ndarray:
        r"""Measurement update with ``z``; returns the a-posteriori state.

        Linear (``h`` is ``None``): :math:`\hat z = H x`. Extended: :math:`\hat z = h(x)`
        and ``H`` is the Jacobian of ``h`` at the a-priori ``x``: a matrix, a function
        ``H(x)``, or ``None`` for :func:`numerical_jacobian`. ``R`` overrides the
        measurement noise for this step; ``s`` is the scheduling point of a
        :class:`GainSchedule` (a number or one value per grid axis).
        """
        z = np.atleast_1d(np.asarray(z, dtype=float))
        Rk = self.R if R is None else _cov(R, self.dim_z, "R")
        with np.errstate(all="ignore"):
            try:
                x, P = self.x, self.P
                if h is None:
                    Hk = self.H if H is None else np.atleast_2d(H)
                    if Hk is None:
                        raise ValueError("update needs H (a matrix) or h (a function)")
                    z_hat = Hk @ x
                else:
                    z_hat = np.atleast_1d(np.asarray(h(x), dtype=float))
                    Hk = (np.atleast_2d(H(x)) if callable(H) else numerical_jacobian(h, x)
                          if H is None else np.atleast_2d(H))
                y = z - z_hat
                PHT = P @ Hk.T
                S = Hk @ PHT + Rk
                SI = np.linalg.inv(S)
                if self.gain is None:
                    K = PHT @ SI
                elif isinstance(self.gain, GainSchedule):
                    if s is None:
                        raise ValueError("a scheduled gain needs the scheduling point s")
                    K = self.gain(*np.atleast_1d(np.asarray(s, dtype=float)).tolist())
                else:
                    K = self.gain
                x_new = x + K @ y
                if self.gain is None:
                    I_KH = self._I - K @ Hk
                    P = I_KH @ P @ I_KH.T + K @ Rk @ K.T
                nis = float(y @ SI @ y)
            except ArithmeticError as exc:
                self.diverge("model", f"update raised {type(exc).__name__}: {exc}")
            except np.linalg.LinAlgError as exc:
                self.diverge("singular", f"innovation covariance S is singular ({exc})")
            if not (math.isfinite(nis) and np.isfinite(K).all()):
                self.diverge("nonfinite", "non-finite gain or innovation in update")
            self._accept(x_new, P, "update")
        self.K, self.y, self.S, self.nis = K, y, S, nis
        self._log_likelihood = None
        self.updates += 1
        if self.nis_window > 0:
            self._nis_run = self._nis_run + 1 if nis > self.nis_threshold else 0
            if self._nis_run >= self.nis_window:
                self.diverge("nis", f"NIS above {self.nis_threshold:.4g} (chi-square {self.dim_z} "
                                     f"dof, p = {self.nis_gate:g}) in {self.nis_window} "
                                     f"consecutive updates, last {nis:.4g}")
        return self.x

    # -- guards ------------------------------------------------------------------------
    def _accept(self, x: np.ndarray, P: np.ndarray, stage: str) -> None:
        """Check, constrain and store a step's result, or reset and raise."""
        if not np.isfinite(x).all():
            self.diverge("nonfinite", f"non-finite state after {stage}: {x.tolist()}")
        if P is not self.P:
            if not np.isfinite(P).all():
                self.diverge("nonfinite", f"non-finite covariance after {stage}")
            P = self._guard(P)
        if self.constraint is not None:
            x = np.asarray(self.constraint(x), dtype=float)
        self.x, self.P = x, P
        self.fresh = False

    def _guard(self, P: np.ndarray) -> np.ndarray:
        r"""Symmetrise :math:`P` and lift eigenvalues below the floor
        :math:`\max(\text{eig\_floor}, \text{EIG\_FLOOR\_REL}\,\lambda_\max)`."""
        P = 0.5 * (P + P.T)
        w = np.linalg.eigvalsh(P)
        floor = max(self.eig_floor, EIG_FLOOR_REL * w[-1])
        if w[0] < floor:
            w, V = np.linalg.eigh(P)
            P = (V * np.maximum(w, floor)) @ V.T
            P = 0.5 * (P + P.T)
            self.guard_count += 1
        return P

    def reset(self, reason: str = "reset requested") -> None:
        """Return to ``x0``/``P0``, count the reset and keep ``reason`` as ``last_reset_reason``."""
        self._start()
        self.resets += 1
        self.last_reset_reason = reason

    def diverge(self, kind: str, reason: str) -> None:
        """Reset, log the reason (a warning when its kind changes) and raise :class:`Diverged`."""
        self.reset(reason)
        level = logging.WARNING if kind != self._last_kind else logging.DEBUG
        self._last_kind = kind
        log.log(level, "%s diverged, reset to x0/P0 (reset %d): %s", self.name, self.resets, reason)
        raise Diverged(reason)


# -- models -----------------------------------------------------------------------------
#: explicit Runge-Kutta schemes whose stages each use only the previous one:
#: (nodes c, weights b) with stage i evaluated at x + c_i h k_{i-1}
_SCHEMES = {
    "euler": ((0.0,), (1.0,)),
    "rk4": ((0.0, 0.5, 0.5, 1.0), (1 / 6, 1 / 3, 1 / 3, 1 / 6)),
}


@dataclass
class Model:
    r"""A nonlinear state-space model in python-control's style, for the extended filter.

    .. math:: \dot x = f(t, x, u, p) \ \text{(continuous, dt = 0)} \quad\text{or}\quad
              x_{k+1} = f(t, x_k, u_k, p) \ \text{(discrete, dt > 0)}, \qquad
              z = h(t, x, u, p)

    Parameters
    ----------
    states, inputs, outputs:
        Names of the entries of ``x``, ``u`` and ``h(...)``.
    f, h:
        ``f(t, x, u, params)`` and ``h(t, x, u, params)`` with 1-D arrays ``x``, ``u``.
    F, H:
        Optional analytic Jacobians :math:`\partial f/\partial x` and
        :math:`\partial h/\partial x`, same signature; otherwise central differences.
    params:
        Passed to every call (the observer's own, deliberately imperfect, parameters).
    dt:
        0 for a continuous model, integrated over each step by ``method``; > 0 for a
        discrete one, whose ``f`` is applied once per step.
    method:
        ``"rk4"`` (classic Runge-Kutta) or ``"euler"``, for a continuous model.
    max_step:
        Longest integration sub-step, s (``None``: one step per call).
    units:
        Unit of each state or output by name (shown on the observer's channels).

    Notes
    -----
    For a continuous model with analytic ``F`` the Jacobian of the discrete step is
    propagated exactly through the scheme's stages
    (:math:`\partial k_i/\partial x = A(\xi_i)(I + c_i h\, \partial k_{i-1}/\partial x)`,
    :math:`\Phi = I + h \sum_i b_i\, \partial k_i/\partial x`; for Euler,
    :math:`\Phi = I + h A`).
    """

    states: Sequence[str]
    inputs: Sequence[str]
    outputs: Sequence[str]
    f: Callable[..., Any]
    h: Callable[..., Any]
    F: Callable[..., Any] | None = None
    H: Callable[..., Any] | None = None
    params: Mapping[str, Any] = field(default_factory=dict)
    dt: float = 0.0
    method: str = "rk4"
    max_step: float | None = None
    units: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.method not in _SCHEMES:
            raise ValueError(f"method must be one of {', '.join(_SCHEMES)}, got {self.method!r}")
        self.states, self.inputs, self.outputs = (tuple(self.states), tuple(self.inputs),
                                                  tuple(self.outputs))

    def step(self, t: float, x: np.ndarray, u: np.ndarray, dt: float, jacobian: bool = False
             ) -> tuple[np.ndarray, np.ndarray | None]:
        """State after one step of ``dt`` from ``(t, x)`` with ``u`` held, and its Jacobian
        (analytic if ``F`` is given, else numerical) when ``jacobian`` is true."""
        p = self.params
        if self.dt > 0:
            x_new = np.atleast_1d(np.asarray(self.f(t, x, u, p), dtype=float))
            if not jacobian:
                return x_new, None
            if self.F is not None:
                return x_new, np.atleast_2d(self.F(t, x, u, p))
            return x_new, numerical_jacobian(lambda v: self.f(t, v, u, p), x)
        if jacobian and self.F is None:
            return self.step(t, x, u, dt)[0], numerical_jacobian(lambda v: self.step(t, v, u, dt)[0], x)
        n = 1 if not self.max_step else max(1, math.ceil(dt / self.max_step - 1e-9))
        hs = dt / n
        nodes, weights = _SCHEMES[self.method]
        eye = np.eye(x.size)
        Phi = eye if jacobian else None
        for i in range(n):
            ti = t + i * hs
            k = dk = 0.0
            incr = np.zeros_like(x, dtype=float)
            dincr = 0.0
            for c, b in zip(nodes, weights):
                xi = x + c * hs * k
                k = np.asarray(self.f(ti + c * hs, xi, u, p), dtype=float)
                incr = incr + b * k
                if jacobian:
                    dk = np.atleast_2d(self.F(ti + c * hs, xi, u, p)) @ (eye + c * hs * dk)
                    dincr = dincr + b * dk
            x = x + hs * incr
            if jacobian:
                Phi = (eye + hs * dincr) @ Phi
        return x, Phi

    def output(self, t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Predicted outputs ``h(t, x, u, params)``."""
        return np.atleast_1d(np.asarray(self.h(t, x, u, self.params), dtype=float))

    def output_jacobian(self, t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """:math:`\\partial h/\\partial x`, analytic if ``H`` is given, else numerical."""
        if self.H is not None:
            return np.atleast_2d(np.asarray(self.H(t, x, u, self.params), dtype=float))
        return numerical_jacobian(lambda v: self.output(t, v, u), x)

    def transition(self, t: float, dt: float) -> tuple[Callable, Callable]:
        """``(f, F)`` for :meth:`KalmanCore.predict` over ``[t, t + dt]``: ``f(x, u)`` and ``F(x, u)``."""
        return (lambda x, u: self.step(t, x, u, dt)[0],
                lambda x, u: self.step(t, x, u, dt, jacobian=True)[1])

    def measurement(self, t: float, u: np.ndarray, rows: Sequence[int] | None = None
                    ) -> tuple[Callable, Callable]:
        """``(h, H)`` for :meth:`KalmanCore.update` at ``t`` with inputs ``u``: ``h(x)``, ``H(x)``,
        restricted to the output ``rows`` that are measured (all by default)."""
        sel = slice(None) if rows is None else list(rows)
        return (lambda x: self.output(t, x, u)[sel],
                lambda x: self.output_jacobian(t, x, u)[sel])


__all__ = ["Diverged", "GainSchedule", "KalmanCore", "Model", "bounds", "numerical_jacobian",
           "steady_state_gain"]
