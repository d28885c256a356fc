"""The Kalman core against independent references: filterpy, closed forms and scipy's DARE."""

import logging
import math

import numpy as np
import pytest
import scipy.linalg
from filterpy.kalman import ExtendedKalmanFilter, KalmanFilter

from cell.estimators.core import (
    Diverged,
    GainSchedule,
    KalmanCore,
    Model,
    bounds,
    numerical_jacobian,
    steady_state_gain,
)

TOL = dict(rtol=1e-9, atol=1e-9)
TOL_APPROX = dict(rel=1e-9, abs=1e-9)


def assert_same(ours, ref, update=False):
    """x and P (and after an update K, y, S, log-likelihood) agree with filterpy's to 1e-9."""
    np.testing.assert_allclose(ours.x, ref.x.ravel(), **TOL)
    np.testing.assert_allclose(ours.P, ref.P, **TOL)
    if update:
        np.testing.assert_allclose(ours.K, ref.K, **TOL)
        np.testing.assert_allclose(ours.y, ref.y.ravel(), **TOL)
        np.testing.assert_allclose(ours.S, ref.S, **TOL)
        assert ours.log_likelihood == pytest.approx(float(np.squeeze(ref.log_likelihood)), **TOL_APPROX)
        assert ours.nis == pytest.approx((ref.y.T @ np.linalg.inv(ref.S) @ ref.y).item(), rel=1e-9)


# -- filterpy ---------------------------------------------------------------------------
def test_linear_filter_matches_filterpy_kalman_filter():
    """Constant-acceleration model, 3 states, 2 measurements, an input; 1000 steps."""
    rng = np.random.default_rng(1)
    dt = 0.1
    F = np.array([[1, dt, dt * dt / 2], [0, 1, dt], [0, 0, 1]])
    B = np.array([[0.0], [dt], [0.0]])
    H = np.array([[1.0, 0, 0], [0, 1.0, 0]])
    Q = np.diag([1e-4, 1e-3, 1e-2])
    R = np.array([[0.5, 0.1], [0.1, 0.3]])
    x0, P0 = np.array([1.0, -0.5, 0.2]), np.diag([2.0, 1.0, 0.5])

    ref = KalmanFilter(dim_x=3, dim_z=2, dim_u=1)
    ref.x, ref.P, ref.F, ref.B, ref.H, ref.Q, ref.R = x0[:, None], P0, F, B, H, Q, R
    ours = KalmanCore(x0, P0, Q, R, F=F, B=B, H=H)

    truth = np.zeros(3)
    for _ in range(1000):
        u = rng.normal(size=1)
        truth = F @ truth + B @ u + rng.multivariate_normal(np.zeros(3), Q)
        z = H @ truth + rng.multivariate_normal(np.zeros(2), R)
        ref.predict(u=u[:, None])
        ours.predict(u)
        assert_same(ours, ref)
        ref.update(z[:, None])
        ours.update(z)
        assert_same(ours, ref, update=True)
    assert ours.guard_count == 0 and ours.resets == 0


# A damped pendulum, Euler-discretised, with the bob's position as the measurement.
G_L, DAMP, L, DT = 9.81, 0.3, 1.5, 0.02


def pend_f(x, u):
    th, om = x
    return np.array([th + DT * om, om + DT * (-G_L * math.sin(th) - DAMP * om + u)])


def pend_F(x, u):
    return np.array([[1.0, DT], [-DT * G_L * math.cos(x[0]), 1.0 - DT * DAMP]])


def pend_h(x):
    return np.array([L * math.sin(x[0]), -L * math.cos(x[0])])


def pend_H(x):
    return np.array([[L * math.cos(x[0]), 0.0], [L * math.sin(x[0]), 0.0]])


