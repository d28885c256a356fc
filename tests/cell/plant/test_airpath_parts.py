"""The air-path components (cell/plant/airpath_parts.py) against closed-form answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cell.plant import airpath_parts as ap


def test_flow_function_is_choked_below_the_critical_ratio_with_the_textbook_value():
    g = 1.4
    crit = (2 / (g + 1)) ** (g / (g - 1))  # 0.528
    choked = math.sqrt(g * (2 / (g + 1)) ** ((g + 1) / (g - 1)))  # 0.6847
    assert ap.flow_function(crit, g) == pytest.approx(choked, rel=1e-9)
    assert ap.flow_function(0.2, g) == pytest.approx(choked, rel=1e-9)
    assert ap.flow_function(1.0, g) == 0.0


def test_flow_function_is_continuous_and_linear_near_one():
    lin = 0.95
    below = ap.flow_function(lin - 1e-9, pr_lin=lin)
    above = ap.flow_function(lin + 1e-9, pr_lin=lin)
    assert above == pytest.approx(below, rel=1e-6)
    # linear to zero at a ratio of 1: half way there, half the value
    assert ap.flow_function(lin + 0.5 * (1 - lin), pr_lin=lin) == pytest.approx(0.5 * below, rel=1e-6)


def test_restriction_flow_reverses_with_the_pressure_ratio():
    fwd = ap.restriction_flow(1e-4, 150e3, 300.0, 100e3)
    rev = ap.restriction_flow(1e-4, 100e3, 300.0, 150e3)
    assert fwd > 0 and rev == pytest.approx(-fwd)
    # choked: W = A p / sqrt(R T) * 0.6847
    assert ap.restriction_flow(1e-4, 300e3, 300.0, 100e3) == pytest.approx(
        1e-4 * 300e3 / math.sqrt(287 * 300) * 0.68473, rel=1e-4)


def test_adiabatic_volume_conserves_mass_and_energy():
    # an independent form: m = pV/(RT), U = m cv T = pV/(gamma-1)
    p, T, V, R, g = 80e3, 320.0, 3e-3, 287.0, 1.4
    cp = R / (g - 1) + R
    w_in, T_in, w_out, q = 0.05, 310.0, 0.04, 50.0
    dp, dT = ap.adiabatic_volume(p, T, V, w_in, T_in, w_out, q)
    m = p * V / (R * T)
    dm = dp * V / (R * T) - p * V / (R * T * T) * dT
    dU = dp * V / (g - 1)
    assert dm == pytest.approx(w_in - w_out, rel=1e-9)
    assert dU == pytest.approx(w_in * cp * T_in - w_out * cp * T + q, rel=1e-9)
    assert m > 0
    # at rest: equal flows at the volume's temperature, no heat
    assert ap.adiabatic_volume(p, T, V, 0.03, T, 0.03) == pytest.approx((0.0, 0.0), abs=1e-9)


def test_compressor_map_is_continuously_differentiable_at_a_pressure_ratio_of_one():
    kw = dict(w_ref=0.2, omega_ref=2e4, k_pr=1.6)
    w = [ap.compressor_flow(1e4, pr, 101e3, 298.0, **kw) for pr in (1 - 1e-4, 1.0, 1 + 1e-4)]
    assert (w[0] - w[1]) == pytest.approx(w[1] - w[2], abs=1e-9)  # slope 0 on both sides
    # zero flow at the speed line's zero-flow ratio, and the offset added on top
    pr0 = 1 + 1.6 * 0.25
    assert ap.compressor_flow(1e4, pr0, 101325.0, 298.0, **kw) == pytest.approx(0.0, abs=1e-12)
    assert ap.compressor_flow(1e4, pr0, 101325.0, 298.0, offset=0.003, **kw) == pytest.approx(0.003)


def test_compressor_power_is_the_isentropic_power_over_the_efficiency():
    T_out = ap.compressor_outlet_temperature(298.0, 2.0, 0.7)
    isentropic = 298.0 * (2.0 ** (0.4 / 1.4) - 1)
    assert T_out - 298.0 == pytest.approx(isentropic / 0.7)
    assert ap.compressor_power(0.1, 298.0, T_out) == pytest.approx(0.1 * 1004.5 * isentropic / 0.7)


def test_volumetric_efficiency_and_cylinder_air_charge():
    # no back pressure effect when p_em = p_im; ideal-gas charge at lambda -> infinity
    eta = ap.volumetric_efficiency(0.9, 100e3, 100e3, 9.3, 1.3)
    assert eta == pytest.approx(0.9)
    cac = ap.cylinder_air_charge(eta, 100e3, 300.0, 0.5e-3, 1e9, 14.7)
    assert cac == pytest.approx(0.9 * 100e3 * 0.5e-3 / (287 * 300), rel=1e-6)
    # a higher exhaust pressure leaves more residual gas: less air
    assert ap.volumetric_efficiency(0.9, 100e3, 150e3, 9.3, 1.3) < eta
    assert ap.engine_air_flow(cac, 4, 30.0) == pytest.approx(cac * 4 * 30 / 2)


def test_turbine_and_shaft():
    assert ap.turbine_flow(150e3, 1000.0, 150e3, 4e-4) == 0.0
    w = ap.turbine_flow(200e3, 1000.0, 100e3, 4e-4)
    assert w == pytest.approx(4e-4 * 200e3 / math.sqrt(287 * 1000) * math.sqrt(1 - 0.5 ** 1.5))
    P = ap.turbine_power(w, 1000.0, 0.5, 0.7, 1200.0, 1.3)
    assert P == pytest.approx(w * 1200 * 1000 * 0.7 * (1 - 0.5 ** (0.3 / 1.3)))
    # balance: no acceleration when eta_m P_t = P_c and no friction
    assert ap.shaft_acceleration(1000.0, 950.0, 1e4, 2e-5, 0.95) == pytest.approx(0.0, abs=1e-9)
    assert np.sign(ap.shaft_acceleration(2000.0, 950.0, 1e4, 2e-5, 0.95)) == 1
