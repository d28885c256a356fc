r"""Components of a mean-value engine air path, as plain functions (seed 003, section 2).

Seed 003 builds its model from *restrictions in series with adiabatic control volumes*
(section 2, after Eriksson et al. 2002): every restriction (air filter, compressor,
intercooler, throttle, engine, turbine, wastegate, exhaust system) gives a mass flow from
the pressures and temperatures around it, and every control volume integrates the flows
in and out into its pressure (and temperature). The functions below are those parts,
scalar and free of any plant, so that the SI air path (:mod:`cell.plant.si_airpath`), its
observer's model and a diesel air path use the same equations with their own parameters.

Units are SI throughout: Pa, K, kg/s, rad/s, W, m², m³.
"""

from __future__ import annotations

import math

#: Gas constant of air, J/(kg K).
R_AIR = 287.0
#: Ratio of specific heats of air.
GAMMA_AIR = 1.4
#: Specific heat of air at constant pressure, J/(kg K).
CP_AIR = GAMMA_AIR * R_AIR / (GAMMA_AIR - 1.0)
#: Specific heat of air at constant volume, J/(kg K).
CV_AIR = CP_AIR - R_AIR


# -- restrictions ---------------------------------------------------------------------------
def flow_function(pr: float, gamma: float = GAMMA_AIR, pr_lin: float = 0.99) -> float:
    r"""Compressible flow function :math:`\Psi(\Pi)` of a nozzle, :math:`\Pi = p_{down}/p_{up}`.

    .. math::
        \Psi(\Pi) = \sqrt{\tfrac{2\gamma}{\gamma - 1}\big(\Pi^{2/\gamma}
                    - \Pi^{(\gamma+1)/\gamma}\big)}

    choked (constant) below the critical ratio :math:`(2/(\gamma+1))^{\gamma/(\gamma-1)}`,
    and linear in :math:`1 - \Pi` above ``pr_lin``, so that the derivative stays finite as
    the pressure ratio approaches 1 (the usual regularisation of mean-value models; without
    it a linearisation at a small pressure drop has an infinite pole).
    """
    crit = (2.0 / (gamma + 1.0)) ** (gamma / (gamma - 1.0))
    pr = max(pr, crit)
    if pr >= 1.0:
        return 0.0
    k = 2.0 * gamma / (gamma - 1.0)
    if pr > pr_lin:
        psi_lin = math.sqrt(k * (pr_lin ** (2.0 / gamma) - pr_lin ** ((gamma + 1.0) / gamma)))
        return psi_lin * (1.0 - pr) / (1.0 - pr_lin)
    return math.sqrt(k * (pr ** (2.0 / gamma) - pr ** ((gamma + 1.0) / gamma)))


def restriction_flow(area: float, p_up: float, T_up: float, p_down: float,
                     R: float = R_AIR, gamma: float = GAMMA_AIR, pr_lin: float = 0.99) -> float:
    r"""Mass flow through a compressible restriction (throttle, wastegate), kg/s.

    .. math:: W = \frac{A\, p_{up}}{\sqrt{R\, T_{up}}}\, \Psi(p_{down} / p_{up})

    ``area`` is the effective area (discharge coefficient included). A pressure ratio above
    1 gives reverse flow with the roles of the two sides swapped (at the upstream
    temperature, a simplification for the short reversals a mean-value model sees).
    """
    if p_down <= p_up:
        return area * p_up / math.sqrt(R * T_up) * flow_function(p_down / p_up, gamma, pr_lin)
    return -area * p_down / math.sqrt(R * T_up) * flow_function(p_up / p_down, gamma, pr_lin)


def incompressible_drop(flow: float, k: float) -> float:
    r"""Pressure drop over an incompressible restriction (air filter, intercooler, exhaust
    system), Pa: :math:`\Delta p = k\, W |W|`."""
    return k * flow * abs(flow)


def throttle_area(alpha_deg: float, a_max: float, a_leak: float) -> float:
    r"""Effective throttle area, m², for a plate angle in degrees (0 closed, 90 open):
    :math:`A = A_{max}(1 - \cos\alpha) + A_{leak}`."""
    a = min(max(alpha_deg, 0.0), 90.0)
    return a_max * (1.0 - math.cos(math.radians(a))) + a_leak