def test_extended_filter_matches_filterpy_ekf_on_a_pendulum():
    rng = np.random.default_rng(2)
    Q, R = np.diag([1e-5, 1e-3]), np.diag([0.02, 0.01])
    x0, P0 = np.array([0.3, 0.0]), np.diag([0.5, 0.5])

    class Pendulum(ExtendedKalmanFilter):
        def predict_x(self, u=0):
            self.x = pend_f(self.x.ravel(), u)[:, None]

    ref = Pendulum(dim_x=2, dim_z=2)
    ref.x, ref.P, ref.Q, ref.R = x0[:, None].copy(), P0.copy(), Q, R
    ours = KalmanCore(x0, P0, Q, R)

    truth = np.array([1.2, 0.0])
    for k in range(1000):
        u = 2.0 * math.sin(0.05 * k)
        truth = pend_f(truth, u) + rng.multivariate_normal(np.zeros(2), Q)
        z = pend_h(truth) + rng.multivariate_normal(np.zeros(2), R)
        ref.F = pend_F(ref.x.ravel(), u)
        ref.predict(u)
        ours.predict(u, f=pend_f, F=pend_F)
        assert_same(ours, ref)
        ref.update(z[:, None], lambda x: pend_H(x.ravel()), lambda x: pend_h(x.ravel())[:, None])
        ours.update(z, h=pend_h, H=pend_H)
        assert_same(ours, ref, update=True)
    # the filter tracks the true pendulum, not only filterpy
    assert abs(ours.x[0] - truth[0]) < 0.1


def test_numerical_jacobians_agree_with_analytic_ones():
    for x in ([0.3, -1.0], [2.5, 4.0], [-1e-3, 1e3]):
        x = np.array(x)
        np.testing.assert_allclose(numerical_jacobian(lambda v: pend_f(v, 0.7), x), pend_F(x, 0.7),
                                   rtol=1e-8, atol=1e-9)
        np.testing.assert_allclose(numerical_jacobian(pend_h, x), pend_H(x), rtol=1e-8, atol=1e-9)
    # and the EKF with numerical Jacobians stays within 1e-6 of the analytic one
    a = KalmanCore([0.3, 0.0], np.eye(2), np.diag([1e-5, 1e-3]), np.diag([0.02, 0.01]))
    b = KalmanCore([0.3, 0.0], np.eye(2), np.diag([1e-5, 1e-3]), np.diag([0.02, 0.01]))
    for k in range(200):
        z = pend_h(np.array([0.8 * math.cos(0.1 * k), 0.0]))
        a.predict(0.0, f=pend_f, F=pend_F)
        b.predict(0.0, f=pend_f)
        a.update(z, h=pend_h, H=pend_H)
        b.update(z, h=pend_h)
    np.testing.assert_allclose(b.x, a.x, rtol=0, atol=1e-6)
    np.testing.assert_allclose(b.P, a.P, rtol=0, atol=1e-6)


# -- steady state -----------------------------------------------------------------------
@pytest.mark.parametrize("Q,R", [(1e-6, 1e-4), (1e-3, 1e-4), (1.0, 1.0), (1e-4, 1.0)])
def test_scalar_gain_converges_to_the_closed_form(Q, R):
    P_prior = (Q + math.sqrt(Q * Q + 4 * Q * R)) / 2  # root of P^2 - Q P - Q R = 0
    K_closed = P_prior / (P_prior + R)
    kf = KalmanCore(0.0, 1.0, Q, R, F=1.0, H=1.0)
    for _ in range(5000):
        kf.predict()
        P_seen = kf.P[0, 0]
        kf.update(0.0)
    assert kf.K[0, 0] == pytest.approx(K_closed, rel=1e-9)
    assert P_seen == pytest.approx(P_prior, rel=1e-9)
    K, P = steady_state_gain(1.0, 1.0, Q, R)
    assert K[0, 0] == pytest.approx(K_closed, rel=1e-9)
    assert P[0, 0] == pytest.approx(P_prior, rel=1e-9)


