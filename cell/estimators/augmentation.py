r"""Bias compensation by model augmentation (seed 002: Höckerdal, Frisk & Eriksson).

The method in three steps (seed 002, §5):

1. **Which augmentations are possible** (§3, Theorem 2): with :math:`(C, A)` observable
   and :math:`A` invertible, the augmented model (eq. 4) is observable if and only if
   :math:`\operatorname{Im} A_q \cap \operatorname{Ker} C = \{0\}`, i.e. :math:`C A_q`
   has full column rank. :func:`pbh_check` refuses any other, naming the columns at fault;
   :func:`pbh_rank` runs the PBH test itself (Theorem 1) on eq. 4.
2. **Estimating** :math:`\hat A_q` from data (§4): from stationary residuals of the
   default observer by SVD and eq. 9 (Approach 2, :func:`approach2`), from the measured
   states directly (Approach 1, :func:`approach1`), or from the bias states of a maximally
   augmented observer (Approach 3, :func:`max_augmentation`, :func:`approach3`). Stationary
   parts are found automatically (:func:`stationary_segments`) where the paper chose them
   by eye; dim q follows from the singular values by :func:`choose_dim`.
3. **The augmented model** (eq. 3, discretised as eq. 4): :func:`augment` wraps a
   :class:`~cell.estimators.core.Model` as :math:`\dot x = f(x - A_q q, u)`,
   :math:`\dot q = 0`, :math:`y = h(x)`; :func:`augmented_linear` builds eq. 4's matrices.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from scipy.ndimage import maximum_filter1d, minimum_filter1d

from cell.estimators.core import Model, numerical_jacobian

#: Default rule for dim q (§4.4, "picking the most significant ones"): keep the singular
#: values at least this fraction of the largest. Seed 002's two cases fall on either side:
#: §6.1 keeps 30/136 = 0.22, §6.2 drops 24/1303 = 0.018.
DIM_RATIO = 0.1


#: Largest condition number of :math:`C \hat A_q` (run-time sensors) accepted when choosing
#: dim q: Theorem 2 asks for full column rank; a nearly dependent column makes its bias state
#: nearly unobservable in practice (its variance barely shrinks, the filter trades it
#: against the others), so dim q is reduced until the condition number is below this.
MAX_COND = 20.0


class AugmentationError(ValueError):
    """An augmentation that the PBH test refuses, or data the estimation cannot use."""


# -- §3: possible augmentations ------------------------------------------------------------
def _label(names: Sequence[str] | None, i: int) -> str:
    return names[i] if names is not None else f"x_{i + 1}"


def pbh_check(C: np.ndarray, Aq: np.ndarray, states: Sequence[str] | None = None,
              outputs: Sequence[str] | None = None, tol: float = 1e-9) -> None:
    r"""Refuse an augmentation :math:`A_q` whose :math:`C A_q` lacks full column rank.

    Seed 002, Theorem 2: for observable :math:`(C, A)` with invertible :math:`A`, the
    augmented model (eq. 4) is observable iff :math:`C A_q` has full column rank. Columns
    are taken in order; a column that adds no rank is named, and the reason is said: the
    states where it is non-zero have a zero column in :math:`C` (no sensor sees them), or
    :math:`C a_j` is a combination of the earlier columns.

    Raises
    ------
    AugmentationError
        With every offending column (1-based, as the paper counts) and why.
    """
    C = np.atleast_2d(np.asarray(C, dtype=float))
    Aq = np.asarray(Aq, dtype=float)
    if Aq.ndim == 1:
        Aq = Aq[:, None]
    if Aq.shape[0] != C.shape[1]:
        raise AugmentationError(f"A_q has {Aq.shape[0]} rows but the model has {C.shape[1]} "
                                "states")
    n_q, n_y = Aq.shape[1], C.shape[0]
    problems = []
    if n_q > n_y:
        problems.append(f"A_q has {n_q} columns but there are only {n_y} measurements "
                        "(Theorem 2 needs n_q <= n_y)")
    CA = C @ Aq
    scale = max(np.abs(CA).max(initial=0.0), np.abs(Aq).max(initial=0.0), 1.0)
    zero_cols_of_C = [i for i in range(C.shape[1]) if not np.abs(C[:, i]).max() > tol * scale]
    rank = 0
    for j in range(n_q):
        r = np.linalg.matrix_rank(CA[:, :j + 1], tol=tol * scale)
        if r > rank:
            rank = r
            continue
        nz = [i for i in range(Aq.shape[0]) if abs(Aq[i, j]) > tol * scale]
        if not np.abs(CA[:, j]).max() > tol * scale:
            unseen = [_label(states, i) for i in nz if i in zero_cols_of_C]
            problems.append(
                f"column {j + 1} of A_q cannot be observed: C·a_{j + 1} = 0, its non-zero rows "
                f"({', '.join(_label(states, i) for i in nz) or 'none'}) are zero columns of C "
                f"(no measurement sees {', '.join(unseen) or 'them'})")
        else:
            problems.append(f"column {j + 1} of A_q cannot be observed: C·a_{j + 1} is a "
                            f"combination of the columns before it")
    if problems:
        raise AugmentationError("augmentation refused (seed 002, Theorem 2: C·A_q must have full "
                                "column rank): " + "; ".join(problems))


def pbh_rank(F: np.ndarray, C: np.ndarray, Aq: np.ndarray, tol: float = 1e-9) -> bool:
    r"""PBH test (seed 002, Theorem 1) of the augmented discrete model eq. 4.

    True when :math:`\begin{pmatrix} C_\mathrm{aug} \\ F_\mathrm{aug} - \lambda I\end{pmatrix}`
    has full column rank at every eigenvalue :math:`\lambda` of :math:`F_\mathrm{aug}` (the
    only places it can lose rank).
    """
    Fa, _, Ca = augmented_linear(F, None, C, Aq)
    n = Fa.shape[0]
    for lam in np.linalg.eigvals(Fa):
        obs = np.vstack([Ca.astype(complex), Fa - lam * np.eye(n)])
        if np.linalg.matrix_rank(obs, tol=tol * max(1.0, np.abs(obs).max())) < n:
            return False
    return True


def augmented_linear(F: np.ndarray, B: np.ndarray | None, C: np.ndarray, Aq: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    r"""Seed 002, eq. 4: the augmented discrete model's :math:`F, B, C`.

    .. math:: F_\mathrm{aug} = \begin{bmatrix} F & (I - F) A_q \\ 0 & I \end{bmatrix},\quad
              B_\mathrm{aug} = \begin{bmatrix} B \\ 0 \end{bmatrix},\quad
              C_\mathrm{aug} = [C\ \ 0]

    (:math:`-T_s A A_q = (I - F) A_q` for the Euler step :math:`F = I + T_s A`).
    """
    F = np.atleast_2d(np.asarray(F, dtype=float))
    C = np.atleast_2d(np.asarray(C, dtype=float))
    Aq = np.asarray(Aq, dtype=float).reshape(F.shape[0], -1)
    n, nq = F.shape[0], Aq.shape[1]
    Fa = np.block([[F, (np.eye(n) - F) @ Aq], [np.zeros((nq, n)), np.eye(nq)]])
    Ba = None if B is None else np.vstack([np.atleast_2d(B).reshape(n, -1),
                                           np.zeros((nq, np.atleast_2d(B).reshape(n, -1).shape[1]))])
    Ca = np.hstack([C, np.zeros((C.shape[0], nq))])
    return Fa, Ba, Ca


# -- §4: estimating A_q ----------------------------------------------------------------------
def stationary_segments(t: np.ndarray, signals: np.ndarray, tol: Sequence[float],
                        window: float = 5.0, settle: float = 5.0, min_length: float = 10.0
                        ) -> list[tuple[float, float]]:
    """Stationary parts of a run, found from the signals that drive it (seed 002, §4.2).

    A sample is stationary when, over the ``window`` s centred on it, every signal (a
    column of ``signals``) stays within its ``tol`` (max minus min). A run of stationary
    samples becomes a segment after dropping its first ``settle`` s (the dynamics settling:
    "to prevent dynamical estimation errors from affecting the estimation of the constant
    or slowly varying bias"); segments shorter than ``min_length`` s are dropped.

    Returns
    -------
    list of (start, end)
        Times of the segments, in order.
    """
    t = np.asarray(t, dtype=float)
    sig = np.asarray(signals, dtype=float).reshape(len(t), -1)
    if len(t) < 3:
        return []
    dt = float(np.median(np.diff(t)))
    w = max(3, int(round(window / dt)) | 1)
    ok = np.ones(len(t), dtype=bool)
    for j, tj in enumerate(tol):
        col = sig[:, j]
        rng = maximum_filter1d(col, w, mode="nearest") - minimum_filter1d(col, w, mode="nearest")
        ok &= rng <= tj
    out = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(int), [0]])))
    for a, b in zip(edges[::2], edges[1::2]):
        start, end = t[a] + settle, t[b - 1]
        if end - start >= min_length:
            out.append((float(start), float(end)))
    return out


def segment_mask(t: np.ndarray, segments: Sequence[tuple[float, float]]) -> np.ndarray:
    """Boolean mask of the samples of ``t`` inside any of ``segments``."""
    t = np.asarray(t, dtype=float)
    m = np.zeros(len(t), dtype=bool)
    for a, b in segments:
        m |= (t >= a) & (t <= b)
    return m


def choose_dim(s: np.ndarray, ratio: float = DIM_RATIO, max_dim: int | None = None) -> int:
    """dim q from the singular values (§4.4): how many are at least ``ratio`` times the
    largest, at most ``max_dim`` (Theorem 2: n_q <= n_y of the run-time sensors)."""
    s = np.asarray(s, dtype=float)
    if s.size == 0 or not s[0] > 0:
        return 0
    n = int(np.sum(s >= ratio * s[0]))
    return min(n, max_dim) if max_dim is not None else n


def observable_dim(C: np.ndarray, Aq: np.ndarray, max_cond: float = MAX_COND) -> int:
    """The largest ``k`` such that the first ``k`` columns of ``Aq`` pass Theorem 2 with a
    margin: :math:`C A_q[:, :k]` of full column rank with condition number <= ``max_cond``."""
    C = np.atleast_2d(np.asarray(C, dtype=float))
    Aq = np.asarray(Aq, dtype=float).reshape(C.shape[1], -1)
    k = 0
    for j in range(1, Aq.shape[1] + 1):
        s = np.linalg.svd(C @ Aq[:, :j], compute_uv=False)
        if j > C.shape[0] or not s[-1] > 0 or s[0] / s[-1] > max_cond:
            break
        k = j
    return k


def stationary_map(F: np.ndarray, K: np.ndarray, C: np.ndarray) -> np.ndarray:
    r"""The map from :math:`A_q q` to the stationary residual (seed 002, §4.2):

    .. math:: r_\mathrm{stat} = C (I - F + K C F)^{-1} (I - K C)(I - F)\, A_q q
    """
    F, K, C = (np.atleast_2d(np.asarray(a, dtype=float)) for a in (F, K, C))
    n = F.shape[0]
    eye = np.eye(n)
    return C @ np.linalg.solve(eye - F + K @ C @ F, (eye - K @ C) @ (eye - F))


def _normalise(A: np.ndarray) -> np.ndarray:
    """Columns to unit length, the largest entry of each positive (A_q's scale and sign are
    free: only span(A_q) matters, §6.1)."""
    A = np.array(A, dtype=float)
    for j in range(A.shape[1]):
        norm = np.linalg.norm(A[:, j])
        if norm > 0:
            A[:, j] /= norm
            if A[np.argmax(np.abs(A[:, j])), j] < 0:
                A[:, j] = -A[:, j]
    return A


@dataclass
class BiasDesign:
    """The result of an estimation of :math:`\\hat A_q` (seed 002, §4)."""

    Aq: np.ndarray
    """Estimated augmentation, ``n`` x ``n_q``, unit columns."""
    singular_values: np.ndarray
    """:math:`S_r`, descending."""
    basis: np.ndarray
    """The singular vectors (:math:`V_r`, all of them, as columns)."""
    n_q: int
    approach: int
    segments: list[tuple[float, float]]
    samples: int
    """Stationary samples the SVD used."""

    def as_dict(self, states: Sequence[str] | None = None) -> dict:
        return {"approach": self.approach, "n_q": self.n_q, "Aq": self.Aq.tolist(),
                "singular_values": self.singular_values.tolist(), "basis": self.basis.tolist(),
                "segments": [list(s) for s in self.segments], "samples": self.samples,
                **({"states": list(states)} if states is not None else {})}


def _svd(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    U, s, _ = scipy.linalg.svd(R, full_matrices=False)
    return U, s


def approach2(residuals: np.ndarray, maps: Sequence[np.ndarray] | np.ndarray,
              weights: Sequence[float] | None = None, n_q: int | None = None,
              ratio: float = DIM_RATIO, max_dim: int | None = None,
              segments: Sequence[tuple[float, float]] = ()) -> BiasDesign:
    r"""Seed 002, Approach 2 (§4.2): SVD of stationary residuals, then eq. 9.

    Parameters
    ----------
    residuals:
        Stationary residuals :math:`r_t = y_t - \hat y_{t|t}` (eq. 8), ``N`` x ``m``.
    maps:
        :func:`stationary_map` at the operating points (one, or one per segment, averaged
        with ``weights``, e.g. the samples per segment): the :math:`C_\mathrm{stat}(\dots)`
        of eq. 9.
    n_q:
        dim q; ``None`` chooses it by :func:`choose_dim` (``ratio``, ``max_dim``).

    Notes
    -----
    :math:`S_r` and :math:`V_r` come from the SVD of the ``m`` x ``N`` matrix of stationary
    residuals; :math:`V_r` is its left singular basis (the residual space). Then (eq. 9)

    .. math:: \hat A_q = \bigl(C_\mathrm{stat}(I - F_\mathrm{stat} + K_\mathrm{stat}
              C_\mathrm{stat} F_\mathrm{stat})^{-1}(I - K_\mathrm{stat}C_\mathrm{stat})
              (I - F_\mathrm{stat})\bigr)^\dagger V_r

    with its columns normalised. Rows of states that no sensor measures come out zero
    (§4.4, Example 3), since those columns of the map are zero.
    """
    R = np.asarray(residuals, dtype=float)
    if R.ndim != 2 or R.shape[0] == 0:
        raise AugmentationError("no stationary residuals: the log has no stationary segment")
    maps = np.asarray(maps, dtype=float)
    M = maps if maps.ndim == 2 else np.average(maps, axis=0, weights=weights)
    U, s = _svd(R.T)
    nq = n_q if n_q is not None else choose_dim(s, ratio, max_dim)
    Aq = np.linalg.pinv(M) @ U[:, :nq]
    Aq[np.abs(Aq) < 1e-12 * max(np.abs(Aq).max(initial=0.0), 1.0)] = 0.0
    return BiasDesign(_normalise(Aq), s, U, nq, 2, list(segments), R.shape[0])


def approach1(states: np.ndarray, predicted: np.ndarray, F: Sequence[np.ndarray],
              seg_index: np.ndarray, n_q: int | None = None, ratio: float = DIM_RATIO,
              max_dim: int | None = None, segments: Sequence[tuple[float, float]] = ()
              ) -> BiasDesign:
    r"""Seed 002, Approach 1 (§4.1): :math:`A_q q_t` from the measured states directly.

    .. math:: A_q q_t = (I - F_t)^{-1}\,(C^\dagger y_{t+1} - f_d(C^\dagger y_t, u_t))

    (the linear case's :math:`F_t C^\dagger y_t + B_t u_t` is the model's one-step
    prediction :math:`f_d`). ``states`` are :math:`C^\dagger y_{t+1}`, ``predicted``
    :math:`f_d(C^\dagger y_t, u_t)` (``N`` x ``n``), ``F`` the :math:`F_t`, one per sample.
    §4.1 warns that this needs a high SNR; the per-sample values are therefore averaged over
    each stationary segment (``seg_index``: the segment of each sample) before the SVD.
    Needs :math:`C` of full column rank.
    """
    X, P = np.asarray(states, dtype=float), np.asarray(predicted, dtype=float)
    if X.shape[0] == 0:
        raise AugmentationError("no stationary samples: the log has no stationary segment")
    n = X.shape[1]
    eye = np.eye(n)
    W = np.array([np.linalg.solve(eye - Fk, d) for Fk, d in zip(F, X - P)])
    seg_index = np.asarray(seg_index)
    rows = [W[seg_index == k].mean(axis=0) for k in np.unique(seg_index)]
    U, s = _svd(np.array(rows).T)
    nq = n_q if n_q is not None else choose_dim(s, ratio, max_dim)
    return BiasDesign(_normalise(U[:, :nq]), s, U, nq, 1, list(segments), X.shape[0])


def max_augmentation(C: np.ndarray) -> np.ndarray:
    """Seed 002, Approach 3 (§4.3, Example 2): the largest possible augmentation, one unit
    column per non-zero column of ``C`` (at most ``n_y`` of them)."""
    C = np.atleast_2d(np.asarray(C, dtype=float))
    cols = [i for i in range(C.shape[1]) if np.abs(C[:, i]).max() > 0][: C.shape[0]]
    A = np.zeros((C.shape[1], len(cols)))
    for j, i in enumerate(cols):
        A[i, j] = 1.0
    return A


def approach3(bias_states: np.ndarray, Aq_max: np.ndarray, n_q: int | None = None,
              ratio: float = DIM_RATIO, max_dim: int | None = None,
              segments: Sequence[tuple[float, float]] = ()) -> BiasDesign:
    r"""Seed 002, Approach 3 (§4.3): SVD of the stationary bias states of an observer
    augmented with :func:`max_augmentation`; :math:`\hat A_q = A_q^\mathrm{max} V` over the
    dominant singular vectors :math:`V` of the stationary :math:`q` (``N`` x ``n_q,max``)."""
    Q = np.asarray(bias_states, dtype=float)
    if Q.ndim != 2 or Q.shape[0] == 0:
        raise AugmentationError("no stationary bias states: the log has no stationary segment")
    U, s = _svd(Q.T)
    nq = n_q if n_q is not None else choose_dim(s, ratio, max_dim)
    return BiasDesign(_normalise(np.asarray(Aq_max) @ U[:, :nq]), s, U, nq, 3, list(segments),
                      Q.shape[0])


def largest_angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    """Largest principal angle between span(A) and span(B), degrees (scipy)."""
    return float(np.degrees(scipy.linalg.subspace_angles(np.asarray(A, dtype=float),
                                                         np.asarray(B, dtype=float)).max()))


# -- §2, eq. 3: the augmented model ---------------------------------------------------------
def augment(model: Model, Aq: np.ndarray, prefix: str = "Q_BIAS_") -> Model:
    r"""The augmented model of seed 002, eq. 3, on the estimator platform.

    .. math:: \dot x = f(x - A_q q, u), \qquad \dot q = 0, \qquad y = h(x)

    States are the model's followed by ``Q_BIAS_1 ... Q_BIAS_nq``. The Jacobian is
    :math:`\begin{bmatrix} A(\xi) & -A(\xi) A_q \\ 0 & 0 \end{bmatrix}` at
    :math:`\xi = x - A_q q`, with :math:`A` the model's own (analytic if it has one);
    an Euler scheme then gives eq. 4 exactly.
    """
    Aq = np.asarray(Aq, dtype=float)
    n = len(model.states)
    Aq = Aq.reshape(n, -1)
    nq = Aq.shape[1]
    f0, h0, F0, H0 = model.f, model.h, model.F, model.H

    def f(t, z, u, p):
        z = np.asarray(z, dtype=float)
        xi = z[:n] - Aq @ z[n:]
        return np.concatenate([np.asarray(f0(t, xi, u, p), dtype=float), np.zeros(nq)])

    def F(t, z, u, p):
        z = np.asarray(z, dtype=float)
        xi = z[:n] - Aq @ z[n:]
        A = (np.atleast_2d(F0(t, xi, u, p)) if F0 is not None
             else numerical_jacobian(lambda v: f0(t, v, u, p), xi))
        out = np.zeros((n + nq, n + nq))
        out[:n, :n] = A
        out[:n, n:] = -A @ Aq
        return out

    def h(t, z, u, p):
        return h0(t, np.asarray(z, dtype=float)[:n], u, p)

    def H(t, z, u, p):
        z = np.asarray(z, dtype=float)
        Hx = (np.atleast_2d(H0(t, z[:n], u, p)) if H0 is not None
              else numerical_jacobian(lambda v: np.atleast_1d(h0(t, v, u, p)), z[:n]))
        return np.hstack([Hx, np.zeros((Hx.shape[0], nq))])

    states = tuple(model.states) + tuple(f"{prefix}{i + 1}" for i in range(nq))
    return Model(states, model.inputs, model.outputs, f, h, F=F, H=H, params=model.params,
                 dt=model.dt, method=model.method, max_step=model.max_step, units=model.units)


__all__ = ["DIM_RATIO", "MAX_COND", "AugmentationError", "BiasDesign", "approach1", "approach2",
           "approach3", "augment", "augmented_linear", "choose_dim", "largest_angle_deg",
           "max_augmentation", "observable_dim", "pbh_check", "pbh_rank", "segment_mask",
           "stationary_map", "stationary_segments"]
