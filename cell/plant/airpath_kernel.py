"""The SI air path's sub-steps (:func:`~cell.plant.si_airpath.plant_rk4`) compiled to machine
code with numba: the simulator's hot path (40 right-hand-side evaluations per 10 ms step).

:func:`steps` is the arithmetic of :func:`~cell.plant.si_airpath.plant_rk4`'s integrator,
operation for operation and in the same order, so that the compiled code gives the same
floats as the reference :func:`~cell.plant.si_airpath.rk4` over
:func:`~cell.plant.si_airpath.airpath_rhs` (``tests/cell/plant/test_si_airpath_fast.py``).
Three things keep it so: numba compiles without fast-math (no contraction into fused
multiply-adds, no reassociation); every power's exponent is read from the constants array at
run time, so that the compiler cannot rewrite ``x ** 2.0`` into ``x * x`` or ``x ** 0.5`` into
a square root (Python calls the C library's ``pow`` for each, and so does the compiled code);
and the terms of the held input (the throttle's area from its cosine, the η_vol speed shape)
are computed in Python by the caller, as the reference does.

The constants (:data:`CONSTANTS` names them in order) and the held input's terms
(:data:`TERMS`) come in one float64 array. :data:`COMPILED` is false when numba is missing;
the plant then runs :func:`~cell.plant.si_airpath.plant_rk4` itself (the same floats, slower).
The compiled code is cached beside this file (numba's ``cache=True``), so a process pays the
compilation (about a second) only once per installation.
"""

from __future__ import annotations

import math

try:  # numba is a dependency; without it the plant runs the Python integrator
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is not installed
    numba = None

#: The air path's constants in the kernel's array, in order (see ``plant_rk4``).
CONSTANTS = (
    "crit_a", "k_a", "e1_a", "e2_a", "th_lin", "psi_lin_th", "den_th",
    "crit_e", "k_e", "e1_e", "e2_e", "wg_lin", "psi_lin_wg", "den_wg",
    "T_ic_guess", "sq_guess", "p_amb", "k_af", "k_ic", "k_es",
    "w_ref", "omega_ref", "k_pr", "offset", "sq_ref", "T_amb", "comp_eff", "e_c",
    "eff_ic", "T_cool", "cp_a", "c_eta", "r_c", "inv_ge", "r_c1", "v_cyl", "n_cyl",
    "t_area", "sq_lin", "cp_e", "t_eff", "e_t", "h_im", "T_wall",
    "cv", "cp", "V_im", "G1", "G2", "V_ic", "V_em", "J", "eta_m", "k_f", "R", "Re",
    "two", "one_half",
)
#: The held input's terms after the constants, in order.
TERMS = ("n", "area_th", "shape", "charge_num", "charge_den", "eo", "dT_phi", "area_wg")
#: Index of the first term in the array.
FIRST_TERM = len(CONSTANTS)