def test_two_state_gain_converges_to_scipys_dare():
    dt = 0.1
    F = np.array([[1.0, dt], [0.0, 0.95]])
    H = np.array([[1.0, 0.0]])
    Q, R = np.diag([1e-3, 5e-2]), np.array([[0.4]])
    P_dare = scipy.linalg.solve_discrete_are(F.T, H.T, Q, R)  # the a-priori Riccati fixed point
    K_dare = P_dare @ H.T @ np.linalg.inv(H @ P_dare @ H.T + R)

    kf = KalmanCore([0.0, 0.0], np.eye(2) * 10, Q, R, F=F, H=H)
    for _ in range(3000):
        kf.predict()
        P_prior = kf.P
        kf.update(0.0)
    np.testing.assert_allclose(kf.K, K_dare, rtol=1e-9)
    np.testing.assert_allclose(P_prior, P_dare, rtol=1e-9)
    K, P = steady_state_gain(F, H, Q, R)
    np.testing.assert_allclose(K, K_dare, rtol=1e-12)
    np.testing.assert_allclose(P, P_dare, rtol=1e-12)


# -- covariance soundness ------------------------------------------------------------------
F2 = np.array([[1.0, 0.1], [0.0, 1.0]])
H2 = np.array([[1.0, 0.0]])
EXTREMES = (1e-12, 1e6)


def _run_and_stack(kf, n, rng, switch=None):
    """Step ``kf`` ``n`` times on random data; return the posterior covariances stacked."""
    Ps = np.empty((n, 2, 2))
    zs = rng.normal(size=n) * 1e3
    for i in range(n):
        if switch is not None and i % 500 == 0:
            switch(kf)
        kf.predict()
        kf.update(zs[i])
        Ps[i] = kf.P
    return Ps


def _assert_sound(Ps, kf):
    assert np.isfinite(Ps).all()
    assert np.array_equal(Ps, Ps.transpose(0, 2, 1)), "P is not exactly symmetric"
    eig = np.linalg.eigvalsh(Ps)
    assert (eig[:, 0] > 0).all(), f"P lost definiteness: min eigenvalue {eig[:, 0].min():g}"
    np.linalg.cholesky(Ps)  # a Cholesky factor of every P exists
    assert kf.resets == 0


@pytest.mark.parametrize("q1", EXTREMES)
@pytest.mark.parametrize("q2", EXTREMES)
@pytest.mark.parametrize("r", EXTREMES)
def test_covariance_stays_symmetric_positive_definite_at_extreme_noise(q1, q2, r):
    kf = KalmanCore([0.0, 0.0], np.eye(2), np.diag([q1, q2]), r, F=F2, H=H2)
    _assert_sound(_run_and_stack(kf, 4000, np.random.default_rng(3)), kf)


def test_covariance_stays_sound_over_1e5_steps_of_random_noise_levels():
    """10^5 steps; every 500 steps Q and R jump to log-uniform values anywhere in 1e-12..1e6."""
    rng = np.random.default_rng(4)

    def switch(kf):
        kf.Q = np.diag(10.0 ** rng.uniform(-12, 6, size=2))
        kf.R = np.atleast_2d(10.0 ** rng.uniform(-12, 6))

    kf = KalmanCore([0.0, 0.0], np.eye(2), np.eye(2), 1.0, F=F2, H=H2)
    Ps = _run_and_stack(kf, 100_000, rng, switch)
    _assert_sound(Ps, kf)


def test_guard_lifts_an_indefinite_covariance_and_counts():
    kf = KalmanCore([0.0, 0.0], np.eye(2), np.zeros((2, 2)), 1.0, F=np.eye(2), H=H2)
    kf.P = np.array([[1.0, 2.0], [2.0, 1.0]])  # eigenvalues 3 and -1
    kf.predict()
    w = np.linalg.eigvalsh(kf.P)
    assert kf.guard_count == 1
    assert w[0] > 0 and w[1] == pytest.approx(3.0)
    kf.predict()  # now sound: the guard leaves it alone
    assert kf.guard_count == 1


