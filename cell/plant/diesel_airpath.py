r"""The large diesel's air path: seed 002's third-order mean-value model (Appendix A).

States (seed 002, §6 and Appendix A; after Wahlström & Eriksson 2006 without the EGR mass
fractions and the actuator dynamics):

- :math:`x_1 = p_\mathrm{im}`, intake manifold pressure, kPa;
- :math:`x_2 = p_\mathrm{em}`, exhaust manifold pressure, kPa;
- :math:`x_3 = n_t`, turbocharger speed, krpm.

Inputs: fuel (``FUEL_RATE``, L/h), engine speed (``ENGINE_SPEED``, rpm), VGT position
(``VGT_POS``, % open) and EGR valve position (``EGR_POS``, % open), and the pressure at the
turbine outlet: ambient plus the exhaust back-pressure of the two banks (``EXH_BP_L``,
``EXH_BP_R``, mmH2O; the truth in the plant, the sensors in an observer). Closing the
back-pressure valve therefore raises :math:`p_\mathrm{em}`.

.. math::
    \dot p_\mathrm{im} &= \tfrac{R_a T_\mathrm{im}}{V_\mathrm{im}}(W_c + W_\mathrm{egr} - W_\mathrm{ei}) \\
    \dot p_\mathrm{em} &= \tfrac{R_e T_\mathrm{em}}{V_\mathrm{em}}
        (W_\mathrm{ei} + W_f - W_t - W_\mathrm{egr}) \\
    \dot\omega_t &= \frac{P_t\eta_m - P_c}{J_t\,\omega_t}

with the components of :mod:`cell.plant.airpath_parts`. :func:`airpath_rhs` is
``f(t, x, u, params)``: the plant integrates it with :class:`AirPathParams` carrying the
engine's true, slowly drifting biases (:class:`Biases`); the observers of
:mod:`cell.estimators.diesel_airpath` integrate it with the nominal parameters (the
*default model* of seed 002, §2), which is therefore wrong in the stationary way the
paper's method compensates.

The plant also holds the engine's air-path controllers: the VGT tracks a boost set-point
(a feed-forward map plus a PI correction) and the EGR valve follows a map of speed and
fuel; both are measured (``VGT_POS``, ``EGR_POS``) as the paper's inputs are.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import fsolve

from cell.plant.airpath_parts import (
    CP_AIR,
    CP_EXH,
    GAMMA_EXH,
    R_AIR,
    R_EXH,
    compressor_map_flow,
    compressor_outlet_temperature,
    compressor_power,
    cylinder_flow,
    isothermal_volume,
    restriction_flow,
    shaft_acceleration,
    turbine_flow,
    turbine_power,
)
from cell.plant.base import Plant, lag_factor

#: Pa per mmH2O.
PA_PER_MMH2O = 9.80665
#: rad/s per krpm.
RADS_PER_KRPM = 1000.0 * 2.0 * math.pi / 60.0

#: Model state names (seed 002's x_1, x_2, x_3) and their units.
STATES = ("P_IM", "P_EM", "N_T")
UNITS = {"P_IM": "kPa", "P_EM": "kPa", "N_T": "krpm"}
#: The bus signal of each state: its sensor, and with ``_TRUE``, ``_EST`` and
#: ``_EST_DEFAULT`` its truth and estimates. The SI air path (seed 003) owns ``P_IM``,
#: ``P_IM_TRUE``, ``P_EM_TRUE``, ``P_IM_EST`` and ``P_EM_EST`` and the DBC files need unique
#: names, so the diesel's manifold pressures are ``DSL_P_IM`` and ``DSL_P_EM``.
SIGNAL = {"P_IM": "DSL_P_IM", "P_EM": "DSL_P_EM", "N_T": "N_T"}
#: Model inputs, in the order of ``u``: the channel names they are read from.
INPUTS = ("FUEL_RATE", "ENGINE_SPEED", "VGT_POS", "EGR_POS", "EXH_BP_L", "EXH_BP_R")


@dataclass(frozen=True)
class AirPathParams:
    """Constants of the air path; the nominal values are the observers' *default model*.

    Sized for the 60 L engine of :class:`~cell.plant.diesel.EngineParams` (2 MW at
    1800 rpm, compressor pressure ratio 3.3 at rated), with one equivalent turbocharger
    standing for the engine's turbochargers.
    """

    p_amb: float = 101_325.0
    """Ambient pressure, Pa."""
    t_amb: float = 298.15
    """Ambient (compressor inlet) temperature, K; as :class:`EngineParams.ambient_temp`."""
    t_im: float = 323.15
    """Intake manifold temperature after the charge-air cooler, K (held; W&E treat it as
    measured)."""
    v_im: float = 0.15
    """Intake manifold plus charge-air cooler volume, m³ (2.5 x displacement)."""
    v_em: float = 0.08
    """Exhaust manifold volume to the turbine, m³."""
    displacement: float = 0.060
    """Swept volume, m³."""
    eta_vol: float = 0.95
    """Volumetric efficiency (as :class:`EngineParams.volumetric_efficiency`)."""
    fuel_density: float = 0.84
    """kg/L."""
    exhaust_heat: float = 12.0e6
    """Heat per kg of fuel that ends up as exhaust enthalpy above the intake temperature,
    J/kg: 28 % of the lower heating value (42.9 MJ/kg). Gives about 440 °C at rated."""
    a_vgt_max: float = 5.5e-3
    """Effective VGT area fully open, m²; it closes to ``vgt_min_frac`` of it."""
    vgt_min_frac: float = 0.15
    """Effective area of the closed VGT as a fraction of the open one."""
    k_t: float = 1.5
    """Exponent of the turbine flow function, :math:`\\sqrt{1 - \\Pi_t^{K_t}}`."""
    a_egr_max: float = 1.4e-3
    """Effective EGR valve area fully open, m²."""
    eta_t_max: float = 0.72
    """Peak turbine efficiency times mechanical efficiency."""
    bsr_opt: float = 0.65
    """Blade-speed ratio of peak turbine efficiency."""
    c_bsr: float = 0.9
    """Curvature of turbine efficiency in the blade-speed ratio."""
    r_t: float = 0.13
    """Turbine wheel radius, m."""
    r_c: float = 0.12
    """Compressor wheel radius, m."""
    inertia: float = 0.03
    """Turbocharger shaft inertia, kg m²."""
    psi_max: float = 1.1
    """Head coefficient at zero flow (surge line)."""
    phi_max: float = 0.2
    """Flow coefficient at zero head."""
    eta_c_max: float = 0.78
    """Peak compressor efficiency."""
    c_eta_c: float = 0.8
    """Curvature of compressor efficiency in the relative flow coefficient."""
    # -- the biases of the real engine against this default model (1 = none) -------------
    egr_flow: float = 1.0
    """EGR flow factor (a fouled EGR cooler passes less)."""
    eta_c_factor: float = 1.0
    """Compressor efficiency factor (drift)."""
    turbine_flow_factor: float = 1.0
    """Turbine map flow factor (map offset)."""
    eta_t_factor: float = 1.0
    """Turbine efficiency factor (map offset)."""


@dataclass(frozen=True)
class Biases:
    """How the simulated engine differs from the default model: slowly varying biases.

    Each factor is ``mean + amp * sin(2 pi t / period + phase)``; the observers do not
    know them (seed 002, §2: "the model captures dynamic behavior reasonably well but
    suffers from stationary errors").
    """

    egr_fouling: float = 0.78
    """Mean EGR flow factor: a fouled EGR cooler passes 22 % less at a given valve area."""
    egr_amp: float = 0.04
    eta_c_drift: float = 0.93
    """Mean compressor efficiency factor: 7 % below the map."""
    eta_c_amp: float = 0.02
    turbine_offset: float = 1.06
    """Mean turbine flow factor: the turbine map's flow is 6 % low."""
    turbine_amp: float = 0.02
    eta_t_offset: float = 0.95
    """Mean turbine efficiency factor."""
    period: float = 900.0
    """Period of the slow variation, s (a few minutes: slow against the dynamics)."""

    def at(self, t: float) -> dict[str, float]:
        """The factors of :class:`AirPathParams` at time ``t``."""
        w = 2.0 * math.pi * t / self.period
        return {"egr_flow": self.egr_fouling + self.egr_amp * math.sin(w),
                "eta_c_factor": self.eta_c_drift + self.eta_c_amp * math.sin(w + 1.0),
                "turbine_flow_factor": self.turbine_offset + self.turbine_amp * math.sin(w + 2.0),
                "eta_t_factor": self.eta_t_offset}


#: No bias: the simulated engine equals the default model.
NO_BIAS = Biases(1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0)


def _flows(x, u, p: AirPathParams) -> tuple[float, ...]:
    """Flows, temperatures and powers at state ``x`` and input ``u`` (SI units)."""
    x0, x1, x2 = x.tolist()[:3] if isinstance(x, np.ndarray) else map(float, x[:3])
    p_im = x0 * 1e3
    p_em = x1 * 1e3
    omega = max(x2, 0.0) * RADS_PER_KRPM
    fuel_lph, speed, vgt, egr, bp_l, bp_r = u.tolist() if isinstance(u, np.ndarray) else map(float, u)
    w_f = max(fuel_lph, 0.0) * p.fuel_density / 3600.0
    p_es = p.p_amb + 0.5 * (bp_l + bp_r) * PA_PER_MMH2O
    w_ei = cylinder_flow(p.eta_vol, max(p_im, 0.0), p.t_im, max(speed, 0.0), p.displacement)
    w_eo = w_ei + w_f
    t_em = p.t_im + p.exhaust_heat * w_f / (CP_EXH * max(w_eo, 1e-3))
    a_egr = p.a_egr_max * p.egr_flow * min(max(egr, 0.0), 100.0) / 100.0
    # EGR flows from the exhaust to the intake manifold only (a reverse flow is cut off)
    w_egr = max(restriction_flow(a_egr, p_em, t_em, p_im, R_EXH, GAMMA_EXH), 0.0)
    vgt_frac = p.vgt_min_frac + (1.0 - p.vgt_min_frac) * min(max(vgt, 0.0), 100.0) / 100.0
    a_vgt = p.a_vgt_max * p.turbine_flow_factor * vgt_frac
    w_t = turbine_flow(p_em, t_em, p_es, a_vgt, p.k_t, R_EXH)
    pr_t = p_es / max(p_em, 1.0)
    dh = 2.0 * CP_EXH * t_em * max(1.0 - min(pr_t, 1.0) ** ((GAMMA_EXH - 1.0) / GAMMA_EXH), 1e-6)
    bsr = p.r_t * omega / math.sqrt(dh)
    eta_t = p.eta_t_factor * max(p.eta_t_max * (1.0 - p.c_bsr * (bsr / p.bsr_opt - 1.0) ** 2), 0.2)
    pt = turbine_power(max(w_t, 0.0), t_em, max(pr_t, 1e-6), eta_t, CP_EXH, GAMMA_EXH)
    pr_c = p_im / p.p_amb
    w_c = compressor_map_flow(pr_c, omega, p.r_c, p.psi_max, p.phi_max, p.p_amb, p.t_amb)
    rho = p.p_amb / (R_AIR * p.t_amb)
    phi_rel = w_c / (rho * math.pi * p.r_c ** 2 * max(p.r_c * omega, 1.0)) / p.phi_max
    eta_c = p.eta_c_factor * max(p.eta_c_max * (1.0 - p.c_eta_c * (phi_rel - 0.55) ** 2), 0.3)
    if pr_c > 1.0:
        pc = compressor_power(w_c, p.t_amb, compressor_outlet_temperature(p.t_amb, pr_c, eta_c),
                              CP_AIR)
    else:
        pc = 0.0
    return w_c, w_egr, w_ei, w_f, w_t, t_em, pt, pc, omega


def airpath_rhs(t: float, x, u, p: AirPathParams) -> np.ndarray:
    """``f(t, x, u, params)``: d/dt of (p_im kPa, p_em kPa, n_t krpm) (seed 002, App. A)."""
    w_c, w_egr, w_ei, w_f, w_t, t_em, pt, pc, omega = _flows(x, u, p)
    return np.array([
        isothermal_volume(R_AIR * p.t_im / p.v_im, w_c + w_egr, w_ei) * 1e-3,
        isothermal_volume(R_EXH * t_em / p.v_em, w_ei + w_f, w_t + w_egr) * 1e-3,
        shaft_acceleration(pt, pc, omega, p.inertia, 1.0, omega_min=100.0) / RADS_PER_KRPM,
    ])


def airpath_jacobian(t: float, x, u, p: AirPathParams, f0: np.ndarray | None = None
                     ) -> np.ndarray:
    """:math:`A = \\partial f/\\partial x` by forward differences (steps of 1e-4 kPa and
    1e-5 krpm): three evaluations of :func:`airpath_rhs` besides ``f0`` (the value at ``x``,
    computed when not given), cheap enough for 100 Hz."""
    x = np.asarray(x, dtype=float)[:3]
    if f0 is None:
        f0 = airpath_rhs(t, x, u, p)
    out = np.empty((3, 3))
    for j, h in enumerate((1e-4, 1e-4, 1e-5)):
        xh = x.copy()
        xh[j] += h
        out[:, j] = (airpath_rhs(t, xh, u, p) - f0) / h
    return out


def airpath_output(t: float, x, u, p: AirPathParams) -> np.ndarray:
    """``h(t, x, u, params)``: the state itself (P_IM, P_EM, N_T sensors; C = I)."""
    return np.asarray(x, dtype=float)[:3].copy()


def egr_flow_of(x, u, p: AirPathParams) -> float:
    """EGR mass flow at ``(x, u)``, kg/s (for figures and checks)."""
    return _flows(x, u, p)[1]


@dataclass(frozen=True)
class ControlParams:
    """The engine's own air-path controllers (their outputs are the measured positions)."""

    boost_rated: float = 3.3
    """Boost pressure ratio set-point at rated (:class:`EngineParams`)."""
    vgt_kp: float = 0.25
    """VGT proportional gain, % per kPa of boost error (negative action: close to boost)."""
    vgt_ki: float = 0.08
    """VGT integral gain, % per kPa s."""
    tau_actuator: float = 0.15
    """VGT and EGR actuator time constant, s."""
    egr_max: float = 55.0
    """EGR opening at low load, %."""
    egr_min: float = 12.0
    """EGR opening at full load, %."""


class DieselAirPath(Plant):
    """The simulated air path of the large diesel (seed 002, Appendix A).

    Parameters
    ----------
    params:
        The engine's air-path constants (:class:`AirPathParams`, nominal = default model).
    biases:
        The slowly varying biases of the engine against the default model.
    control:
        The VGT and EGR controllers.
    pem_sensor:
        Whether the exhaust manifold pressure has a sensor (``DSL_P_EM``). Seed 002, §6.2
        uses it for the design only; ``--no-pem-sensor`` leaves it off the bus.
    seed:
        Noise seed.
    period:
        Step period, s (the engine's 10 ms). Integrated by one classic RK4 step.

    Outputs: the sensors ``DSL_P_IM`` (kPa), ``N_T`` (rpm), ``VGT_POS``, ``EGR_POS`` (%) and,
    with ``pem_sensor``, ``DSL_P_EM`` (kPa, with the exhaust pulsation as noise); the truth
    ``DSL_P_IM_TRUE``, ``DSL_P_EM_TRUE`` (kPa) and ``N_T_TRUE`` (rpm) (see :data:`SIGNAL`).
    """

    inputs = ("ENGINE_SPEED", "FUEL_RATE", "ENGINE_LOAD", "EXH_BP_L_TRUE", "EXH_BP_R_TRUE")
    outputs_all = ("DSL_P_IM", "N_T", "VGT_POS", "EGR_POS", "DSL_P_EM",
                   "DSL_P_IM_TRUE", "DSL_P_EM_TRUE", "N_T_TRUE")

    #: sensor noise standard deviations: P_IM kPa, N_T rpm, positions %, P_EM kPa
    NOISE = {"P_IM": 0.6, "N_T": 80.0, "POS": 0.15, "P_EM": 3.0}

    def __init__(self, params: AirPathParams | None = None, biases: Biases | None = None,
                 control: ControlParams | None = None, pem_sensor: bool = True, seed: int = 0,
                 period: float = 0.01, name: str = "airpath") -> None:
        super().__init__(name, period)
        self.params = params or AirPathParams()
        self.biases = biases if biases is not None else Biases()
        self.control = control or ControlParams()
        self.pem_sensor = pem_sensor
        self.outputs = tuple(o for o in self.outputs_all if pem_sensor or o != "DSL_P_EM")
        self._rng = np.random.default_rng([seed, 0x002])
        self._a_act = lag_factor(period, self.control.tau_actuator)
        self.t = 0.0
        self.x = np.array([self.params.p_amb / 1e3, self.params.p_amb / 1e3 + 5.0, 20.0])
        self.vgt = 60.0
        self.egr = 30.0
        self.integral = 0.0
        self._noise = np.zeros(4)
        self._pulse = 0.0

    # -- controllers ------------------------------------------------------------------------
    def boost_setpoint(self, speed: float, load: float) -> float:
        """Intake pressure set-point, kPa: ambient to ``boost_rated`` with load and speed."""
        c = self.control
        rel_speed = min(max(speed / 1800.0, 0.0), 1.2)
        return self.params.p_amb / 1e3 * (1.0 + (c.boost_rated - 1.0) * max(load, 0.0)
                                          * (0.55 + 0.45 * rel_speed))

    def _vgt_feedforward(self, load: float) -> float:
        return 75.0 - 35.0 * min(max(load, 0.0), 1.1)

    def _egr_setpoint(self, load: float) -> float:
        c = self.control
        return c.egr_max - (c.egr_max - c.egr_min) * min(max(load, 0.0), 1.0)

    def _inputs(self, u: Mapping[str, float]) -> tuple[float, ...]:
        return (u.get("FUEL_RATE", 0.0), u.get("ENGINE_SPEED", 0.0), self.vgt, self.egr,
                u.get("EXH_BP_L_TRUE", 0.0), u.get("EXH_BP_R_TRUE", 0.0))

    def _params_at(self, t: float) -> AirPathParams:
        return replace(self.params, **self.biases.at(t))

    def _control(self, u: Mapping[str, float], dt: float) -> None:
        load = u.get("ENGINE_LOAD", 0.0) / 100.0
        speed = u.get("ENGINE_SPEED", 0.0)
        c = self.control
        err = self.x[0] - self.boost_setpoint(speed, load)  # kPa; > 0: too much boost, open
        raw = self._vgt_feedforward(load) + c.vgt_kp * err + self.integral
        target = min(max(raw, 10.0), 100.0)
        if raw == target:  # anti-windup: integrate only when not saturated
            self.integral += c.vgt_ki * err * dt
        self.integral = min(max(self.integral, -60.0), 60.0)
        self.vgt += self._a_act * (target - self.vgt)
        self.egr += self._a_act * (self._egr_setpoint(load) - self.egr)

    def start(self, u: Mapping[str, float]) -> None:
        """Start in the steady state of the initial inputs, controllers included.

        Solved for directly (:meth:`_steady`); if that fails, 20 s of simulated time settle it.
        """
        if not self._steady(u):
            for _ in range(round(20.0 / self.period)):
                self._advance(0.0, u)
        self._draw()

    def _steady(self, u: Mapping[str, float]) -> bool:
        """Solve f(x) = 0 with the controllers at rest: the boost on its set-point and the
        VGT free in 10..100 %, or, when the VGT saturates, the VGT at its limit and the boost
        free. Returns False when no solution is found."""
        load = u.get("ENGINE_LOAD", 0.0) / 100.0
        speed = u.get("ENGINE_SPEED", 0.0)
        sp = self.boost_setpoint(speed, load)
        egr = self._egr_setpoint(load)
        ff = self._vgt_feedforward(load)
        p = self._params_at(0.0)
        base = self._inputs(u)

        def at(vgt: float) -> tuple[float, ...]:
            return (base[0], base[1], vgt, egr, base[4], base[5])

        def free_vgt(z):
            return airpath_rhs(0.0, (sp, z[0], z[1]), at(z[2]), p)

        guess = np.array([sp * 1.2 + 2.0, 8.0 + 36.0 * min(max(load, 0.0), 1.0), ff])
        with np.errstate(all="ignore"):
            z, _, ier, _ = fsolve(free_vgt, guess, full_output=True)
            if ier == 1 and 10.0 <= z[2] <= 100.0 and np.abs(free_vgt(z)).max() < 1e-6:
                x, vgt = np.array([sp, z[0], z[1]]), float(z[2])
            else:
                vgt = 100.0 if z[2] > 100.0 or not np.isfinite(z[2]) else 10.0
                x, _, ier, _ = fsolve(lambda v: airpath_rhs(0.0, v, at(vgt), p),
                                      np.array([sp, guess[0], guess[1]]), full_output=True)
                if ier != 1 or np.abs(airpath_rhs(0.0, x, at(vgt), p)).max() > 1e-6:
                    return False
        self.x = np.asarray(x, dtype=float)
        self.vgt, self.egr = vgt, egr
        self.integral = vgt - ff - self.control.vgt_kp * (self.x[0] - sp)
        return True

    def _advance(self, t: float, u: Mapping[str, float]) -> None:
        dt = self.period
        self._control(u, dt)
        p = self._params_at(t)
        uu = self._inputs(u)
        x = self.x
        k1 = airpath_rhs(t, x, uu, p)
        k2 = airpath_rhs(t, x + 0.5 * dt * k1, uu, p)
        k3 = airpath_rhs(t, x + 0.5 * dt * k2, uu, p)
        k4 = airpath_rhs(t, x + dt * k3, uu, p)
        self.x = x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        self.x[2] = max(self.x[2], 0.5)

    def _draw(self) -> None:
        n = self.NOISE
        self._noise = self._rng.normal(0.0, [n["P_IM"], n["N_T"], n["POS"], n["P_EM"]])

    def step(self, t: float, u: Mapping[str, float]) -> None:
        self._advance(t, u)
        self.t = t
        self._draw()

    def output(self) -> dict[str, float]:
        p_im, p_em, n_t = (float(v) for v in self.x)
        nz = self._noise.tolist()
        out = {
            "DSL_P_IM": p_im + nz[0],
            "N_T": n_t * 1000.0 + nz[1],
            "VGT_POS": min(max(self.vgt + nz[2], 0.0), 100.0),
            "EGR_POS": min(max(self.egr + nz[2] * 0.7, 0.0), 100.0),
            "DSL_P_IM_TRUE": p_im,
            "DSL_P_EM_TRUE": p_em,
            "N_T_TRUE": n_t * 1000.0,
        }
        if self.pem_sensor:
            out["DSL_P_EM"] = p_em + nz[3]
        return out

    def __repr__(self) -> str:
        return f"DieselAirPath({self.name!r}, pem_sensor={self.pem_sensor})"
