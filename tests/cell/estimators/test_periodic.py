"""The periodic-input observer (seed 001, eqs. 4-9): gains against closed forms, convergence
against systems integrated by scipy, the per-frame products against a plain recursion."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from cell.estimators.periodic import (
    LinearPeriodic,
    PeriodicObserver,
    cascade,
    design_full,
    design_partial,
    single,
)

STEP = math.radians(6.0)


def test_full_design_of_a_first_order_lag_is_the_papers_closed_form():
    tau = 3.7  # radians of crank angle
    alpha2 = [4.0 / (k * k + 1) for k in range(4)]
    g = design_full([[-1 / tau]], [[1 / tau]], [[1.0]], [[-4 / tau]], alpha2)
    # L = (A - Lt) C^-1 = 3 / tau; P = tau / 8 solves 2 P Lt = -1; L_k = alpha_k^2 (1/tau) P
    assert g.L[0, 0] == pytest.approx(3 / tau)
    for k, a in enumerate(alpha2):
        assert g.Lk[k][0, 0] == pytest.approx(a / 8)


def test_full_design_solves_the_lyapunov_equation():
    A = np.array([[0.0, 1.0], [-4.0, -0.4]])
    A0 = np.array([[0.0], [1.0]])
    Lt = np.array([[-2.0, 0.5], [0.0, -3.0]])
    C = np.array([[2.0, 0.0], [1.0, 1.0]])
    g = design_full(A, A0, C, Lt, [1.0, 0.5])
    np.testing.assert_allclose(g.L @ C, A - Lt, atol=1e-12)  # eq. 6
    # the Lyapunov solution, by hand for this triangular Lt: vec(P) from the 4x4 system
    K = np.kron(np.eye(2), Lt.T) + np.kron(Lt.T, np.eye(2))
    Pref = np.linalg.solve(K, -np.eye(2).reshape(-1)).reshape(2, 2)
    np.testing.assert_allclose(g.Lk[0].real, A0.T @ Pref @ np.linalg.inv(C), atol=1e-12)
    np.testing.assert_allclose(g.Lk[1].real, 0.5 * A0.T @ Pref @ np.linalg.inv(C), atol=1e-12)


@pytest.mark.parametrize("bad,match", [
    (dict(Ltilde=[[0.5]]), "asymptotically stable"),
    (dict(alpha2=[1.0, 0.0]), "nonzero"),
])
def test_full_design_refuses_bad_choices(bad, match):
    kw = {"A": [[-1.0]], "A0": [[1.0]], "C": [[1.0]], "Ltilde": [[-2.0]], "alpha2": [1.0, 1.0]}
    with pytest.raises(ValueError, match=match):
        design_full(**{**kw, **bad})
    with pytest.raises(ValueError, match="C square"):
        design_full([[0, 1], [-1, -1]], [[0], [1]], [[1, 0]], [[-1, 0], [0, -1]], [1.0])


def _rod(wb=3.0, xi=0.15):
    A = np.array([[0.0, 1.0], [-wb**2, -2 * xi * wb]])
    return A, np.array([[0.0], [1.0]]), np.array([[1.0, 0.0]]), np.array([[2 * xi * wb], [2 * wb**2]])


def test_partial_design_is_eq_9_with_the_per_harmonic_beta():
    A, A0, C, L = _rod()
    g = design_partial(A, A0, C, L, 2.0, 2, eps=0.1, beta2=1.0)
    raw = design_partial(A, A0, C, L, 2.0, 2, eps=0.1, beta2=1.0, normalise=False)
    for k in range(3):
        Pk = C @ np.linalg.inv(1j * k * 2.0 * np.eye(2) - (A - L @ C)) @ A0
        np.testing.assert_allclose(raw.Lk[k], 0.1 * Pk.conj().T, atol=1e-12)
        np.testing.assert_allclose(g.Lk[k], 0.1 * 2.0 * Pk.conj().T / abs(Pk[0, 0]) ** 2, atol=1e-9)
    with pytest.raises(ValueError, match="A - L C"):
        design_partial(A, A0, C, -L, 2.0, 2)


def _fourier(a, omega0, c):
    """w(a) = c0 + 2 Re sum c_k e^{i k omega0 a}."""
    w = np.full_like(a, c[0].real, dtype=float)
    for k in range(1, len(c)):
        w += 2 * np.real(c[k] * np.exp(1j * k * omega0 * a))
    return w


def _simulate(A, A0, C, w, n, x0):
    """y at the samples of the system driven by w(a), integrated by scipy."""
    A, A0, C = map(np.atleast_2d, (A, A0, C))
    sol = solve_ivp(lambda a, x: A @ x + A0[:, 0] * w(a), (0, n * STEP), x0,
                    t_eval=np.arange(n) * STEP, rtol=1e-9, atol=1e-9, max_step=STEP / 4)
    return (C @ sol.y).T


def test_a_first_order_sensor_observer_recovers_the_input_coefficients():
    tau, omega0 = 3.0, 0.5
    c = np.array([14.7, 0.25, -0.15j, 0.1 * np.exp(1j)])
    A, A0, C = [[-1 / tau]], [[1 / tau]], [[1.0]]
    g = design_full(A, A0, C, [[-4 / tau]], [4 / (k * k + 1) for k in range(4)])
    obs = PeriodicObserver(A, A0, C, 3, omega0, g, STEP)
    assert obs.monodromy_radius() < 0.95
    n = 120 * 30
    y = _simulate(A, A0, C, lambda a: _fourier(np.array([a]), omega0, c)[0], n, [14.7])
    lp = single(obs)
    z = obs.initial(y[0, 0])
    for j in range(0, n, 4):
        z, out = lp.run(z, j, y[j:j + 4])
    est = obs.coefficients(z)[:, 0]
    # the 6 deg discretisation (input held over a sample) costs a few per cent per harmonic
    np.testing.assert_allclose(est, c, atol=0.02)


def test_the_rod_observer_recovers_a_periodic_input_through_eq_9():
    A, A0, C, L = _rod()
    omega0 = 2.0  # the firing period, 180 deg
    c = np.array([9 * 1500.0, 120.0 + 40j, -30j])
    g = design_partial(A, A0, C, L, omega0, 2)
    obs = PeriodicObserver(A, A0, C, 2, omega0, g, STEP)
    assert obs.monodromy_radius() < 0.99
    n = 30 * 60
    x0 = np.linalg.solve(A, -A0[:, 0] * c[0].real)
    y = _simulate(A, A0, C, lambda a: _fourier(np.array([a]), omega0, c)[0], n, x0)
    lp = single(obs)
    z = obs.initial(y[0, 0])
    for j in range(0, n, 4):
        z, _ = lp.run(z, j, y[j:j + 4])
    est = obs.coefficients(z)[:, 0]
    np.testing.assert_allclose(est[1:], c[1:], rtol=0.08)
    assert est[0].real == pytest.approx(c[0].real, rel=1e-3)


def test_frame_products_equal_the_sample_by_sample_recursion():
    A, A0, C, L = _rod()
    obs = PeriodicObserver(A, A0, C, 2, 2.0, design_partial(A, A0, C, L, 2.0, 2), STEP,
                           banks=4, bank=lambda j: j // 30, cycle=120)
    lp = single(obs)
    rng = np.random.default_rng(0)
    z0 = rng.normal(size=obs.d)
    for j, n in ((0, 4), (118, 4), (7, 3), (40, 1)):
        y = rng.normal(size=(n, 1))
        z, outs = z0.copy(), []
        for i in range(n):
            M, N = obs.transition(j + i)
            outs.append(obs.w_row(j + i) @ z)
            z = M @ z + N @ y[i]
        z_f, o_f = lp.run(z0, j, y)
        np.testing.assert_allclose(z_f, z, rtol=1e-10, atol=1e-9)
        np.testing.assert_allclose(o_f[:, 0], np.concatenate(outs), rtol=1e-10, atol=1e-9)


def test_banks_learn_one_pulse_per_window():
    A, A0, C, L = _rod()
    omega0 = 2.0
    amp = np.array([1.3, 0.9, 1.0, 0.7])  # each 180 deg window its own pulse height
    g = design_partial(A, A0, C, L, omega0, 2)
    obs = PeriodicObserver(A, A0, C, 2, omega0, g, STEP, banks=4, bank=lambda j: j // 30, cycle=120)
    assert obs.monodromy_radius() < 1.0

    def w(a):
        win = int((a % (4 * math.pi)) // math.pi)
        return 9000.0 + 800.0 * amp[win] * math.cos(omega0 * a)

    n = 120 * 40
    x0 = np.linalg.solve(A, -A0[:, 0] * 9000.0)
    y = _simulate(A, A0, C, w, n, x0)
    lp = single(obs)
    z = obs.initial(y[0, 0])
    for j in range(0, n, 4):
        z, _ = lp.run(z, j, y[j:j + 4])
    c1 = np.array([abs(obs.coefficients(z, b)[1, 0]) for b in range(4)])
    assert list(np.argsort(c1)) == list(np.argsort(amp))
    np.testing.assert_allclose(c1 / c1.mean(), amp / amp.mean(), atol=0.1)


def test_a_cascade_inverts_two_lags_in_series():
    omega0, t1, t2 = 0.5, 3.9, 3.1
    c = np.array([14.7, 0.5, 0.3j])
    stages = []
    for tau in (t2, t1):
        A, A0, C = [[-1 / tau]], [[1 / tau]], [[1.0]]
        g = design_full(A, A0, C, [[-4 / tau]], [4 / (k * k + 1) for k in range(3)])
        stages.append(PeriodicObserver(A, A0, C, 2, omega0, g, STEP))
    lp = cascade(*stages)
    assert isinstance(lp, LinearPeriodic)
    A2 = np.array([[-1 / t1, 0.0], [1 / t2, -1 / t2]])  # w -> x1 (tau1) -> y (tau2)
    A02, C2 = np.array([[1 / t1], [0.0]]), np.array([[0.0, 1.0]])
    n = 120 * 40
    y = _simulate(A2, A02, C2, lambda a: _fourier(np.array([a]), omega0, c)[0], n, [14.7, 14.7])
    z = np.concatenate([stages[0].initial(14.7), stages[1].initial(14.7)])
    for j in range(0, n, 4):
        z, out = lp.run(z, j, y[j:j + 4])
    est = stages[1].coefficients(z[stages[0].d:])[:, 0]
    np.testing.assert_allclose(est, c, atol=0.04)
    w_true = _fourier(np.arange(n - 4, n) * STEP, omega0, c)
    np.testing.assert_allclose(out[:, 0], w_true, atol=0.08)


def test_the_period_must_be_whole_samples():
    with pytest.raises(ValueError, match="whole number"):
        PeriodicObserver([[-1.0]], [[1.0]], [[1.0]], 1, 0.7, design_full(
            [[-1.0]], [[1.0]], [[1.0]], [[-2.0]], [1.0, 1.0]), STEP)


def _tables_one_angle_at_a_time(obs: PeriodicObserver):
    """The observer's M, N, W built angle by angle, as the discretisation in the module
    docstring reads (the plain reference of the stacked construction)."""
    n, m, p, d, D = obs.n, obs.m, obs.p, obs.d, obs.step
    L = obs.gains.L
    M, N, W = np.zeros((obs.period, d, d)), np.zeros((obs.period, d, p)), np.zeros((obs.period, m, d))
    for j in range(obs.period):
        a = obs.angle(j)
        Wj = obs.w_row(j)
        W[j] = Wj
        Wc = np.zeros((m, d))
        Wc[:, n:] = Wj[:, n:]
        M[j, :n, :n] = obs._phi
        M[j, :n, :] += obs._gam @ obs.A0 @ Wc
        N[j, :n, :] = obs._gam @ L
        G = np.zeros((obs.nc, p))
        off = obs.bank_of(j) * obs.nc_bank
        G[off:off + m] = obs.gains.Lk[0].real
        for k in range(1, obs.h + 1):
            ek = np.exp(-1j * k * obs.omega0 * a) * obs.gains.Lk[k]
            base = off + m * (2 * k - 1)
            G[base:base + m] = ek.real
            G[base + m:base + 2 * m] = ek.imag
        Ex = 0.5 * obs.C @ (np.eye(n) + obs._phi)
        Ec = 0.5 * obs.C @ obs._gam @ obs.A0 @ Wc[:, n:]
        Ey = 0.5 * obs.C @ obs._gam @ L - np.eye(p)
        M[j, n:, :n] = -D * G @ Ex
        M[j, n:, n:] = np.eye(obs.nc) - D * G @ Ec
        N[j, n:, :] = -D * G @ Ey
    return M, N, W


@pytest.mark.parametrize("which", ["uego-750", "uego-6000", "rod"])
def test_stacked_tables_are_the_angle_by_angle_ones_bit_for_bit(which):
    """The tables are built for every angle at once (a band design off the hot path in a
    fraction of the time); the numbers are the per-angle construction's, to the last bit."""
    from cell.estimators.cylinders import RodInversion, uego_design

    if which == "rod":
        observers = [RodInversion()._obs]  # four coefficient banks, two states
    else:
        observers = list(uego_design(0.025, 0.020, 3, 4.0, 4.0, float(which.split("-")[1]))[1])
    for obs in observers:
        for got, ref in zip((obs._M, obs._N, obs._W), _tables_one_angle_at_a_time(obs)):
            assert got.shape == ref.shape
            assert np.array_equal(got, ref)