# -- divergence -------------------------------------------------------------------------
def test_non_finite_state_resets_logs_and_raises(caplog):
    kf = KalmanCore([1.0, 2.0], np.eye(2), np.eye(2) * 0.01, 1.0, H=H2, name="blowup")
    kf.predict(f=lambda x, u: x * 2.0)
    caplog.set_level(logging.DEBUG, logger="cell.estimators.core")
    with pytest.raises(Diverged, match="non-finite state after predict"):
        kf.predict(f=lambda x, u: x * np.inf)
    np.testing.assert_array_equal(kf.x, [1.0, 2.0])
    np.testing.assert_array_equal(kf.P, np.eye(2))
    assert kf.resets == 1 and "non-finite state" in kf.last_reset_reason
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "blowup" in warnings[0].message
    assert "non-finite state" in warnings[0].message
    # the same kind again is counted and kept, but not warned about again
    with pytest.raises(Diverged):
        kf.predict(f=lambda x, u: x * np.nan)
    assert kf.resets == 2
    assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 1
    # and the filter works on after the reset
    kf.predict(f=lambda x, u: x)
    kf.update(1.0, h=lambda x: x[:1])
    assert np.isfinite(kf.x).all()


def test_model_arithmetic_error_resets():
    kf = KalmanCore([1.0], 1.0, 0.1, 1.0)
    with pytest.raises(Diverged, match="ZeroDivisionError"):
        kf.predict(f=lambda x, u: np.array([1.0 / 0.0]))
    assert kf.resets == 1


def test_nis_gate_resets_after_n_consecutive_outliers(caplog):
    kf = KalmanCore([0.0], 1.0, 1e-4, 1.0, F=1.0, H=1.0, nis_gate=0.999, nis_window=5)
    assert kf.nis_threshold == pytest.approx(10.827566, rel=1e-6)  # chi2(1) 99.9 % quantile
    for _ in range(50):
        kf.predict()
        kf.update(0.0)
    for outliers in (4, 4):  # interrupted runs of outliers do not reset
        for _ in range(outliers):
            kf.predict()
            kf.update(10.0)
            assert kf.nis > kf.nis_threshold
        kf.predict()
        kf.update(0.0)
    assert kf.resets == 0
    with pytest.raises(Diverged, match="NIS above"):
        for _ in range(5):
            kf.predict()
            kf.update(1e4)
    assert kf.resets == 1 and kf.x[0] == 0.0 and kf.P[0, 0] == 1.0
    assert "5 consecutive updates" in kf.last_reset_reason
    assert "NIS above" in caplog.text


# -- gain modes -------------------------------------------------------------------------
def test_constant_gain_with_the_steady_state_gain_equals_the_full_filter():
    rng = np.random.default_rng(5)
    F = np.array([[1.0, 0.1], [0.0, 0.98]])
    H = np.array([[1.0, 0.0]])
    Q, R = np.diag([1e-3, 1e-2]), np.array([[0.2]])
    K_ss, P_ss = steady_state_gain(F, H, Q, R)
    full = KalmanCore([0.0, 0.0], np.eye(2), Q, R, F=F, H=H)
    const = KalmanCore([0.0, 0.0], P_ss, Q, R, F=F, H=H, gain=K_ss)
    assert const.mode == "constant" and full.mode == "full"
    diff = []
    for z in rng.normal(size=2000) + 3.0:
        for kf in (full, const):
            kf.predict()
            kf.update(z)
        diff.append(np.abs(full.x - const.x).max())
    assert max(diff[1000:]) < 1e-9  # after convergence the two are the same filter
    assert diff[0] > 1e-3  # but not before
    np.testing.assert_array_equal(const.P, P_ss)  # P is not propagated
    np.testing.assert_array_equal(const.K, K_ss)
    np.testing.assert_allclose(const.S, H @ P_ss @ H.T + R)


def test_gain_schedule_interpolates_linearly_and_clamps_on_one_axis():
    speeds = [1000.0, 2000.0, 4000.0]
    table = np.array([[[0.1]], [[0.3]], [[0.7]]])
    sched = GainSchedule(speeds, table)
    for s, k in [(1000, 0.1), (1500, 0.2), (2000, 0.3), (3000, 0.5), (3500, 0.6), (4000, 0.7),
                 (0, 0.1), (-1e9, 0.1), (9000, 0.7), (1e12, 0.7)]:
        assert sched(s)[0, 0] == pytest.approx(k, rel=1e-12), s
    with pytest.raises(ArithmeticError):
        sched(math.nan)