# -- compressor -----------------------------------------------------------------------------
def compressor_flow(omega: float, pr: float, p_in: float, T_in: float, *, w_ref: float,
                    omega_ref: float, k_pr: float, p_ref: float = 101_325.0,
                    T_ref: float = 298.0, offset: float = 0.0) -> float:
    r"""Compressor mass flow from a simple map: speed lines that are parabolas in the
    pressure ratio, kg/s.

    .. math::
        W_c = \frac{p_{in}}{p_{ref}}\sqrt{\frac{T_{ref}}{T_{in}}}\;
              W_{ref} \frac{\omega}{\omega_{ref}}\,(1 - r|r|) + W_{off}, \qquad
        r = \frac{\Pi - 1}{\Pi_0(\omega) - 1}, \quad
        \Pi_0(\omega) = 1 + k_\Pi \Big(\frac{\omega}{\omega_{ref}}\Big)^2

    :math:`\Pi_0` is the zero-flow (surge-side) pressure ratio of the speed line, which
    rises with the square of the tip speed (Euler's turbomachine equation). Below a
    pressure ratio of 1 the compressor passes more than its line's maximum, like a
    restriction (:math:`r < 0`, clipped at -3); the map is continuously differentiable.
    ``offset`` is the flow offset by which an observer's model may be wrong (seed 003's
    model-versus-engine errors).
    """
    pr0 = 1.0 + k_pr * (omega / omega_ref) ** 2
    r = min(max((pr - 1.0) / max(pr0 - 1.0, 0.02), -3.0), 1.0)
    w_max = w_ref * max(omega, 0.0) / omega_ref * (p_in / p_ref) * math.sqrt(T_ref / T_in)
    return w_max * (1.0 - r * abs(r)) + offset


def compressor_outlet_temperature(T_in: float, pr: float, efficiency: float,
                                  gamma: float = GAMMA_AIR) -> float:
    r"""Outlet temperature, K: :math:`T_c = T_{in}\big(1 + (\Pi^{(\gamma-1)/\gamma} - 1)/\eta_c\big)`."""
    return T_in * (1.0 + (max(pr, 1e-3) ** ((gamma - 1.0) / gamma) - 1.0) / efficiency)


def compressor_power(flow: float, T_in: float, T_out: float, cp: float = CP_AIR) -> float:
    r"""Power absorbed by the compressor, W: :math:`P_c = W_c c_p (T_c - T_{in})`."""
    return flow * cp * (T_out - T_in)


# -- intercooler ----------------------------------------------------------------------------
def intercooler_temperature(T_in: float, T_coolant: float, effectiveness: float) -> float:
    r"""Outlet temperature of a heat exchanger of given effectiveness, K:
    :math:`T_{ic} = T_c - \varepsilon (T_c - T_{cool})`."""
    return T_in - effectiveness * (T_in - T_coolant)


# -- control volumes ------------------------------------------------------------------------
def isothermal_volume(p_dot_gain: float, w_in: float, w_out: float) -> float:
    r"""Pressure derivative of an isothermal control volume, Pa/s:
    :math:`\dot p = \frac{R T}{V}(W_{in} - W_{out})` with ``p_dot_gain`` = :math:`R T / V`."""
    return p_dot_gain * (w_in - w_out)


def adiabatic_volume(p: float, T: float, volume: float, w_in: float, T_in: float, w_out: float,
                     heat: float = 0.0, R: float = R_AIR, gamma: float = GAMMA_AIR
                     ) -> tuple[float, float]:
    r"""Pressure and temperature derivatives of an adiabatic control volume.

    Mass and energy balance of an ideal gas in a fixed volume (Eriksson et al. 2002, used
    by seed 003 for every volume):

    .. math::
        \dot p = \frac{\gamma R}{V}\big(W_{in} T_{in} - W_{out} T\big)
                 + \frac{\gamma - 1}{V}\dot Q, \qquad
        \dot T = \frac{R T}{p V c_v}\Big(W_{in}(c_p T_{in} - c_v T) - R\, W_{out} T
                 + \dot Q\Big)

    ``heat`` is the heat flow into the gas, W (wall heat transfer; 0 for the adiabatic
    volume of the paper).
    """
    cv = R / (gamma - 1.0)
    cp = cv + R
    p_dot = gamma * R / volume * (w_in * T_in - w_out * T) + (gamma - 1.0) / volume * heat
    T_dot = R * T / (p * volume * cv) * (w_in * (cp * T_in - cv * T) - R * w_out * T + heat)
    return p_dot, T_dot


