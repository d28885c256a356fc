"""Seed 002's method: the PBH check (Theorem 2, Examples 1-3), the estimation of A_q
(Approaches 1-3, eq. 9, §4.4) and the augmented model (eqs. 3-4)."""

import numpy as np
import pytest

from cell.estimators import augmentation as bias
from cell.estimators.core import Model, numerical_jacobian, steady_state_gain

C2 = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


# -- Theorem 2 and Examples 1-2 ----------------------------------------------------------
def test_example1_refused_names_column_2_and_unseen_state():
    Aq = np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0]])
    with pytest.raises(bias.AugmentationError) as exc:
        bias.pbh_check(C2, Aq)
    msg = str(exc.value)
    assert "column 2" in msg and "column 1" not in msg
    assert "x_3" in msg and "zero column" in msg


def test_example1_second_zero_made_one_is_accepted():
    bias.pbh_check(C2, np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 1.0]]))


def test_example1_first_zero_made_one_is_refused():
    """The paper says "either of the two zeros"; making the *first* one a one gives
    C A_q = [[1, 1], [0, 0]], which is rank 1: Theorem 2 itself refuses it."""
    with pytest.raises(bias.AugmentationError, match="column 2 .*combination"):
        bias.pbh_check(C2, np.array([[1.0, 1.0], [0.0, 0.0], [0.0, 1.0]]))


def test_example2_max_augmentations():
    x = 2.5
    bias.pbh_check(C2, np.array([[x, 0], [0, x], [0, 0]]))
    bias.pbh_check(C2, np.array([[0, x], [x, 0], [0, 0]]))
    with pytest.raises(bias.AugmentationError, match="column 2"):
        bias.pbh_check(C2, np.array([[x, 0], [0, 0], [0, x]]))
    np.testing.assert_array_equal(bias.max_augmentation(C2), [[1, 0], [0, 1], [0, 0]])


def test_dependent_column_and_too_many_columns_are_named():
    with pytest.raises(bias.AugmentationError, match="column 2 .*combination"):
        bias.pbh_check(C2, np.array([[1.0, 2.0], [1.0, 2.0], [0.0, 0.0]]))
    with pytest.raises(bias.AugmentationError, match="only 2 measurements"):
        bias.pbh_check(C2, np.eye(3))


def test_names_states_when_given():
    with pytest.raises(bias.AugmentationError, match="N_T"):
        bias.pbh_check(np.array([[1.0, 0, 0], [0, 1.0, 0]]), np.array([[0.0], [0.0], [1.0]]),
                       states=("P_IM", "P_EM", "N_T"))


@pytest.mark.parametrize("seed", range(6))
def test_theorem2_agrees_with_the_pbh_test_itself(seed):
    """Theorem 2's rank condition against Theorem 1 (PBH) on eq. 4, for random systems."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3, 3)) - 3 * np.eye(3)
    F = np.eye(3) + 0.01 * A
    C = C2 if seed % 2 else np.array([[1.0, 0.0, 1.0]])
    for Aq in (rng.normal(size=(3, 1)), np.array([[0.0], [0.0], [1.0]]),
               np.array([[1.0], [0.0], [-1.0]]), rng.normal(size=(3, 2))):
        try:
            bias.pbh_check(C, Aq)
            ok = True
        except bias.AugmentationError:
            ok = False
        assert ok == bias.pbh_rank(F, C, Aq)


# -- §4.4 and Example 3 -----------------------------------------------------------------------
def test_example3_unmeasured_row_comes_out_zero():
    F = np.array([[1.0, 1.0, -1.0], [-1.0, 0.0, 1.0], [1.0, 1.0, -1.0]])
    Aq = np.ones((3, 1))
    Q, R = np.eye(3) * 0.1, np.eye(2) * 0.1
    K, _ = steady_state_gain(F, C2, Q, R)
    M = bias.stationary_map(F, K, C2)
    rng = np.random.default_rng(3)
    q = rng.uniform(0.5, 2.0, 400)
    residuals = (M @ Aq @ q[None, :]).T + rng.normal(0, 1e-3, (400, 2))
    design = bias.approach2(residuals, M)
    assert design.n_q == 1
    assert design.Aq[2, 0] == 0.0
    assert np.all(np.abs(design.Aq[:2, 0]) > 0.1)


def test_approach2_recovers_the_span_with_full_c():
    rng = np.random.default_rng(0)
    A = np.array([[-3.0, 1.0, 0.5], [2.0, -6.0, 1.0], [0.5, 1.5, -1.0]])
    F, C = np.eye(3) + 0.01 * A, np.eye(3)
    K, _ = steady_state_gain(F, C, np.eye(3) * 1e-3, np.eye(3) * 0.25)
    M = bias.stationary_map(F, K, C)
    Aq = np.array([[1.0, -2.0], [2.0, 1.0], [0.0, 0.0]])
    q = rng.uniform(0, 4, (500, 2))
    design = bias.approach2((M @ Aq @ q.T).T, M)
    assert design.n_q == 2
    assert bias.largest_angle_deg(design.Aq, Aq) < 1e-6


def test_approach1_and_approach3_recover_the_direction():
    """Approach 1: exact states of a biased linear system; Approach 3: stationary q's."""
    A = np.array([[-3.0, 1.0, 0.5], [2.0, -6.0, 1.0], [0.5, 1.5, -1.0]])
    F = np.eye(3) + 0.01 * A
    a = np.array([0.6, 0.8, 0.0])
    X1, P, Fs, seg = [], [], [], []
    rng = np.random.default_rng(1)
    for k in range(4):
        x = rng.uniform(50, 150, 3)
        qk = rng.uniform(1, 3)
        X1.append(F @ x + (np.eye(3) - F) @ a * qk)
        P.append(F @ x)
        Fs.append(F)
        seg.append(k)
    d1 = bias.approach1(np.array(X1), np.array(P), Fs, np.array(seg))
    assert d1.n_q == 1 and bias.largest_angle_deg(d1.Aq, a[:, None]) < 1e-6
    Amax = bias.max_augmentation(np.eye(3))
    qs = rng.uniform(1, 3, (50, 1)) * a[None, :]
    d3 = bias.approach3(qs, Amax)
    assert d3.n_q == 1 and bias.largest_angle_deg(d3.Aq, a[:, None]) < 1e-6


