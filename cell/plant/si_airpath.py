r"""The mean-value air path of the turbocharged SI engine (seed 003, section 2).

Seed 003's model is a chain of restrictions and control volumes from the air filter to the
exhaust system (its eq. 2, thirteen states). This one keeps the five states the observer
needs and the paper's acceptance is about, and makes the other volumes quasi-static
(restrictions whose pressure drop follows the throughflow)::

    p_amb ─ air filter ─ compressor ─[ p_ic : compressor outlet + intercooler volume ]─ throttle
          ─[ p_im, T_im : intake manifold, adiabatic ]─ engine (η_vol, eq. 1)
          ─[ p_em : exhaust manifold ]─ turbine ∥ wastegate ─ exhaust system ─ p_amb
                       ω_tc : turbo shaft power balance (turbine drives compressor)

States ``x = (p_ic, p_im, T_im, p_em, omega_tc)`` (Pa, Pa, K, Pa, rad/s); inputs
``u = (alpha, u_wg, speed, lambda)`` (throttle angle deg, wastegate opening 0..1, rpm, -);
ambient pressure and temperature are parameters (the test cell's conditioned air).
:func:`airpath_rhs` is the model's ``f(t, x, u, params)``; the plant (:class:`SIAirPath`)
integrates it with :data:`PLANT_PARAMS`, the observer with :data:`MODEL_PARAMS`.

The simulated engine differs from the observer's default model by documented errors,
as a real engine differs from its model (seed 003, Figure 1: "wrong stationary values"):

=========================  ==================  ==================  =======================
parameter                  engine (plant)      default model       effect
=========================  ==================  ==================  =======================
``c_eta_vol``              0.93                0.88 (-5.4 %)       p_im too high, CAC low
``eta_vol_speed_shape``    0.10                0 (flat)            error varies with speed
``comp_flow_offset``       0                   +0.002 kg/s         p_ic over-estimated
``h_im`` (wall heat)       3 W/K               0 (adiabatic)       CAC over-estimated
``turbine_efficiency``     0.66                0.68                N_TC, p_em
=========================  ==================  ==================  =======================

The exhaust manifold temperature drives the turbine; the gas reaching the catalyst
(``T_EXH_TRUE``) has passed the turbine and the downpipe, whose walls lag it: it follows
issue 8's catalyst-inlet map over this engine's relative charge, with a 3 s lag.

The plant also holds the engine control unit that turns the duty cycle's load demand
into throttle and wastegate positions (:func:`throttle_command`, :class:`BoostControl`),
its actuators, and the sensors: ``P_IC`` (fast, white noise), ``P_IM`` (white noise plus
the engine's pumping ripple at the firing frequency, sampled at the plant rate), ``T_IM``
(a slow thermocouple: first-order lag of 2.5 s), ``N_TC``, ``THROTTLE``, ``WASTEGATE``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from cell.core.errors import ConfigError
from cell.plant import airpath_kernel, airpath_parts as ap
from cell.plant.airpath_kernel import CONSTANTS, FIRST_TERM
from cell.plant.base import Plant, lag_factor
from cell.plant.si_engine import steady_exhaust_temp

#: λ above which the engine runs without fuel (issue 8's fuel cut: λ = 10 stands for air).
FUEL_CUT_LAMBDA = 5.0

RPM_PER_RAD_S = 30.0 / math.pi
STATES = ("p_ic", "p_im", "T_im", "p_em", "omega_tc")
INPUTS = ("alpha", "u_wg", "speed", "lambda")


@dataclass(frozen=True)
class SIAirPathParams:
    """Every constant of the 2.3 L turbocharged SI engine's air path (seed 003: a SAAB
    B235R, 2.3 L, four cylinders), with the reasoning behind its value."""

    # ambient (the test cell's conditioned combustion air)
    p_amb: float = 101_300.0
    """Ambient pressure, Pa."""
    T_amb: float = 298.0
    """Ambient temperature, K."""

    # engine
    displacement: float = 2.3e-3
    """Swept volume V_d, m³ (B235R: 2.3 L)."""
    cylinders: int = 4
    r_c: float = 9.3
    """Compression ratio."""
    gamma_e: float = 1.3
    """Ratio of specific heats on the exhaust side (seed 003's γ_e)."""
    afr_s: float = 14.7
    """Stoichiometric air/fuel ratio of gasoline."""
    c1: float = 0.3
    """Charge-cooling parameter C_1 (seed 003, eq. 1)."""
    c_eta_vol: float = 0.93
    """Engine pumping parameter C_ηvol (seed 003's 'similar to volumetric efficiency')."""
    eta_vol_speed_shape: float = 0.10
    """Curvature of η_vol over speed, about 3000 rpm (:func:`~.airpath_parts.volumetric_efficiency`)."""
    eta_vol_speed_ref: float = 50.0
    """Speed of the η_vol optimum, rev/s (3000 rpm)."""
    indicated_efficiency: float = 0.37
    """Gross indicated efficiency at λ = 1 (fuel to indicated work)."""
    fmep: tuple[float, float, float] = (60e3, 12.0, 0.02)
    """Friction mean effective pressure c0 + c1 N + c2 N² (Pa, N in rpm): 0.9 bar at
    1800 rpm, 1.9 bar at 6000 rpm."""
    lhv: float = 43.0e6
    """Lower heating value of gasoline, J/kg."""
    fuel_density: float = 0.745
    """Gasoline density, kg/L (EN 228: 0.72-0.775)."""

    # air filter, compressor, intercooler, throttle
    k_af: float = 2.0e5
    """Air-filter loss coefficient, Pa/(kg/s)²: 2 kPa at 0.1 kg/s."""
    comp_w_ref: float = 0.20
    """Compressor flow at zero pressure rise on the reference speed line, kg/s."""
    comp_omega_ref: float = 20_000.0
    """Reference compressor speed, rad/s (191 000 rpm)."""
    comp_k_pr: float = 1.6
    """Zero-flow pressure rise at the reference speed: Π_0 = 2.6."""
    comp_efficiency: float = 0.72
    comp_flow_offset: float = 0.0
    """Flow offset of the compressor map, kg/s (0 on the engine; the model's is wrong)."""
    k_ic: float = 4.0e5
    """Intercooler loss coefficient, Pa/(kg/s)²: 4 kPa at 0.1 kg/s."""
    ic_effectiveness: float = 0.8
    T_coolant: float = 305.0
    """Intercooler cooling-air temperature, K."""
    V_ic: float = 6.0e-3
    """Volume from compressor outlet through the intercooler to the throttle, m³."""
    throttle_a_max: float = 8.0e-4
    """Throttle effective area at 90° (with discharge coefficient), m²."""
    throttle_pr_lin: float = 0.95
    """Pressure ratio above which the throttle flow function is linear (regularisation)."""
    throttle_a_leak: float = 4.0e-6
    """Leakage area of the closed throttle, m²."""

    # intake manifold
    V_im: float = 3.0e-3
    """Intake manifold volume, m³."""
    h_im: float = 3.0
    """Wall heat-transfer conductance of the intake manifold, W/K (seed 003, Figure 6:
    'unmodeled heat transfer in the intake manifold')."""
    T_wall_im: float = 330.0
    """Intake manifold wall temperature, K."""

    # exhaust manifold, turbine, wastegate, exhaust system
    V_em: float = 1.2e-3
    """Exhaust manifold volume up to the turbine, m³."""
    R_e: float = 290.0
    """Gas constant of the exhaust, J/(kg K)."""
    cp_e: float = 1200.0
    """Specific heat of the exhaust at constant pressure, J/(kg K)."""
    dT_comb: float = 800.0
    """Exhaust temperature rise over the intake at λ = 1 and high flow, K."""
    turbine_area: float = 3.6e-4
    """Turbine effective area, m²."""
    turbine_efficiency: float = 0.66
    wastegate_area: float = 3.5e-4
    """Wastegate effective area fully open, m²."""
    k_es: float = 1.5e6
    """Exhaust-system (catalyst, silencers) loss, Pa/(kg/s)²: 15 kPa at 0.1 kg/s."""

    # turbo shaft
    J_tc: float = 2.5e-5
    """Turbo rotor inertia, kg m²."""
    eta_m: float = 0.95
    """Mechanical efficiency of the shaft bearings."""
    k_fric: float = 2.0e-8
    """Shaft friction, N m s/rad."""

    # engine control unit (plant only)
    p_im_max: float = 175_000.0
    """Intake manifold pressure the ECU aims at at full load, Pa."""
    tau_throttle: float = 0.03
    """Throttle actuator time constant, s (electronic throttle)."""
    tau_wastegate: float = 0.25
    """Wastegate actuator time constant, s (pneumatic)."""

    # catalyst inlet (plant only)
    tau_exh: float = 3.0
    """Lag of the catalyst-inlet gas temperature, s: the turbine housing and downpipe walls
    (as issue 8's breathing model)."""

    # sensors (plant only)
    period: float = 0.01
    """Plant step, s (100 Hz)."""
    settle: float = 8.0
    """Time the ECU's loops are given to settle before the run starts, s."""
    substeps: int = 10
    """RK4 sub-steps per plant step (1 ms: the stiffest pole of the air path is ~ -900 /s)."""
    noise_p_ic: float = 300.0
    """P_IC sensor noise, Pa (std)."""
    noise_p_im: float = 600.0
    """P_IM sensor noise, Pa (std)."""
    ripple_p_im: float = 0.025
    """P_IM pumping ripple, fraction of p_im (amplitude at the firing frequency)."""
    tau_T_im_sensor: float = 2.5
    """T_IM thermocouple time constant, s (seed 003, Figure 1: 'the slow sensor misses it')."""
    noise_T_im: float = 0.2
    """T_IM sensor noise, K."""
    noise_n_tc: float = 300.0
    """N_TC sensor noise, rpm."""
    noise_throttle: float = 0.05
    """THROTTLE position noise, deg."""
    noise_wastegate: float = 0.2
    """WASTEGATE position noise, %."""

    @property
    def v_cyl(self) -> float:
        return self.displacement / self.cylinders


#: The simulated engine.
PLANT_PARAMS = SIAirPathParams()
#: The observer's default model: the same equations, the documented errors (module docstring).
MODEL_PARAMS = replace(PLANT_PARAMS, c_eta_vol=0.88, eta_vol_speed_shape=0.0,
                       comp_flow_offset=0.002, h_im=0.0, turbine_efficiency=0.68)


# -- the model (seed 003, eqs. 1-2) ------------------------------------------------------------
class Flows(NamedTuple):
    """The algebraic quantities of the air path at one state and input (a named tuple: the
    model evaluates it at every step)."""

    w_c: float
    w_th: float
    w_ac: float
    w_eo: float
    w_t: float
    w_wg: float
    T_ic: float
    T_em: float
    cac: float
    p_c: float
    p_es: float
    pr_t: float
    P_c: float
    P_t: float


def flows(x: Sequence[float], u: Sequence[float], p: SIAirPathParams, dc: float = 0.0) -> Flows:
    """Every flow, temperature and power of the air path at state ``x`` and input ``u``;
    ``dc`` is the ΔC_ηvol offset of the augmented model (seed 003, §4.2)."""
    p_ic, p_im, T_im, p_em, omega = x[0], x[1], x[2], x[3], x[4]
    alpha, u_wg, speed, lam = u[0], u[1], u[2], u[3]
    n = speed / 60.0
    # throttle (its flow sets the quasi-static drops over the air filter and intercooler)
    T_ic_guess = p.T_coolant + 15.0
    w_th0 = ap.restriction_flow(ap.throttle_area(alpha, p.throttle_a_max, p.throttle_a_leak),
                                p_ic, T_ic_guess, p_im, pr_lin=p.throttle_pr_lin)
    p_af = p.p_amb - ap.incompressible_drop(w_th0, p.k_af)
    p_c = p_ic + ap.incompressible_drop(w_th0, p.k_ic)
    pr_c = p_c / p_af
    w_c = ap.compressor_flow(omega, pr_c, p_af, p.T_amb, w_ref=p.comp_w_ref,
                             omega_ref=p.comp_omega_ref, k_pr=p.comp_k_pr,
                             offset=p.comp_flow_offset)
    T_c = ap.compressor_outlet_temperature(p.T_amb, pr_c, p.comp_efficiency)
    T_ic = ap.intercooler_temperature(T_c, p.T_coolant, p.ic_effectiveness)
    w_th = w_th0 * math.sqrt(T_ic_guess / T_ic)
    P_c = ap.compressor_power(w_c, p.T_amb, T_c)
    # engine (eq. 1)
    eta = ap.volumetric_efficiency(p.c_eta_vol + dc, p_im, p_em, p.r_c, p.gamma_e, n,
                                   p.eta_vol_speed_ref, p.eta_vol_speed_shape)
    cac = ap.cylinder_air_charge(eta, p_im, T_im, p.v_cyl, lam, p.afr_s, p.c1)
    w_ac = ap.engine_air_flow(cac, p.cylinders, n)
    lam_c = max(lam, 0.05)
    w_eo = w_ac * (1.0 + 1.0 / (lam_c * p.afr_s))
    # exhaust: temperature from the fuel burnt, turbine and wastegate in parallel
    phi = min(1.0 / lam_c, 1.05)
    T_em = T_im + p.dT_comb * phi * (0.6 + 0.5 * w_ac / (w_ac + 0.03))
    p_es = p.p_amb + ap.incompressible_drop(w_eo, p.k_es)
    w_t = ap.turbine_flow(p_em, T_em, p_es, p.turbine_area, R=p.R_e)
    w_wg = ap.restriction_flow(p.wastegate_area * min(max(u_wg, 0.0), 1.0), p_em, T_em, p_es,
                               R=p.R_e, gamma=p.gamma_e)
    pr_t = min(p_es / p_em, 1.0)
    P_t = ap.turbine_power(w_t, T_em, pr_t, p.turbine_efficiency, p.cp_e, p.gamma_e)
    return Flows(w_c, w_th, w_ac, w_eo, w_t, w_wg, T_ic, T_em, cac, p_c, p_es, pr_t, P_c, P_t)


def airpath_rhs(t: float, x: Sequence[float], u: Sequence[float], p: SIAirPathParams
                ) -> list[float]:
    r"""The state derivatives (seed 003, eq. 2): ``f(t, x, u, params)``.

    .. math::
        \dot p_{ic} = \frac{R T_{ic}}{V_{ic}}(W_c - W_{th}), \quad
        (\dot p_{im}, \dot T_{im}) = \text{adiabatic volume}(W_{th}, T_{ic}; W_{ac}), \quad
        \dot p_{em} = \frac{R_e T_{em}}{V_{em}}(W_{eo} - W_t - W_{wg}), \quad
        \dot\omega_{tc} = \frac{\eta_m P_t - P_c}{J \omega_{tc}} - \frac{k_f}{J}\omega_{tc}

    ``x`` may carry a sixth state, ΔC_ηvol (seed 003, §4.2, eq. 5: :math:`\dot{\Delta C}_{\eta vol} = 0`).
    """
    dc = x[5] if len(x) > 5 else 0.0
    f = flows(x, u, p, dc)
    heat = p.h_im * (p.T_wall_im - x[2])
    dp_im, dT_im = ap.adiabatic_volume(x[1], x[2], p.V_im, f.w_th, f.T_ic, f.w_ac, heat)
    out = [ap.isothermal_volume(ap.R_AIR * f.T_ic / p.V_ic, f.w_c, f.w_th), dp_im, dT_im,
           ap.isothermal_volume(p.R_e * f.T_em / p.V_em, f.w_eo, f.w_t + f.w_wg),
           ap.shaft_acceleration(f.P_t, f.P_c, x[4], p.J_tc, p.eta_m, p.k_fric)]
    if len(x) > 5:
        out.append(0.0)
    return out


def rk4(x: list[float], u: Sequence[float], p: SIAirPathParams, h: float, n: int) -> list[float]:
    """``n`` classic Runge-Kutta steps of ``h`` with ``u`` held (plain floats: fast)."""
    for _ in range(n):
        k1 = airpath_rhs(0.0, x, u, p)
        k2 = airpath_rhs(0.0, [a + 0.5 * h * b for a, b in zip(x, k1)], u, p)
        k3 = airpath_rhs(0.0, [a + 0.5 * h * b for a, b in zip(x, k2)], u, p)
        k4 = airpath_rhs(0.0, [a + h * b for a, b in zip(x, k3)], u, p)
        x = [a + h / 6.0 * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
             for a, b1, b2, b3, b4 in zip(x, k1, k2, k3, k4)]
    return x


def plant_constants(p: SIAirPathParams) -> dict[str, float]:
    """The constants of the air path's integrator for the parameters ``p``, by name
    (:data:`~cell.plant.airpath_kernel.CONSTANTS`): what :func:`plant_rk4` and the compiled
    kernel compute once instead of at every right-hand-side evaluation."""
    g, R = ap.GAMMA_AIR, ap.R_AIR
    ge, Re = p.gamma_e, p.R_e
    k_a = 2.0 * g / (g - 1.0)
    e1_a, e2_a = 2.0 / g, (g + 1.0) / g
    k_e = 2.0 * ge / (ge - 1.0)
    e1_e, e2_e = 2.0 / ge, (ge + 1.0) / ge
    th_lin = p.throttle_pr_lin
    wg_lin = 0.99
    T_ic_guess = p.T_coolant + 15.0
    cv = R / (g - 1.0)
    c = {
        "crit_a": (2.0 / (g + 1.0)) ** (g / (g - 1.0)), "k_a": k_a, "e1_a": e1_a, "e2_a": e2_a,
        "th_lin": th_lin, "psi_lin_th": math.sqrt(k_a * (th_lin ** e1_a - th_lin ** e2_a)),
        "den_th": 1.0 - th_lin,
        "crit_e": (2.0 / (ge + 1.0)) ** (ge / (ge - 1.0)), "k_e": k_e, "e1_e": e1_e,
        "e2_e": e2_e, "wg_lin": wg_lin,
        "psi_lin_wg": math.sqrt(k_e * (wg_lin ** e1_e - wg_lin ** e2_e)),
        "den_wg": 1.0 - wg_lin,
        "T_ic_guess": T_ic_guess, "sq_guess": math.sqrt(R * T_ic_guess),
        "p_amb": p.p_amb, "k_af": p.k_af, "k_ic": p.k_ic, "k_es": p.k_es,
        "w_ref": p.comp_w_ref, "omega_ref": p.comp_omega_ref, "k_pr": p.comp_k_pr,
        "offset": p.comp_flow_offset, "sq_ref": math.sqrt(298.0 / p.T_amb),
        "T_amb": p.T_amb, "comp_eff": p.comp_efficiency, "e_c": (g - 1.0) / g,
        "eff_ic": p.ic_effectiveness, "T_cool": p.T_coolant, "cp_a": ap.CP_AIR,
        "c_eta": p.c_eta_vol + 0.0, "r_c": p.r_c, "inv_ge": 1.0 / ge, "r_c1": p.r_c - 1.0,
        "v_cyl": p.v_cyl, "n_cyl": p.cylinders,
        "t_area": p.turbine_area, "sq_lin": math.sqrt(0.02),
        "cp_e": p.cp_e, "t_eff": p.turbine_efficiency, "e_t": (ge - 1.0) / ge,
        "h_im": p.h_im, "T_wall": p.T_wall_im, "cv": cv, "cp": cv + R, "V_im": p.V_im,
        "G1": g * R / p.V_im, "G2": (g - 1.0) / p.V_im, "V_ic": p.V_ic, "V_em": p.V_em,
        "J": p.J_tc, "eta_m": p.eta_m, "k_f": p.k_fric, "R": R, "Re": Re,
        "two": 2, "one_half": 1.5,
    }
    return {name: c[name] for name in CONSTANTS}


def held_terms(p: SIAirPathParams, u: Sequence[float]) -> tuple[float, ...]:
    """The terms of the held input ``u`` that every evaluation in a call of the integrator
    shares (:data:`~cell.plant.airpath_kernel.TERMS`, in order)."""
    alpha, u_wg, speed, lam = u[0], u[1], u[2], u[3]
    n = speed / 60.0
    a = min(max(alpha, 0.0), 90.0)
    area_th = p.throttle_a_max * (1.0 - math.cos(math.radians(a))) + p.throttle_a_leak
    shape = 1.0 - p.eta_vol_speed_shape * (n / p.eta_vol_speed_ref - 1.0) ** 2
    inv = 1.0 / (max(lam, 0.05) * p.afr_s)
    charge_num, charge_den = 1.0 + p.c1 * inv, 1.0 + inv
    lam_c = max(lam, 0.05)
    eo = 1.0 + 1.0 / (lam_c * p.afr_s)
    dT_phi = p.dT_comb * min(1.0 / lam_c, 1.05)
    area_wg = p.wastegate_area * min(max(u_wg, 0.0), 1.0)
    return n, area_th, shape, charge_num, charge_den, eo, dT_phi, area_wg


def plant_rk4(p: SIAirPathParams):
    """:func:`rk4` of the five-state air path for the parameters ``p``, as one function.

    The same arithmetic as :func:`rk4` over :func:`airpath_rhs` and :func:`flows`, operation
    for operation (so the same floats), with the parts inlined, the constants of ``p``
    (:func:`plant_constants`) and the terms of the held input ``u`` (:func:`held_terms`)
    computed once per call instead of at every one of the ``4 n`` evaluations. The plant
    runs its compiled twin (:func:`compiled_rk4`) where numba is installed.
    """
    (crit_a, k_a, e1_a, e2_a, th_lin, psi_lin_th, den_th,
     crit_e, k_e, e1_e, e2_e, wg_lin, psi_lin_wg, den_wg,
     T_ic_guess, sq_guess, p_amb, k_af, k_ic, k_es,
     w_ref, omega_ref, k_pr, offset, sq_ref, T_amb, comp_eff, e_c,
     eff_ic, T_cool, cp_a, c_eta, r_c, inv_ge, r_c1, v_cyl, n_cyl,
     t_area, sq_lin, cp_e, t_eff, e_t, h_im, T_wall,
     cv, cp, V_im, G1, G2, V_ic, V_em, J, eta_m, k_f, R, Re,
     two, one_half) = plant_constants(p).values()
    sqrt = math.sqrt

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

    def run(x: list[float], u, h: float, steps: int) -> list[float]:
        n, area_th, shape, charge_num, charge_den, eo, dT_phi, area_wg = held_terms(p, u)
        half, sixth = 0.5 * h, h / 6.0

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

        x0, x1, x2, x3, x4 = x
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
        return [x0, x1, x2, x3, x4]

    return run


def compiled_rk4(p: SIAirPathParams):
    """:func:`plant_rk4` compiled (:mod:`cell.plant.airpath_kernel`): the same floats, about
    fifty times as fast; :func:`plant_rk4` itself where numba is not installed."""
    if not airpath_kernel.COMPILED:
        return plant_rk4(p)
    c = np.zeros(FIRST_TERM + len(airpath_kernel.TERMS))
    c[:FIRST_TERM] = list(plant_constants(p).values())
    kernel = airpath_kernel.steps

    def run(x: list[float], u, h: float, steps: int) -> list[float]:
        c[FIRST_TERM:] = held_terms(p, u)
        return list(kernel(x[0], x[1], x[2], x[3], x[4], c, h, steps))

    return run


def initial_guess(p: SIAirPathParams, speed: float, alpha: float) -> list[float]:
    """A state near the operating point, to start the stationary search from."""
    p_im = p.p_amb * min(0.25 + alpha / 90.0, 1.1)
    return [p.p_amb * 1.02, p_im, 320.0, p.p_amb * 1.1 + 200.0 * speed, 3000.0 + 2.0 * speed]


def steady_state(p: SIAirPathParams, u: Sequence[float], x0: Sequence[float] | None = None,
                 dc: float = 0.0) -> np.ndarray:
    """The stationary state at constant input ``u`` (seed 003, §3.1: 'found by simulating
    the model until stationary conditions are present'), polished by a root finder.

    Raises
    ------
    ArithmeticError
        No stationary point was found (the message gives the input).
    """
    import scipy.integrate
    import scipy.optimize

    x = list(x0) if x0 is not None else initial_guess(p, u[2], u[0])
    if dc:
        x = [*x[:5], dc]

    def rhs(t: float, v: np.ndarray) -> list[float]:
        return airpath_rhs(t, v, u, p)

    sol = scipy.integrate.solve_ivp(rhs, (0.0, 30.0), x, method="LSODA", rtol=1e-8,
                                    atol=[1.0, 1.0, 1e-3, 1.0, 0.1] + [1e-9] * (len(x) - 5))
    xs = sol.y[:, -1]
    n5 = 5
    root = scipy.optimize.root(lambda v: airpath_rhs(0.0, [*v, *xs[n5:]], u, p)[:n5], xs[:n5],
                               method="hybr")
    xr = np.concatenate([root.x, xs[n5:]])
    scale = np.array([1e5, 1e5, 300.0, 1e5, 1e4])
    if not (np.all(np.isfinite(xr)) and np.max(np.abs(np.array(airpath_rhs(0.0, xr, u, p)[:5])
                                                     / scale)) < 1e-6):
        raise ArithmeticError(f"no stationary point of the air path at throttle {u[0]:.1f} deg, "
                              f"wastegate {u[1]:.2f}, {u[2]:.0f} rpm")
    return xr


# -- the engine control unit -----------------------------------------------------------------
def p_im_target(load: float, p: SIAirPathParams) -> float:
    """Intake manifold pressure (Pa) the ECU aims at for a load demand 0..1: from 0.13 bar
    on overrun (closed throttle) to 0.97 bar at a load of 0.6 throttled, boosted linearly to
    ``p_im_max`` at full load."""
    ld = min(max(load, 0.0), 1.0)
    if ld <= 0.6:
        return p.p_amb * (0.13 + 0.83 * ld / 0.6)
    return p.p_amb * 0.96 + (ld - 0.6) / 0.4 * (p.p_im_max - p.p_amb * 0.96)


def throttle_command(load: float, speed: float, p_ic: float, p: SIAirPathParams) -> float:
    """Throttle angle (deg) for a load demand: the ECU's feed-forward inversion of the
    throttle equation for the air flow that the target pressure gives at this speed
    (its own calibration: η_vol 0.9 at 310 K); wide open when the boost is short. The
    angle is continuous in ``p_ic``: the area needed grows without bound as the target
    approaches the boost pressure."""
    target = p_im_target(load, p)
    if target >= p_ic:
        return 90.0
    w = 0.9 * target * p.displacement * speed / 120.0 / (ap.R_AIR * 310.0)
    psi = ap.flow_function(target / p_ic, pr_lin=p.throttle_pr_lin)
    area = w * math.sqrt(ap.R_AIR * (p.T_coolant + 15.0)) / (p_ic * max(psi, 1e-6))
    c = 1.0 - (area - p.throttle_a_leak) / p.throttle_a_max
    return math.degrees(math.acos(min(max(c, 0.0), 1.0 - 1e-9)))


class BoostControl:
    """The ECU's wastegate controller: closed at part load (quick response), a PI loop on
    p_ic towards ``p_im_target + 5 kPa`` (at least 8 % above ambient) when boosting."""

    kp = 2.0e-5
    """Proportional gain, 1/Pa (a 10 kPa over-boost opens the wastegate 20 %)."""
    ki = 1.0e-5
    """Integral gain, 1/(Pa s)."""

    def __init__(self, p: SIAirPathParams) -> None:
        self.p = p
        self.integral = 0.0

    def command(self, load: float, p_ic: float, dt: float) -> float:
        p = self.p
        target = max(p_im_target(load, p) + 5000.0, p.p_amb * 1.08)
        e = p_ic - target
        u = self.kp * e + self.integral
        if 0.0 < u < 1.0 or (u <= 0.0 < e) or (u >= 1.0 and e < 0.0):  # anti-windup
            self.integral = min(max(self.integral + self.ki * e * dt, 0.0), 1.0)
        return min(max(self.kp * e + self.integral, 0.0), 1.0)


def engine_torque(f: Flows, x: Sequence[float], speed: float, lam: float,
                  p: SIAirPathParams) -> tuple[float, float]:
    """Brake torque (N m) and fuel flow (kg/s): gross indicated work of the fuel burnt,
    less pumping (p_em - p_im) and friction (FMEP)."""
    fuel = 0.0 if lam >= FUEL_CUT_LAMBDA else f.w_ac / (max(lam, 0.5) * p.afr_s)
    burnt = min(fuel, f.w_ac / p.afr_s)  # rich: the excess fuel does no work
    omega = max(speed, 1.0) * math.pi / 30.0
    c0, c1, c2 = p.fmep
    fmep = c0 + c1 * speed + c2 * speed * speed
    pmep = x[3] - x[1]
    torque = (p.indicated_efficiency * burnt * p.lhv / omega
              - p.displacement * (fmep + pmep) / (4.0 * math.pi))
    return torque, fuel


# -- the plant ---------------------------------------------------------------------------------
class SIAirPath(Plant):
    """The engine's air path, ECU, actuators and sensors (engine profile ``si-turbo``).

    Consumes the duty cycle (``ENGINE_SPEED``, ``SI_LOAD_DEMAND``) and the engine-out λ
    (``LAMBDA_ENGINE_TRUE``); produces what the catalyst and cylinder plants need
    (exhaust flow and temperature, torque) and the air-path sensors and truth.
    The state is integrated with :func:`rk4` in ``substeps`` sub-steps per plant step.
    It starts in the stationary state of the first inputs it sees (the air path solved
    at the ECU's first throttle angle, then ``settle`` seconds of its own dynamics).
    """

    inputs = ("ENGINE_SPEED", "SI_LOAD_DEMAND", "LAMBDA_ENGINE_TRUE")
    outputs = ("EXH_MASS_FLOW_TRUE", "T_EXH_TRUE", "ENGINE_TORQUE", "FUEL_RATE", "ENGINE_POWER",
               "P_IC", "P_IM", "T_IM", "N_TC", "THROTTLE", "WASTEGATE",
               "P_IC_TRUE", "P_IM_TRUE", "T_IM_TRUE", "P_EM_TRUE", "N_TC_TRUE", "CAC_TRUE")

    def __init__(self, params: SIAirPathParams | None = None, seed: int = 0,
                 name: str = "airpath") -> None:
        self.T_cat_in = 0.0
        p = self.params = params if params is not None else PLANT_PARAMS
        if p.substeps < 1:
            raise ConfigError(f"plant {name}: substeps must be >= 1, got {p.substeps}")
        super().__init__(name, p.period)
        self._rng = np.random.default_rng([seed, 0x3A1])
        self._a_th = lag_factor(p.period, p.tau_throttle)
        self._a_wg = lag_factor(p.period, p.tau_wastegate)
        self._a_T = lag_factor(p.period, p.tau_T_im_sensor)
        self._a_exh = lag_factor(p.period, p.tau_exh)
        self._noise = np.zeros((0, 6))
        self._k_noise = 0
        self.crank_phase = 0.0
        self.x: list[float] = []
        self._rk4 = compiled_rk4(p)

    def _inputs(self, u: Mapping[str, float]) -> tuple[float, float, float]:
        speed = u.get("ENGINE_SPEED", 1800.0)
        load = u.get("SI_LOAD_DEMAND", 0.3)
        lam = u.get("LAMBDA_ENGINE_TRUE", 1.0)
        return speed, load, lam

    def start(self, u: Mapping[str, float]) -> None:
        p = self.params
        speed, load, lam = self._inputs(u)
        self.ecu = BoostControl(p)
        self.alpha, self.u_wg = throttle_command(load, speed, p.p_amb, p), 0.0
        self.x = list(steady_state(p, (self.alpha, self.u_wg, speed, lam)))
        self._u = (self.alpha, self.u_wg, speed, lam)
        for _ in range(round(p.settle / p.period)):  # the ECU's loops settle
            self._advance(speed, load, lam)
        self.T_sensor = self.x[2]
        self.T_cat_in = self._T_cat_in_target(speed, lam)
        self._update()

    def _T_cat_in_target(self, speed: float, lam: float) -> float:
        """Steady catalyst-inlet temperature, °C: issue 8's map
        (:func:`~cell.plant.si_engine.steady_exhaust_temp`) over this engine's relative
        charge (cylinder air over the swept volume at ambient density and η_vol 0.9), so that
        the catalyst sees the temperatures it was built for."""
        p = self.params
        w_ac = flows(self.x, self._u, p).w_ac
        swept = 0.9 * p.p_amb / (ap.R_AIR * p.T_amb) * p.displacement * max(speed, 1.0) / 120.0
        return steady_exhaust_temp(speed, w_ac / swept, lam >= FUEL_CUT_LAMBDA)

    def _advance(self, speed: float, load: float, lam: float) -> None:
        p = self.params
        self.x = self._rk4(self.x, self._u, p.period / p.substeps, p.substeps)
        self.alpha += self._a_th * (throttle_command(load, speed, self.x[0], p) - self.alpha)
        self.u_wg += self._a_wg * (self.ecu.command(load, self.x[0], p.period) - self.u_wg)
        self._u = (self.alpha, self.u_wg, speed, lam)

    def step(self, t: float, u: Mapping[str, float]) -> None:
        p = self.params
        speed, load, lam = self._inputs(u)
        self._advance(speed, load, lam)
        self.T_sensor += self._a_T * (self.x[2] - self.T_sensor)
        self.crank_phase = (self.crank_phase + speed / 60.0 * p.period * p.cylinders / 2.0) % 1.0
        self.T_cat_in += self._a_exh * (self._T_cat_in_target(speed, lam) - self.T_cat_in)
        self._update()

    def _draw(self) -> np.ndarray:
        if self._k_noise >= len(self._noise):
            self._noise = self._rng.standard_normal((1024, 6))
            self._k_noise = 0
        e = self._noise[self._k_noise]
        self._k_noise += 1
        return e

    def _update(self) -> None:
        p, x = self.params, self.x
        alpha, u_wg, speed, lam = self._u
        f = flows(x, self._u, p)
        torque, fuel = engine_torque(f, x, speed, lam, p)
        self.flows = f
        e = self._draw()
        ripple = p.ripple_p_im * x[1] * math.sin(2.0 * math.pi * self.crank_phase)
        self._out = {
            "EXH_MASS_FLOW_TRUE": f.w_eo,
            "T_EXH_TRUE": self.T_cat_in,
            "ENGINE_TORQUE": max(torque, 0.0),
            "FUEL_RATE": fuel * 3600.0 / p.fuel_density,
            "ENGINE_POWER": max(torque, 0.0) * speed * math.pi / 30.0 / 1000.0,
            "P_IC": (x[0] + p.noise_p_ic * e[0]) / 1000.0,
            "P_IM": (x[1] + ripple + p.noise_p_im * e[1]) / 1000.0,
            "T_IM": self.T_sensor + p.noise_T_im * e[2] - 273.15,
            "N_TC": x[4] * RPM_PER_RAD_S + p.noise_n_tc * e[3],
            "THROTTLE": alpha + p.noise_throttle * e[4],
            "WASTEGATE": 100.0 * u_wg + p.noise_wastegate * e[5],
            "P_IC_TRUE": x[0] / 1000.0,
            "P_IM_TRUE": x[1] / 1000.0,
            "T_IM_TRUE": x[2] - 273.15,
            "P_EM_TRUE": x[3] / 1000.0,
            "N_TC_TRUE": x[4] * RPM_PER_RAD_S,
            "CAC_TRUE": f.cac * 1e6,
        }

    def output(self) -> dict[str, float]:
        return self._out