def test_gain_schedule_is_bilinear_and_clamps_on_two_axes():
    speed = np.array([800.0, 1500.0, 3000.0, 6000.0])
    load = np.array([0.1, 0.4, 1.0])

    def k_of(n, m):  # a bilinear function of (n, m) per entry: reproduced exactly
        return np.array([[1 + 1e-3 * n + 2 * m + 1e-3 * n * m], [0.5 - 1e-4 * n * m]])

    table = np.array([[k_of(n, m) for m in load] for n in speed])
    sched = GainSchedule((speed, load), table)
    rng = np.random.default_rng(6)
    for n, m in zip(rng.uniform(800, 6000, 50), rng.uniform(0.1, 1.0, 50)):
        # bilinear within a cell; piecewise across cells, and k_of is bilinear globally
        np.testing.assert_allclose(sched(n, m), k_of(n, m), rtol=1e-12)
    for (n, m), (cn, cm) in [((0, 0), (800, 0.1)), ((1e5, 2.0), (6000, 1.0)),
                             ((2000, -5), (2000, 0.1)), ((-1, 0.7), (800, 0.7))]:
        np.testing.assert_allclose(sched(n, m), k_of(cn, cm), rtol=1e-12)


def test_scheduled_gain_is_used_by_update():
    sched = GainSchedule([0.0, 10.0], [[[0.2]], [[0.6]]])
    kf = KalmanCore([0.0], 1.0, 0.1, 1.0, F=1.0, H=1.0, gain=sched)
    assert kf.mode == "scheduled"
    kf.predict()
    kf.update(1.0, s=5.0)
    assert kf.x[0] == pytest.approx(0.4)
    kf.update(kf.x[0] + 1.0, s=50.0)  # clamped: K = 0.6
    assert kf.x[0] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="scheduling point"):
        kf.update(1.0)


def test_gain_schedule_refuses_bad_tables():
    with pytest.raises(ValueError, match="shape"):
        GainSchedule([1.0, 2.0], np.zeros((3, 1, 1)))
    with pytest.raises(ValueError, match="increasing"):
        GainSchedule([2.0, 1.0], np.zeros((2, 1, 1)))
    with pytest.raises(ValueError, match="shape"):
        KalmanCore([0.0, 0.0], 1.0, 1.0, 1.0, gain=GainSchedule([1.0, 2.0], np.zeros((2, 1, 1))))


