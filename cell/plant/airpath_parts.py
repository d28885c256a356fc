r"""Components of a mean-value engine air path, as plain functions.

These are the building blocks of a mean-value air-path model after Wahlström & Eriksson
(2006), the model seed 002 (Appendix A) simplifies to three states. They are plain functions
over floats in SI units (Pa, K, kg/s, rad/s, W), so a simulator plant and an observer's
model call the same equations with their own parameters (STYLE.md, "a plant is not a
model").

========================================  =================================================
function                                  equation
========================================  =================================================
:func:`orifice_psi`                       isentropic restriction flow function (choked below
                                          the critical pressure ratio)
:func:`orifice_flow`                      compressible flow through a restriction (EGR valve)
:func:`turbine_flow`                      VGT flow, :math:`\sqrt{1 - \Pi_t^{K_t}}`
:func:`turbine_power`, :func:`compressor_power`   isentropic power with efficiency
:func:`compressor_flow`                   compressor map, head/flow-coefficient parabola
:func:`cylinder_flow`                     speed-density (volumetric efficiency) flow
:func:`pressure_derivative`               isothermal control-volume mass balance
:func:`shaft_acceleration`                turbocharger shaft power balance
========================================  =================================================

Near a pressure ratio of one the square-root flow functions have an infinite slope; they
are continued linearly below a small pressure drop (``lin``), which keeps an EKF's Jacobian
finite and the flow continuous.
"""

from __future__ import annotations

import math

#: Gas constant of air, J/(kg K).
R_AIR = 287.0
#: Gas constant of exhaust gas, J/(kg K).
R_EXH = 286.0
#: Specific heat at constant pressure of air, J/(kg K).
CP_AIR = 1005.0
#: Specific heat at constant pressure of exhaust gas, J/(kg K).
CP_EXH = 1150.0
#: Ratio of specific heats of air.
GAMMA_AIR = 1.4
#: Ratio of specific heats of exhaust gas.
GAMMA_EXH = 1.3


def orifice_psi(pr: float, gamma: float = GAMMA_EXH, lin: float = 0.01) -> float:
    r"""Isentropic restriction flow function :math:`\Psi(\Pi)` (W&E 2006, eq. 31 form).

    .. math::
        \Psi(\Pi) = \sqrt{\tfrac{2\gamma}{\gamma-1}\left(\Pi^{2/\gamma} -
        \Pi^{(\gamma+1)/\gamma}\right)}, \qquad
        \Pi_\mathrm{crit} = \left(\tfrac{2}{\gamma+1}\right)^{\gamma/(\gamma-1)}

    constant (choked) below :math:`\Pi_\mathrm{crit}`, continued linearly to 0 at
    :math:`\Pi = 1` above ``1 - lin``, and 0 for :math:`\Pi \ge 1` (no reverse flow).
    """
    crit = (2.0 / (gamma + 1.0)) ** (gamma / (gamma - 1.0))
    if pr >= 1.0:
        return 0.0
    k = 2.0 * gamma / (gamma - 1.0)
    if pr > 1.0 - lin:
        p0 = 1.0 - lin
        psi0 = math.sqrt(k * (p0 ** (2.0 / gamma) - p0 ** ((gamma + 1.0) / gamma)))
        return psi0 * (1.0 - pr) / lin
    pr = max(pr, crit)
    return math.sqrt(k * (pr ** (2.0 / gamma) - pr ** ((gamma + 1.0) / gamma)))


def orifice_flow(area: float, p_up: float, t_up: float, p_down: float, r_gas: float = R_EXH,
                 gamma: float = GAMMA_EXH) -> float:
    r"""Compressible flow through a restriction of effective ``area`` m², kg/s.

    .. math:: W = \frac{A\, p_\mathrm{up}}{\sqrt{R\, T_\mathrm{up}}}\,
              \Psi\!\left(\frac{p_\mathrm{down}}{p_\mathrm{up}}\right)

    (Wahlström & Eriksson 2006, the EGR valve; :func:`orifice_psi`).
    """
    if p_up <= 0.0 or area <= 0.0:
        return 0.0
    return area * p_up / math.sqrt(r_gas * t_up) * orifice_psi(p_down / p_up, gamma)


def turbine_flow(area: float, p_in: float, t_in: float, p_out: float, k_t: float,
                 r_gas: float = R_EXH, lin: float = 0.02) -> float:
    r"""Mass flow through a variable-geometry turbine, kg/s (W&E 2006, VGT flow model).

    .. math:: W_t = \frac{A_\mathrm{vgt}\, p_\mathrm{em}}{\sqrt{R_e T_\mathrm{em}}}
              \sqrt{1 - \Pi_t^{K_t}}, \qquad \Pi_t = p_\mathrm{out} / p_\mathrm{em}

    The turbine is not choked: its flow falls as the outlet pressure rises, which is how an
    exhaust back-pressure raises the exhaust manifold pressure. Below a drop of ``lin`` in
    :math:`1 - \Pi_t^{K_t}` the root is continued linearly (and negative for reverse flow).
    """
    if p_in <= 0.0:
        return 0.0
    s = 1.0 - (p_out / p_in) ** k_t if p_out > 0.0 else 1.0
    root = math.sqrt(s) if s >= lin else s / math.sqrt(lin)
    return area * p_in / math.sqrt(r_gas * t_in) * root