@pytest.mark.parametrize("s, n", [((136, 30, 0.01), 2), ((1303, 24, 0.92), 1), ((5, 0, 0), 1)])
def test_dim_rule_on_the_papers_singular_values(s, n):
    assert bias.choose_dim(np.array(s, float)) == n


def test_no_stationary_residuals_is_refused():
    with pytest.raises(bias.AugmentationError, match="no stationary segment"):
        bias.approach2(np.zeros((0, 3)), np.eye(3))


# -- stationary segments -----------------------------------------------------------------------
def test_stationary_segments_found_and_settled():
    t = np.arange(0, 100, 0.1)
    u = np.where(t < 30, t, 30.0) + np.where(t > 70, (t - 70) * 2, 0.0)
    segs = bias.stationary_segments(t, u[:, None], [0.5], window=2.0, settle=5.0, min_length=10.0)
    assert len(segs) == 1
    a, b = segs[0]
    assert 35.0 <= a <= 37.0 and 68.0 <= b <= 70.0
    assert bias.stationary_segments(t, t[:, None], [0.5]) == []


# -- eqs. 3-4 ----------------------------------------------------------------------------------
def test_augmented_linear_is_eq4():
    A = np.array([[-1.0, 0.2], [0.3, -2.0]])
    F = np.eye(2) + 0.1 * A
    Aq = np.array([[1.0], [2.0]])
    Fa, Ba, Ca = bias.augmented_linear(F, np.ones((2, 1)), np.array([[1.0, 0.0]]), Aq)
    np.testing.assert_allclose(Fa[:2, 2:], -0.1 * A @ Aq)
    np.testing.assert_allclose(Fa[2:, 2:], [[1.0]])
    np.testing.assert_allclose(Ba[2:], [[0.0]])
    np.testing.assert_allclose(Ca, [[1.0, 0.0, 0.0]])


def test_augment_moves_the_stationary_point_by_aq_q():
    """eq. 3: x' = f(x - A_q q): the equilibrium moves by A_q q; the Jacobian is exact."""
    A = np.array([[-2.0, 0.5], [0.1, -1.0]])
    m = Model(("a", "b"), ("u",), ("a",), lambda t, x, u, p: A @ x + np.array([u[0], 0.0]),
              lambda t, x, u, p: x[:1])
    Aq = np.array([[1.0], [-1.0]])
    aug = bias.augment(m, Aq)
    assert aug.states == ("a", "b", "Q_BIAS_1")
    u = np.array([3.0])
    x_eq = np.linalg.solve(-A, [3.0, 0.0])
    z = np.concatenate([x_eq + Aq[:, 0] * 2.0, [2.0]])
    np.testing.assert_allclose(aug.f(0, z, u, {}), 0.0, atol=1e-12)
    np.testing.assert_allclose(aug.F(0, z, u, {}), numerical_jacobian(lambda v: aug.f(0, v, u, {}), z),
                               atol=1e-6)
    np.testing.assert_allclose(aug.H(0, z, u, {}), [[1.0, 0.0, 0.0]], atol=1e-8)


def test_observable_dim_drops_a_nearly_dependent_column():
    C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Aq = np.array([[0.585, 0.78], [0.81, 0.62], [0.061, 0.078]])  # C·A_q nearly rank 1
    assert bias.observable_dim(C, Aq) == 1
    assert bias.observable_dim(C, np.array([[1.0, 0.0], [0.5, 0.5], [0.0, 1.0]])) == 2
    assert bias.observable_dim(C, np.array([[0.0], [1.0], [0.0]])) == 0