# -- constraint -------------------------------------------------------------------------
def test_constraint_keeps_a_state_in_bounds_after_predict_and_update():
    """An oxygen-storage-like fraction in [0, 1], pushed out by its dynamics and data."""
    kf = KalmanCore([0.5, 1.0], np.eye(2) * 0.1, np.eye(2) * 1e-3, 0.01,
                    constraint=bounds([0.0, -np.inf], [1.0, np.inf]))
    seen = []
    for k in range(300):
        z = 1.5 if (k // 50) % 2 == 0 else -0.5  # data outside [0, 1]
        kf.predict(f=lambda x, u: np.array([x[0] + 0.2 * x[1], x[1]]))
        seen.append(kf.x[0])
        kf.update(z, h=lambda x: x[:1])
        seen.append(kf.x[0])
    seen = np.array(seen)
    assert seen.min() >= 0.0 and seen.max() <= 1.0
    assert seen.min() == 0.0 and seen.max() == 1.0  # it did have to act


# -- models -----------------------------------------------------------------------------
def _pend_model(**kw):
    def f(t, x, u, p):
        return np.array([x[1], -p["g_l"] * math.sin(x[0]) - p["c"] * x[1] + u[0]])

    def F(t, x, u, p):
        return np.array([[0.0, 1.0], [-p["g_l"] * math.cos(x[0]), -p["c"]]])

    return Model(states=("theta", "omega"), inputs=("torque",), outputs=("x", "y"), f=f,
                 h=lambda t, x, u, p: pend_h(x), params={"g_l": G_L, "c": DAMP}, **kw)


def test_model_euler_step_is_the_textbook_map_with_its_jacobian():
    m = _pend_model(F=None, method="euler")
    x, u = np.array([0.4, -0.2]), np.array([0.7])
    xn, Phi = m.step(0.0, x, u, DT, jacobian=True)
    np.testing.assert_allclose(xn, pend_f(x, 0.7), rtol=1e-14)
    np.testing.assert_allclose(Phi, pend_F(x, 0.7), rtol=1e-8)


def test_model_rk4_is_accurate_and_its_propagated_jacobian_is_exact():
    lin = Model(states=("a",), inputs=(), outputs=("a",), f=lambda t, x, u, p: -2.0 * x,
                h=lambda t, x, u, p: x, F=lambda t, x, u, p: np.array([[-2.0]]), max_step=0.01)
    xn, Phi = lin.step(0.0, np.array([1.0]), np.array([]), 1.0, jacobian=True)
    assert xn[0] == pytest.approx(math.exp(-2.0), rel=1e-8)  # RK4: O(h^4) global error
    assert Phi[0, 0] == pytest.approx(xn[0], rel=1e-14)  # linear: the step's Jacobian is the step

    def f(t, x, u, p):
        return np.array([x[1], -G_L * math.sin(x[0]) - DAMP * x[1] + u[0]])

    def F(t, x, u, p):
        return np.array([[0.0, 1.0], [-G_L * math.cos(x[0]), -DAMP]])

    m = Model(states=("theta", "omega"), inputs=("torque",), outputs=("x", "y"), f=f,
              h=lambda t, x, u, p: pend_h(x), F=F, max_step=0.03)
    x, u = np.array([1.1, 0.5]), np.array([0.3])
    _, Phi = m.step(0.0, x, u, 0.1, jacobian=True)
    np.testing.assert_allclose(Phi, numerical_jacobian(lambda v: m.step(0.0, v, u, 0.1)[0], x),
                               rtol=1e-8, atol=1e-10)
    f_cl, F_cl = m.transition(0.0, 0.1)
    np.testing.assert_array_equal(f_cl(x, u), m.step(0.0, x, u, 0.1)[0])
    np.testing.assert_array_equal(F_cl(x, u), Phi)


def test_discrete_model_applies_f_once_and_measurement_selects_rows():
    m = Model(states=("a", "b"), inputs=("u",), outputs=("a", "b", "sum"), dt=0.1,
              f=lambda t, x, u, p: np.array([x[1], x[0] + u[0]]),
              h=lambda t, x, u, p: np.array([x[0], x[1], x[0] + x[1]]))
    xn, Phi = m.step(0.0, np.array([1.0, 2.0]), np.array([3.0]), 0.1, jacobian=True)
    np.testing.assert_array_equal(xn, [2.0, 4.0])
    np.testing.assert_allclose(Phi, [[0, 1], [1, 0]], atol=1e-10)
    h, H = m.measurement(0.0, np.array([0.0]), rows=[2])
    np.testing.assert_array_equal(h(np.array([1.0, 2.0])), [3.0])
    np.testing.assert_allclose(H(np.array([1.0, 2.0])), [[1.0, 1.0]], rtol=1e-9)
    with pytest.raises(ValueError, match="method"):
        Model(states=("a",), inputs=(), outputs=(), f=m.f, h=m.h, method="midpoint")


def test_core_refuses_inconsistent_shapes():
    with pytest.raises(ValueError, match="P0 must be 2x2"):
        KalmanCore([0.0, 0.0], np.eye(3), np.eye(2), 1.0)
    with pytest.raises(ValueError, match="H must have shape"):
        KalmanCore([0.0, 0.0], np.eye(2), np.eye(2), 1.0, H=[[1.0, 0.0, 0.0]])
    kf = KalmanCore([0.0, 0.0], np.eye(2), np.eye(2), 1.0)
    with pytest.raises(ValueError, match="needs F"):
        kf.predict()
    with pytest.raises(ValueError, match="needs H"):
        kf.update(1.0)