# -- engine ---------------------------------------------------------------------------------
def volumetric_efficiency(c_eta_vol: float, p_im: float, p_em: float, r_c: float,
                          gamma_e: float, speed_rps: float = 0.0, speed_ref: float = 30.0,
                          speed_shape: float = 0.0) -> float:
    r"""Volumetric efficiency with the exhaust back-pressure effect (seed 003, eq. 1).

    .. math::
        \eta_{vol} = C_{\eta vol}\,\frac{r_c - (p_{em}/p_{im})^{1/\gamma_e}}{r_c - 1}\,
                     \big(1 - k_N (N/N_{ref} - 1)^2\big)

    the residual gas left at exhaust pressure re-expands to intake pressure and takes that
    much of the swept volume (Andersson & Eriksson 2004); ``speed_shape`` :math:`k_N` bends
    it over speed (ram and throttling effects of the runners).
    """
    ratio = max(p_em / p_im, 1e-3) ** (1.0 / gamma_e)
    shape = 1.0 - speed_shape * (speed_rps / speed_ref - 1.0) ** 2
    return c_eta_vol * (r_c - ratio) / (r_c - 1.0) * shape


def cylinder_air_charge(eta_vol: float, p_im: float, T_im: float, v_cyl: float, lam: float,
                        afr_s: float, c1: float = 0.0, R: float = R_AIR) -> float:
    r"""Cylinder air charge, kg of air per cylinder and cycle (seed 003, eq. 1).

    .. math::
        CAC = \eta_{vol}\,\frac{p_{im} V_d / n_{cyl}}{R\, T_{im}}\,
              \frac{1 + C_1/(\lambda (A/F)_s)}{1 + 1/(\lambda (A/F)_s)}

    The fuel vapour takes part of the charge volume (denominator); its evaporation cools
    the charge and lets in a little more air (charge-cooling parameter :math:`C_1`). At
    fuel cut (:math:`\lambda \to \infty`) both factors are 1.
    """
    inv = 1.0 / (max(lam, 0.05) * afr_s)
    return eta_vol * p_im * v_cyl / (R * T_im) * (1.0 + c1 * inv) / (1.0 + inv)


def engine_air_flow(cac: float, n_cyl: int, speed_rps: float, n_r: float = 2.0) -> float:
    r"""Air mass flow into the cylinders, kg/s: :math:`W_{ac} = CAC\, n_{cyl} N / n_r`."""
    return cac * n_cyl * speed_rps / n_r


# -- turbine, wastegate, shaft ---------------------------------------------------------------
def turbine_flow(p_em: float, T_em: float, p_es: float, area: float, k1: float = 1.5,
                 R: float = R_AIR, lin: float = 0.02) -> float:
    r"""Turbine mass flow, kg/s: the turbine as a restriction with the standard
    "square-root" characteristic.

    .. math:: W_t = \frac{A_t\, p_{em}}{\sqrt{R T_{em}}}\sqrt{1 - \Pi_t^{k_1}}, \qquad
              \Pi_t = p_{es}/p_{em}

    linear in :math:`1 - \Pi_t^{k_1}` below ``lin`` (finite derivative at zero flow), and
    zero for a reversed pressure ratio.
    """
    z = 1.0 - min(p_es / p_em, 1.0) ** k1
    root = math.sqrt(z) if z >= lin else z / math.sqrt(lin)
    return area * p_em / math.sqrt(R * T_em) * root