def _steps(x0: float, x1: float, x2: float, x3: float, x4: float, c, h: float, steps: int):
    """``steps`` RK4 sub-steps of ``h`` from ``(x0 .. x4)``; ``c``: constants, then terms."""
    crit_a, k_a, e1_a, e2_a, th_lin, psi_lin_th, den_th = c[0], c[1], c[2], c[3], c[4], c[5], c[6]
    crit_e, k_e, e1_e, e2_e, wg_lin, psi_lin_wg, den_wg = (c[7], c[8], c[9], c[10], c[11],
                                                           c[12], c[13])
    T_ic_guess, sq_guess, p_amb, k_af, k_ic, k_es = c[14], c[15], c[16], c[17], c[18], c[19]
    w_ref, omega_ref, k_pr, offset, sq_ref = c[20], c[21], c[22], c[23], c[24]
    T_amb, comp_eff, e_c, eff_ic, T_cool, cp_a = c[25], c[26], c[27], c[28], c[29], c[30]
    c_eta, r_c, inv_ge, r_c1, v_cyl, n_cyl = c[31], c[32], c[33], c[34], c[35], c[36]
    t_area, sq_lin, cp_e, t_eff, e_t, h_im, T_wall = (c[37], c[38], c[39], c[40], c[41],
                                                      c[42], c[43])
    cv, cp, V_im, G1, G2, V_ic, V_em = c[44], c[45], c[46], c[47], c[48], c[49], c[50]
    J, eta_m, k_f, R, Re, two, one_half = c[51], c[52], c[53], c[54], c[55], c[56], c[57]
    k = FIRST_TERM
    n, area_th, shape, charge_num, charge_den = c[k], c[k + 1], c[k + 2], c[k + 3], c[k + 4]
    eo, dT_phi, area_wg = c[k + 5], c[k + 6], c[k + 7]
    sqrt = math.sqrt
    half, sixth = 0.5 * h, h / 6.0

    def ff_a(pr: float) -> float:
        pr = max(pr, crit_a)
        if pr >= 1.0:
            return 0.0
        if pr > th_lin:
            return psi_lin_th * (1.0 - pr) / den_th
        return sqrt(k_a * (pr ** e1_a - pr ** e2_a))

    def ff_e(pr: float) -> float:
        pr = max(pr, crit_e)
        if pr >= 1.0:
            return 0.0
        if pr > wg_lin:
            return psi_lin_wg * (1.0 - pr) / den_wg
        return sqrt(k_e * (pr ** e1_e - pr ** e2_e))

    def rhs(p_ic: float, p_im: float, T_im: float, p_em: float, omega: float):
        if p_im <= p_ic:
            w_th0 = area_th * p_ic / sq_guess * ff_a(p_im / p_ic)
        else:
            w_th0 = -area_th * p_im / sq_guess * ff_a(p_ic / p_im)
        p_af = p_amb - k_af * w_th0 * abs(w_th0)
        p_c = p_ic + k_ic * w_th0 * abs(w_th0)
        pr_c = p_c / p_af
        pr0 = 1.0 + k_pr * (omega / omega_ref) ** two
        r = min(max((pr_c - 1.0) / max(pr0 - 1.0, 0.02), -3.0), 1.0)
        w_max = w_ref * max(omega, 0.0) / omega_ref * (p_af / 101_325.0) * sq_ref
        w_c = w_max * (1.0 - r * abs(r)) + offset
        T_c = T_amb * (1.0 + (max(pr_c, 1e-3) ** e_c - 1.0) / comp_eff)
        T_ic = T_c - eff_ic * (T_c - T_cool)
        w_th = w_th0 * sqrt(T_ic_guess / T_ic)
        P_c = w_c * cp_a * (T_c - T_amb)
        ratio = max(p_em / p_im, 1e-3) ** inv_ge
        eta = c_eta * (r_c - ratio) / r_c1 * shape
        cac = eta * p_im * v_cyl / (R * T_im) * charge_num / charge_den
        w_ac = cac * n_cyl * n / 2.0
        w_eo = w_ac * eo
        T_em = T_im + dT_phi * (0.6 + 0.5 * w_ac / (w_ac + 0.03))
        p_es = p_amb + k_es * w_eo * abs(w_eo)
        z = 1.0 - min(p_es / p_em, 1.0) ** one_half
        root = sqrt(z) if z >= 0.02 else z / sq_lin
        w_t = t_area * p_em / sqrt(Re * T_em) * root
        if p_es <= p_em:
            w_wg = area_wg * p_em / sqrt(Re * T_em) * ff_e(p_es / p_em)
        else:
            w_wg = -area_wg * p_es / sqrt(Re * T_em) * ff_e(p_em / p_es)
        pr_t = min(p_es / p_em, 1.0)
        P_t = w_t * cp_e * T_em * t_eff * (1.0 - min(pr_t, 1.0) ** e_t)
        heat = h_im * (T_wall - T_im)
        return (R * T_ic / V_ic * (w_c - w_th),
                G1 * (w_th * T_ic - w_ac * T_im) + G2 * heat,
                R * T_im / (p_im * V_im * cv) * (w_th * (cp * T_ic - cv * T_im)
                                                 - R * w_ac * T_im + heat),
                Re * T_em / V_em * (w_eo - (w_t + w_wg)),
                (eta_m * P_t - P_c) / (J * max(omega, 500.0)) - k_f * omega / J)

    for _ in range(steps):
        a0, a1, a2, a3, a4 = rhs(x0, x1, x2, x3, x4)
        b0, b1, b2, b3, b4 = rhs(x0 + half * a0, x1 + half * a1, x2 + half * a2,
                                 x3 + half * a3, x4 + half * a4)
        c0, c1_, c2, c3, c4 = rhs(x0 + half * b0, x1 + half * b1, x2 + half * b2,
                                  x3 + half * b3, x4 + half * b4)
        d0, d1, d2, d3, d4 = rhs(x0 + h * c0, x1 + h * c1_, x2 + h * c2, x3 + h * c3,
                                 x4 + h * c4)
        x0 = x0 + sixth * (a0 + 2.0 * b0 + 2.0 * c0 + d0)
        x1 = x1 + sixth * (a1 + 2.0 * b1 + 2.0 * c1_ + d1)
        x2 = x2 + sixth * (a2 + 2.0 * b2 + 2.0 * c2 + d2)
        x3 = x3 + sixth * (a3 + 2.0 * b3 + 2.0 * c3 + d3)
        x4 = x4 + sixth * (a4 + 2.0 * b4 + 2.0 * c4 + d4)
    return x0, x1, x2, x3, x4


#: Whether :func:`steps` is compiled (numba is installed).
COMPILED = numba is not None
#: The sub-steps, compiled when numba is installed (else the Python function above).
steps = numba.njit(cache=True, nogil=True)(_steps) if COMPILED else _steps

__all__ = ["COMPILED", "CONSTANTS", "FIRST_TERM", "TERMS", "steps"]