def turbine_power(flow: float, t_in: float, pr: float, eta: float, cp: float = CP_EXH,
                  gamma: float = GAMMA_EXH) -> float:
    r"""Power delivered by a turbine expanding ``flow`` kg/s from ``t_in`` K by ``pr`` = p_out/p_in, W.

    .. math:: P_t\,\eta = \eta\, W_t\, c_{p,e}\, T_\mathrm{em}
              \left(1 - \Pi_t^{(\gamma_e-1)/\gamma_e}\right)
    """
    pr = min(max(pr, 1e-6), 1.0)
    return eta * flow * cp * t_in * (1.0 - pr ** ((gamma - 1.0) / gamma))


def compressor_power(flow: float, t_in: float, pr: float, eta: float, cp: float = CP_AIR,
                     gamma: float = GAMMA_AIR) -> float:
    r"""Power absorbed by a compressor raising ``flow`` kg/s by ``pr`` = p_out/p_in, W.

    .. math:: P_c = \frac{W_c\, c_{p,a}\, T_\mathrm{amb}}{\eta_c}
              \left(\Pi_c^{(\gamma_a-1)/\gamma_a} - 1\right)
    """
    return flow * cp * t_in * (max(pr, 1e-6) ** ((gamma - 1.0) / gamma) - 1.0) / eta


def compressor_head(pr: float, omega: float, radius: float, t_in: float, cp: float = CP_AIR,
                    gamma: float = GAMMA_AIR) -> float:
    r"""Energy transfer (head) coefficient :math:`\Psi_c = 2 c_p T (\Pi^{(\gamma-1)/\gamma}-1) / U^2`,
    :math:`U = r\,\omega` the blade tip speed (W&E 2006, compressor map)."""
    u = max(radius * omega, 1.0)
    return 2.0 * cp * t_in * (max(pr, 1e-6) ** ((gamma - 1.0) / gamma) - 1.0) / (u * u)


def compressor_flow(pr: float, omega: float, radius: float, psi_max: float, phi_max: float,
                    p_in: float, t_in: float, r_gas: float = R_AIR) -> float:
    r"""Compressor mass flow from its map, kg/s.

    The flow coefficient falls on a parabola in the head coefficient (a smooth variant of
    W&E 2006's ellipse, valid also for :math:`\Pi_c < 1`):

    .. math:: \Phi_c = \Phi_\mathrm{max}\,(1 - s|s|), \quad s = \Psi_c / \Psi_\mathrm{max},
              \qquad W_c = \Phi_c\, \rho_\mathrm{amb}\, \pi r^2 U

    and is zero beyond :math:`\Psi_\mathrm{max}` (the surge line).
    """
    s = compressor_head(pr, omega, radius, t_in) / psi_max
    phi = max(phi_max * (1.0 - s * abs(s)), 0.0)
    rho = p_in / (r_gas * t_in)
    return phi * rho * math.pi * radius * radius * max(radius * omega, 1.0)


def cylinder_flow(eta_vol: float, p_im: float, t_im: float, speed_rpm: float,
                  displacement: float, r_gas: float = R_AIR) -> float:
    r"""Gas flow into the cylinders of a four-stroke engine, kg/s (speed-density).

    .. math:: W_\mathrm{ei} = \frac{\eta_\mathrm{vol}\, p_\mathrm{im}\, N\, V_d}{120\, R_a T_\mathrm{im}}
    """
    return eta_vol * p_im * speed_rpm * displacement / (120.0 * r_gas * t_im)


def pressure_derivative(r_gas: float, temp: float, volume: float, flow_in: float,
                        flow_out: float) -> float:
    r"""Isothermal control volume (W&E 2006, manifold models), Pa/s.

    .. math:: \frac{dp}{dt} = \frac{R\, T}{V}\,(W_\mathrm{in} - W_\mathrm{out})
    """
    return r_gas * temp / volume * (flow_in - flow_out)


def shaft_acceleration(p_turbine: float, p_compressor: float, inertia: float, omega: float,
                       omega_min: float = 100.0) -> float:
    r"""Turbocharger shaft power balance, rad/s² (W&E 2006, turbo model).

    .. math:: \frac{d\omega_t}{dt} = \frac{P_t \eta_m - P_c}{J_t\, \omega_t}

    with :math:`\omega_t` floored at ``omega_min`` (the balance is singular at standstill).
    """
    return (p_turbine - p_compressor) / (inertia * max(omega, omega_min))


__all__ = [
    "CP_AIR", "CP_EXH", "GAMMA_AIR", "GAMMA_EXH", "R_AIR", "R_EXH",
    "compressor_flow", "compressor_head", "compressor_power", "cylinder_flow", "orifice_flow",
    "orifice_psi", "pressure_derivative", "shaft_acceleration", "turbine_flow", "turbine_power",
]