def turbine_power(flow: float, T_in: float, pr: float, efficiency: float, cp: float,
                  gamma: float) -> float:
    r"""Power delivered by the turbine, W:
    :math:`P_t = W_t c_{p} T_{em} \eta_t (1 - \Pi_t^{(\gamma-1)/\gamma})`."""
    return flow * cp * T_in * efficiency * (1.0 - min(pr, 1.0) ** ((gamma - 1.0) / gamma))


def shaft_acceleration(p_turbine: float, p_compressor: float, omega: float, inertia: float,
                       mech_efficiency: float, friction: float = 0.0,
                       omega_min: float = 500.0) -> float:
    r"""Turbo shaft power balance, rad/s²:

    .. math:: \dot\omega_{tc} = \frac{\eta_m P_t - P_c}{J\,\omega_{tc}} - \frac{k_f}{J}\omega_{tc}

    (``omega`` is floored at ``omega_min`` in the division: the balance is one of power,
    singular at standstill).
    """
    return (mech_efficiency * p_turbine - p_compressor) / (inertia * max(omega, omega_min)) \
        - friction * omega / inertia


__all__ = ["CP_AIR", "CV_AIR", "GAMMA_AIR", "R_AIR", "adiabatic_volume", "compressor_flow",
           "compressor_outlet_temperature", "compressor_power", "cylinder_air_charge",
           "engine_air_flow", "flow_function", "incompressible_drop", "intercooler_temperature",
           "isothermal_volume", "restriction_flow", "shaft_acceleration", "throttle_area",
           "turbine_flow", "turbine_power", "volumetric_efficiency"]


# -- the diesel air path's additions (seed 002, Appendix A; issue 11) -------------------------
#: Gas constant of exhaust gas, J/(kg K).
R_EXH = 286.0
#: Ratio of specific heats of exhaust gas.
GAMMA_EXH = 1.3
#: Specific heat of exhaust gas at constant pressure, J/(kg K).
CP_EXH = 1150.0


def compressor_head(pr: float, omega: float, radius: float, T_in: float, cp: float = CP_AIR,
                    gamma: float = GAMMA_AIR) -> float:
    r"""Energy transfer (head) coefficient of a compressor (Wahlström & Eriksson 2006):

    .. math:: \Psi_c = \frac{2 c_p T_{in} (\Pi^{(\gamma-1)/\gamma} - 1)}{U^2}, \qquad U = r\,\omega

    :math:`U` is the blade tip speed (floored at 1 m/s).
    """
    u = max(radius * omega, 1.0)
    return 2.0 * cp * T_in * (max(pr, 1e-6) ** ((gamma - 1.0) / gamma) - 1.0) / (u * u)


def compressor_map_flow(pr: float, omega: float, radius: float, psi_max: float, phi_max: float,
                        p_in: float, T_in: float, R: float = R_AIR) -> float:
    r"""Compressor mass flow from a head/flow-coefficient map (Wahlström & Eriksson 2006), kg/s.

    The flow coefficient falls on a parabola in the head coefficient (a smooth variant of
    W&E's ellipse that also holds for :math:`\Pi < 1`), zero beyond :math:`\Psi_{max}` (the
    surge line):

    .. math:: \Phi_c = \Phi_{max}(1 - s|s|), \quad s = \Psi_c/\Psi_{max}, \qquad
              W_c = \Phi_c\, \rho_{in}\, \pi r^2 U
    """
    s = compressor_head(pr, omega, radius, T_in) / psi_max
    phi = max(phi_max * (1.0 - s * abs(s)), 0.0)
    return phi * p_in / (R * T_in) * math.pi * radius * radius * max(radius * omega, 1.0)


def cylinder_flow(eta_vol: float, p_im: float, T_im: float, speed_rpm: float,
                  displacement: float, R: float = R_AIR) -> float:
    r"""Gas flow into the cylinders of a four-stroke diesel, kg/s (speed-density):

    .. math:: W_{ei} = \frac{\eta_{vol}\, p_{im}\, N\, V_d}{120\, R\, T_{im}}
    """
    return eta_vol * p_im * speed_rpm * displacement / (120.0 * R * T_im)


__all__ += ["CP_EXH", "GAMMA_EXH", "R_EXH", "compressor_head", "compressor_map_flow",
            "cylinder_flow"]
