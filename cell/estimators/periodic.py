r"""The periodic-input observer of seed 001: a state and the Fourier coefficients of its input.

The system (seed 001, eq. 1) is driven by an unknown :math:`T_0`-periodic input written as a
finite Fourier series over :math:`h` harmonics,

.. math:: \dot x = A x + A_0 w, \quad y = C x, \quad
          w(\alpha) = \sum_{k=-h}^{h} c_k e^{i k \omega_0 \alpha},

and the observer (eq. 4) is the Luenberger filter with adaptation laws for the coefficients,

.. math:: \dot{\hat x} = A\hat x + A_0 \hat w - L(C\hat x - y), \qquad
          \dot{\hat c}_k = -e^{-ik\omega_0\alpha} L_k (C\hat x - y), \quad k = 0..h,

with :math:`\hat c_{-k} = \bar{\hat c}_k` (a real input). The independent variable
:math:`\alpha` is the crank angle in radians: engine signals are periodic in angle, so
:math:`\omega_0` is a constant (:math:`2\pi/4\pi` = 0.5 for one 720 deg cycle).

Gain designs (:func:`design_full`, :func:`design_partial`):

- *full measurement* (:math:`p = n`, eqs. 6-8): :math:`L = (A - \tilde L) C^{-1}`,
  :math:`L_k = \alpha_k^2 A_0^\dagger P C^{-1}` with :math:`P \tilde L + \tilde L^\dagger P =
  -I` solved by :func:`scipy.linalg.solve_continuous_lyapunov`;
- *partial measurement* (:math:`p < n`, eq. 9): :math:`L` given (:math:`A - LC` stable) and
  :math:`L_k = \epsilon \beta_k^2 P_k^\dagger`, :math:`P_k = C (ik\omega_0 - (A - LC))^{-1}
  A_0`. Averaging the coefficient errors over a period gives :math:`\dot{\tilde c}_k \approx
  -\epsilon \beta_k^2 P_k^\dagger P_k \tilde c_k`, which converges for this sign (the paper
  prints a leading minus that, with its eq. 4, would diverge). The paper's rod section
  writes a per-harmonic :math:`\beta_k`; we take :math:`\beta_k^2 = \beta^2 \omega_0 /
  \|P_k\|^2`, so that with :math:`\epsilon` = 0.1 and :math:`\beta^2` = 1 each
  coefficient's averaged error decays at the rate 0.1 per radian of the fundamental's phase
  (:math:`\omega_0\alpha`), whatever the units of the model.

*Coefficient banks.* A signal made of one pulse per cylinder (the crank speed) is described
per cylinder: ``banks`` sets of coefficients over the firing period, the set of cylinder
``i`` being the one used and adapted while cylinder ``i`` fires (``bank(j)``). The
coefficients :math:`c_{k,i}` of seed 001's balance energy :math:`V_i` are those of bank
``i``. With one bank this is eq. 4 as printed.

The implementation is discrete in angle, one step per sample (6 deg, like the paper's). The
state :math:`\hat x` is kept half a sample before each sample; over the interval centred on
sample ``j``, with :math:`y_j` and :math:`\hat w(\alpha_j)` held, it is advanced exactly
(matrix exponential of :math:`A - LC`), and :math:`\hat c_k` by one Euler step on the
innovation at the sample, :math:`C(\hat x_{j-1/2} + \hat x_{j+1/2})/2 - y_j`. The observer
is then a linear periodically time-varying system in the real state
:math:`z = (\hat x, \hat c_0, \Re\hat c_1, \Im\hat c_1, \dots)`,
:math:`z_{j+1} = M_j z_j + N_j y_j`, and :class:`PeriodicObserver` precomputes, per start
angle and run length, the products over a frame's samples: a frame of ``n`` samples costs
two small matrix products (vectorised per frame, no per-sample Python loop).
:class:`Cascade` chains observers whose reconstructed input feeds the next one's
measurement (seed 001, Figure 2) into one such system.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm, solve_continuous_lyapunov


def _mat(a, rows: int | None = None) -> np.ndarray:
    m = np.atleast_2d(np.asarray(a, dtype=float))
    if rows is not None and m.shape[0] != rows and m.shape[1] == rows and m.shape[0] == 1:
        m = m.T
    return m


@dataclass(frozen=True)
class Gains:
    """Observer gains: ``L`` (n x p) and ``Lk[k]`` (m x p, complex) for k = 0..h."""

    L: np.ndarray
    Lk: tuple[np.ndarray, ...]


def design_full(A, A0, C, Ltilde, alpha2: Sequence[float]) -> Gains:
    """Full-measurement gains, seed 001 eqs. 6-8.

    Parameters
    ----------
    A, A0, C:
        The model (``C`` square and invertible: every state measured).
    Ltilde:
        The asymptotically stable matrix :math:`\\tilde L` (n x n) the error follows.
    alpha2:
        :math:`\\alpha_k^2` for k = 0..h (all nonzero).
    """
    A, C, Lt = _mat(A), _mat(C), _mat(Ltilde)
    A0 = _mat(A0, A.shape[0])
    n = A.shape[0]
    if C.shape != (n, n):
        raise ValueError(f"full measurement needs C square ({n}x{n}), got {C.shape[0]}x{C.shape[1]}")
    if np.any(np.linalg.eigvals(Lt).real >= 0):
        raise ValueError("Ltilde must be asymptotically stable")
    if any(not a != 0 for a in alpha2):
        raise ValueError("every alpha_k^2 must be nonzero")
    Ci = np.linalg.inv(C)
    P = solve_continuous_lyapunov(Lt.T, -np.eye(n))  # P Lt + Lt^T P = -I (eq. 8)
    L = (A - Lt) @ Ci  # eq. 6
    Lk = tuple((a * A0.T @ P @ Ci).astype(complex) for a in alpha2)  # eq. 7
    return Gains(L, Lk)


def design_partial(A, A0, C, L, omega0: float, h: int, eps: float = 0.1, beta2: float = 1.0,
                   normalise: bool = True) -> Gains:
    """Partial-measurement gains, seed 001 eq. 9 (see the module docstring for
    :math:`\\beta_k`); ``normalise=False`` uses :math:`\\beta_k = \\beta` as printed."""
    A, C = _mat(A), _mat(C)
    A0, L = _mat(A0, A.shape[0]), _mat(L, A.shape[0])
    Acl = A - L @ C
    if np.any(np.linalg.eigvals(Acl).real >= 0):
        raise ValueError("A - L C must be asymptotically stable")
    n = A.shape[0]
    Lk = []
    for k in range(h + 1):
        Pk = C @ np.linalg.solve(1j * k * omega0 * np.eye(n) - Acl, A0)  # p x m
        if np.linalg.matrix_rank(Pk) < min(Pk.shape):
            raise ValueError(f"P_{k} is not full rank: harmonic {k} is not observable")
        b2 = beta2 * omega0 / np.linalg.norm(Pk, 2) ** 2 if normalise else beta2
        Lk.append(eps * b2 * Pk.conj().T)
    return Gains(L, tuple(Lk))


class PeriodicObserver:
    """One periodic-input observer (seed 001, eq. 4), discrete in angle.

    Parameters
    ----------
    A, A0, C:
        The model (n x n, n x m, p x n).
    h:
        Harmonics estimated (k = 0..h).
    omega0:
        Fundamental, rad per unit of angle (0.5 for a 720 deg period in radians).
    gains:
        From :func:`design_full` or :func:`design_partial`.
    step:
        Sample angle (radians); the period :math:`2\\pi/\\omega_0` must be a whole number of
        steps.
    banks, bank, cycle:
        Coefficient banks (module docstring): ``bank(j)`` is the bank active at angle index
        ``j``, periodic over ``cycle`` steps (a multiple of the Fourier period).

    The real state is ``z = (x, bank 0: c0, Re c1, Im c1, ..., Re ch, Im ch, bank 1: ...)``;
    :meth:`w_row` reconstructs :math:`\\hat w` from it at an angle index.
    """

    def __init__(self, A, A0, C, h: int, omega0: float, gains: Gains, step: float,
                 banks: int = 1, bank=None, cycle: int | None = None) -> None:
        self.A, self.C = _mat(A), _mat(C)
        self.A0 = _mat(A0, self.A.shape[0])
        self.n, self.m = self.A0.shape
        self.p = self.C.shape[0]
        self.h, self.omega0, self.step, self.gains = int(h), float(omega0), float(step), gains
        period = 2.0 * math.pi / self.omega0 / self.step
        if abs(period - round(period)) > 1e-6:
            raise ValueError(f"the period 2 pi / omega0 is {period:g} steps, not a whole number")
        self.fourier_period = int(round(period))
        self.period = int(cycle or self.fourier_period)
        if self.period % self.fourier_period:
            raise ValueError(f"cycle {self.period} is not a multiple of the Fourier period "
                             f"{self.fourier_period} steps")
        self.banks = int(banks)
        self._bank = bank or (lambda j: 0)
        self.nc_bank = self.m * (2 * self.h + 1)
        self.nc = self.banks * self.nc_bank
        self.d = self.n + self.nc
        Acl = self.A - gains.L @ self.C
        big = np.zeros((2 * self.n, 2 * self.n))
        big[:self.n, :self.n] = Acl * self.step
        big[:self.n, self.n:] = np.eye(self.n) * self.step
        e = expm(big)
        self._phi, self._gam = e[:self.n, :self.n], e[:self.n, self.n:]
        self._M, self._N, self._W = self._tables()

    # -- the linear periodic system ---------------------------------------------------------
    def angle(self, j: int) -> float:
        return (j % self.fourier_period) * self.step

    def bank_of(self, j: int) -> int:
        """The coefficient bank active at angle index ``j``."""
        return int(self._bank(j % self.period))

    def w_row(self, j: int) -> np.ndarray:
        """The m x d matrix giving :math:`\\hat w` at angle index ``j`` from ``z``."""
        m, a = self.m, self.angle(j)
        off = self.n + self.bank_of(j) * self.nc_bank
        W = np.zeros((m, self.d))
        W[:, off:off + m] = np.eye(m)
        for k in range(1, self.h + 1):
            base = off + m * (2 * k - 1)
            W[:, base:base + m] = 2.0 * math.cos(k * self.omega0 * a) * np.eye(m)
            W[:, base + m:base + 2 * m] = -2.0 * math.sin(k * self.omega0 * a) * np.eye(m)
        return W

    def _tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``M``, ``N`` and ``W`` at every angle index of the period, computed for all of them at
        once (stacked products with the same association as one angle at a time, so the same
        numbers as the per-angle construction, bit for bit)."""
        n, m, p, d, D, P_ = self.n, self.m, self.p, self.d, self.step, self.period
        L, h, w0 = self.gains.L, self.h, self.omega0
        idx = np.arange(P_)
        angles = [self.angle(j) for j in range(P_)]
        banks = np.array([self.bank_of(j) for j in range(P_)])
        eye_m = np.eye(m)
        # W: c0 and (Re, Im) of each harmonic of the active bank, as w_row builds it
        W = np.zeros((P_, m, d))
        off = self.n + banks * self.nc_bank
        cols = off[:, None] + np.arange(m)[None, :]
        W[idx[:, None, None], np.arange(m)[None, :, None], cols[:, None, :]] = eye_m
        for k in range(1, h + 1):
            cs = np.array([2.0 * math.cos(k * w0 * a) for a in angles])
            sn = np.array([-2.0 * math.sin(k * w0 * a) for a in angles])
            base = off + m * (2 * k - 1)
            blk = np.arange(m)
            W[idx[:, None, None], blk[None, :, None], (base[:, None] + blk)[:, None, :]] = \
                cs[:, None, None] * eye_m
            W[idx[:, None, None], blk[None, :, None], (base[:, None] + m + blk)[:, None, :]] = \
                sn[:, None, None] * eye_m
        Wc = W.copy()
        Wc[:, :, :n] = 0.0
        M = np.zeros((P_, d, d))
        N = np.zeros((P_, d, p))
        # x is held half a sample early: x+ = phi x + gam (A0 w(a_j) + L y_j) spans the
        # interval centred on the sample (no half-sample lag of y or w)
        M[:, :n, :n] = self._phi
        M[:, :n, :] += np.matmul(self._gam @ self.A0, Wc)
        N[:, :n, :] = self._gam @ L
        # the innovation at the sample: C (x + x+) / 2 - y; c+ = c - D G(a) innovation
        G = np.zeros((P_, self.nc, p))
        bank_rows = banks * self.nc_bank
        rows0 = bank_rows[:, None] + np.arange(m)[None, :]
        G[idx[:, None], rows0] = self.gains.Lk[0].real
        a_arr = np.array(angles)
        for k in range(1, h + 1):
            ek = np.exp(-1j * k * w0 * a_arr)[:, None, None] * self.gains.Lk[k]
            base = bank_rows + m * (2 * k - 1)
            G[idx[:, None], base[:, None] + np.arange(m)[None, :]] = ek.real
            G[idx[:, None], base[:, None] + m + np.arange(m)[None, :]] = ek.imag
        Ex = 0.5 * self.C @ (np.eye(n) + self._phi)  # innovation from x
        Ec = np.matmul(0.5 * self.C @ self._gam @ self.A0, Wc[:, :, n:])  # ... from c
        Ey = 0.5 * self.C @ self._gam @ L - np.eye(p)  # ... from y
        M[:, n:, :n] = np.matmul(-D * G, Ex)
        M[:, n:, n:] = np.eye(self.nc) - np.matmul(D * G, Ec)
        N[:, n:, :] = np.matmul(-D * G, Ey)
        return M, N, W

    def transition(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """``(M_j, N_j)``: :math:`z_{j+1} = M_j z_j + N_j y_j` at angle index ``j``."""
        j %= self.period
        return self._M[j], self._N[j]

    def monodromy_radius(self) -> float:
        """Spectral radius of the map over one period: < 1 means the observer converges."""
        F = np.eye(self.d)
        for j in range(self.period):
            F = self._M[j] @ F
        return float(np.max(np.abs(np.linalg.eigvals(F))))

    def coefficients(self, z: np.ndarray, bank: int = 0) -> np.ndarray:
        """:math:`\\hat c_k` for k = 0..h (complex, shape (h+1, m)) of a bank, from ``z``."""
        n, m = self.n + bank * self.nc_bank, self.m
        c = np.zeros((self.h + 1, m), dtype=complex)
        c[0] = z[n:n + m]
        for k in range(1, self.h + 1):
            base = n + m * (2 * k - 1)
            c[k] = z[base:base + m] + 1j * z[base + m:base + 2 * m]
        return c

    def initial(self, y0: float | np.ndarray = 0.0) -> np.ndarray:
        """A starting state at a steady measurement ``y0``: x at the steady state and
        :math:`c_0` the input that holds it (a scalar ``y0`` for p = 1)."""
        z = np.zeros(self.d)
        y0 = np.atleast_1d(np.asarray(y0, dtype=float))
        x, *_ = np.linalg.lstsq(self.C, y0, rcond=None)
        z[:self.n] = x
        w, *_ = np.linalg.lstsq(self.A0, -self.A @ x, rcond=None)
        for b in range(self.banks):
            off = self.n + b * self.nc_bank
            z[off:off + self.m] = w
        return z


class LinearPeriodic:
    """A linear periodic system in the observers' form, with per-frame products cached.

    ``M[j]``, ``N[j]`` (the transition at angle index ``j``) and ``O[j]``, ``P[j]`` (outputs
    ``o_j = O_j z_j + P_j y_j`` at that sample, before the transition). :meth:`run` takes the
    ``n`` samples of a frame and returns the state after them and the ``n`` output rows, with
    one matrix product of ``[[F, G], [H, J]]`` by ``(z, y)``; the products for each (start
    index, n) are computed once.
    """

    def __init__(self, M: np.ndarray, N: np.ndarray, O: np.ndarray, P: np.ndarray) -> None:  # noqa: E741
        self.M, self.N, self.O, self.P = M, N, O, P
        self.period, self.d = M.shape[0], M.shape[1]
        self.p, self.q = N.shape[2], O.shape[1]
        self._cache: dict[tuple[int, int], tuple[np.ndarray, ...]] = {}
        self._stacked: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def frame(self, j: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        key = (j % self.period, n)
        got = self._cache.get(key)
        if got is not None:
            return got
        d, p, q = self.d, self.p, self.q
        F = np.eye(d)
        G = np.zeros((d, n * p))
        H = np.zeros((n * q, d))
        J = np.zeros((n * q, n * p))
        for i in range(n):
            jj = (j + i) % self.period
            H[i * q:(i + 1) * q] = self.O[jj] @ F
            J[i * q:(i + 1) * q] = self.O[jj] @ G
            J[i * q:(i + 1) * q, i * p:(i + 1) * p] += self.P[jj]
            F, G = self.M[jj] @ F, self.M[jj] @ G
            G[:, i * p:(i + 1) * p] += self.N[jj]
        got = self._cache[key] = (F, G, H, J)
        return got

    def run(self, z: np.ndarray, j: int, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """State after the samples ``y`` (shape (n, p) or (n,)) from angle index ``j``, and the
        outputs at each sample (shape (n, q))."""
        n = len(y)
        got = self._stacked.get((j % self.period, n))
        if got is None:
            F, G, H, J = self.frame(j, n)
            got = self._stacked[(j % self.period, n)] = (np.block([[F, G], [H, J]]),
                                                          np.empty(self.d + n * self.p))
        S, buf = got
        buf[:self.d] = z
        buf[self.d:] = np.ravel(y)
        v = S @ buf
        return v[:self.d], v[self.d:].reshape(n, self.q)


def single(obs: PeriodicObserver) -> LinearPeriodic:
    """One observer as a :class:`LinearPeriodic` whose outputs are (:math:`\\hat w`, :math:`C\\hat x`)."""
    O = np.concatenate([obs._W, np.broadcast_to(np.hstack([obs.C, np.zeros((obs.p, obs.nc))]),  # noqa: E741
                                                (obs.period, obs.p, obs.d))], axis=1)
    return LinearPeriodic(obs._M, obs._N, O, np.zeros((obs.period, O.shape[1], obs.p)))


def cascade(first: PeriodicObserver, second: PeriodicObserver) -> LinearPeriodic:
    """Two observers in series (seed 001, Figure 2): the first's reconstructed input
    :math:`\\hat w_1` is the second's measurement. Outputs: (:math:`\\hat w_2`,
    :math:`\\hat w_1`, :math:`C_1 \\hat x_1`)."""
    if first.period != second.period or first.m != second.p:
        raise ValueError("a cascade needs one period and the first input as the second output")
    P_, d1, d2 = first.period, first.d, second.d
    M = np.zeros((P_, d1 + d2, d1 + d2))
    N = np.zeros((P_, d1 + d2, first.p))
    M[:, :d1, :d1] = first._M
    N[:, :d1] = first._N
    M[:, d1:, d1:] = second._M
    M[:, d1:, :d1] = second._N @ first._W  # y2_j = w1(z1_j)
    q = second.m + first.m + first.p
    O = np.zeros((P_, q, d1 + d2))  # noqa: E741
    O[:, :second.m, d1:] = second._W
    O[:, second.m:second.m + first.m, :d1] = first._W
    O[:, second.m + first.m:, :first.n] = first.C
    return LinearPeriodic(M, N, O, np.zeros((P_, q, first.p)))


__all__ = ["Gains", "LinearPeriodic", "PeriodicObserver", "cascade", "design_full",
           "design_partial", "single"]
