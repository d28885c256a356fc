r"""The three-way catalyst's equations (seed 000, section III), shared by plant and observer.

Plain functions over floats, each citing the paper's equation. The simulator's
:class:`~cell.plant.catalyst.Catalyst` calls them with its own :class:`TWCKinetics`; the
observer's model (:mod:`cell.estimators.catalyst`) calls them with its own, deliberately
different, instance.

Oxygen storage (eqs. 10-12, 15-17)
----------------------------------
Each of ``n`` cells of length :math:`\Delta z` stores oxygen on ceria sites,
:math:`[Ce_2O_3] = (1 - \phi) OSC`, :math:`[Ce_2O_4] = \phi\, OSC` (eq. 10). Reactions 6a
(:math:`2 Ce_2O_3 + O_2 \rightleftharpoons 2 Ce_2O_4`) and 6b
(:math:`Ce_2O_4 + CO \rightleftharpoons Ce_2O_3 + CO_2`) run at the rates of eq. 16,

.. math:: R_1 = k_1^f [Ce_2O_3]^2 [O_2] - k_1^b [Ce_2O_4]^2 c_0, \qquad
          R_2 = k_2^f [Ce_2O_4] [CO] - k_2^b [Ce_2O_3] [CO_2]

with Arrhenius forward rates :math:`k_j^f = A_j e^{-E_j / R T}` and backward rates
:math:`k_j^b = k_j^f / K_j`, :math:`K_j = e^{-\Delta G_j / R T}`. The gas balance of eq. 17,
:math:`[X]^i = [X]^{i-1} \mp R^i \tau` with the residence time
:math:`\tau = c_0 M_{exh} A_{cs} \Delta z / \dot m_{exh}` (eq. 9), is linear in the cell's
own concentration, so it is solved for it exactly, as eq. 13 is for the gas temperature:

.. math:: [O_2]^i = \frac{[O_2]^{i-1} + \tau\, k_1^b [Ce_2O_4]^2 c_0}{1 + \tau\, k_1^f [Ce_2O_3]^2}, \qquad
          [CO]^i = \frac{[CO]^{i-1} + \tau\, k_2^b [Ce_2O_3] C}{1 + \tau (k_2^f [Ce_2O_4] + k_2^b [Ce_2O_3])}

where :math:`C = [CO] + [CO_2]` is conserved along the brick. Then
:math:`R_1^i = ([O_2]^{i-1} - [O_2]^i)/\tau`, :math:`R_2^i = ([CO]^{i-1} - [CO]^i)/\tau` and
eq. 15, :math:`d\phi^i/dt = (2 R_1^i - R_2^i) / OSC`. λ of a gas follows eq. 12,
:math:`\lambda = (2([O_2] + [CO_2]) + [CO]) / (2([CO] + [CO_2]))`.

Feed gas
--------
The paper gives the catalyst's inlet as λ only; the species of eq. 12 are taken from it
(:func:`feed_gas`): carbon :math:`C = y_C c_0` at and below λ = 1, all of it CO₂ when lean,
with :math:`[O_2] = (\lambda - 1) C`, and :math:`[CO] = 2 (1 - \lambda) C` when rich (both
invert eq. 12 exactly). When lean, the carbon fraction falls as :math:`y_C / (1 + k (\lambda
- 1))` with :math:`k = y_C / y_{O_2,air}`, so that very lean gas (fuel cut) tends to air's
21 % oxygen.

Thermal model (eqs. 4, 13, 14)
------------------------------
Five cells: the gas temperature of each by eq. 13, the substrate's by eq. 14 with the heat
of reaction of eq. 4, :math:`\dot Q_{reac} = K_{reac} \dot m_{exh} \eta(T_{cat})`, and an
S-shaped (logistic) efficiency :math:`\eta`.

Parameters the paper does not give
----------------------------------
Every number is in :class:`TWCKinetics` and :class:`TWCThermal`, with where it comes from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

R_GAS = 8.314
"""Universal gas constant, J/(mol K) (the paper's nomenclature)."""


@dataclass(frozen=True)
class TWCKinetics:
    """Geometry, oxygen storage capacity, reaction kinetics and feed-gas composition.

    The geometry is seed 000's Table I; the rest is not in the paper and is chosen to be
    physically plausible, with its source named on each field.
    """

    volume: float = 0.597e-3
    """Brick volume, m³ (Table I: 0.597 l)."""
    length: float = 0.068
    """Brick length, m (Table I: 68 mm). The cross section ``A_cs`` is volume / length
    (8.78e-3 m², a 106 mm round brick)."""
    cells: int = 3
    """Oxygen-storage cells (section III.C: three, from the sensitivity analysis of [13])."""
    osc_fresh: float = 45.0
    """OSC of the fresh catalyst, mol of ceria sites per m³ of brick. 45 mol/m³ in 0.597 l is
    0.43 g of O₂ (eq. 6a: one O₂ per two sites), within the 0.2-1 g/l of fresh Pd/Rh
    catalysts with ceria (Kiwitz et al. [16] identify ~0.5 g/l). The observer's estimate
    and the simulator's truth are normalised to it, as the paper's figures are."""
    A1: float = 9.6e5
    """Arrhenius factor of reaction 6a, m⁶/(mol² s): with ``E1`` it gives a cell Damköhler
    number k₁ OSC² τ of about 100 at 450 °C and 10 g/s (fast storage, as [16] finds), and
    below 1 under 200 °C (no storage in a cold catalyst)."""
    E1: float = 60.0e3
    """Activation energy of 6a, J/mol (ceria oxidation: 40-90 kJ/mol in [16] and [3])."""
    A2: float = 7.2e6
    """Arrhenius factor of reaction 6b, m³/(mol s): a Damköhler number k₂ OSC τ of ~150
    at 450 °C and 10 g/s."""
    E2: float = 50.0e3
    """Activation energy of 6b, J/mol (CO oxidation on ceria: 40-80 kJ/mol, [3])."""
    dG1: float = -100.0e3
    """Gibbs energy of 6a, J/mol: K₁ = 6.5e5 at 700 K, so storage stops at φ ≈ 0.97 in
    lean gas of 0.3 % O₂ (the equilibrium of R₁ = 0)."""
    dG2: float = -50.0e3
    """Gibbs energy of 6b, J/mol: K₂ = 5e3 at 700 K, so release stops at φ ≈ 0.002 in rich
    gas of CO/CO₂ = 0.1."""
    y_c: float = 0.13
    """Mole fraction of carbon (CO + CO₂) in stoichiometric gasoline exhaust (wet: 12-14 %)."""
    y_o2_air: float = 0.21
    """Oxygen mole fraction of air, the limit of very lean exhaust (fuel cut)."""
    M_exh: float = 0.0288
    """Mean molar mass of the exhaust gas, kg/mol (nomenclature: M_exh; N₂-dominated)."""
    pressure: float = 1.0e5
    """Exhaust gas pressure, Pa (section III.B: P = 1e5 Pa)."""

    @property
    def area(self) -> float:
        """Cross-section A_cs, m²."""
        return self.volume / self.length

    @property
    def dz(self) -> float:
        """Length of one oxygen-storage cell, m."""
        return self.length / self.cells

    def scaled(self, **factors: float) -> TWCKinetics:
        """A copy with some fields multiplied (``A1=0.8``): an observer's imperfect model."""
        from dataclasses import replace

        return replace(self, **{k: getattr(self, k) * v for k, v in factors.items()})


@dataclass(frozen=True)
class TWCThermal:
    """Constants of the five-cell thermal model (eqs. 4, 13, 14). Not in the paper; typical
    values of a 400 cpsi cordierite monolith, after [14], [15] and [17]."""

    cells: int = 5
    """Thermal cells (section III.C: five)."""
    epsilon: float = 0.75
    """Open frontal area (400 cpsi, 6.5 mil walls: 0.76)."""
    rho_s: float = 2500.0
    """Density of the solid (cordierite and washcoat), kg/m³."""
    c_s: float = 1000.0
    """Specific heat of the solid, J/(kg K) (cordierite: 0.9-1.1 kJ/(kg K) at 300-800 °C)."""
    c_pg: float = 1100.0
    """Specific heat of the exhaust gas, J/(kg K) (at 400-700 °C)."""
    h: float = 150.0
    """Gas-solid heat transfer coefficient, W/(m² K): Nu ≈ 3.6 in 1.1 mm laminar channels
    with a gas conductivity of 0.045 W/(m K)."""
    A_geo: float = 2800.0
    """Geometric surface per brick volume, m²/m³ (400 cpsi: 2740)."""
    h_out: float = 15.0
    """Heat transfer to ambient through mat, can and heat shield, W/(m² K)."""
    T_amb: float = 25.0
    """Ambient temperature, °C."""
    K_reac: float = 1.1e8
    """Eq. 4's factor, J/(kg m³): 66 kJ per kg of exhaust at full conversion (the exotherm of
    stoichiometric exhaust, 60 K adiabatic rise) over the brick volume."""
    T_light_off: float = 250.0
    """Temperature of 50 % efficiency of the S-shaped η(T_cat), °C (Pd/Rh: 200-300 °C)."""
    light_off_width: float = 15.0
    """Width of the logistic η(T_cat), K (10-90 % over 66 K)."""


# -- gas ------------------------------------------------------------------------------------
def gas_concentration(T_kelvin: float, k: TWCKinetics) -> float:
    """Total gas concentration c₀ = P / (R T), mol/m³ (section III.B)."""
    return k.pressure / (R_GAS * T_kelvin)


def residence_time(mdot: float, c0: float, k: TWCKinetics) -> float:
    """Residence time of one cell, c₀ M_exh A_cs Δz / ṁ_exh, s (eqs. 9, 17)."""
    return c0 * k.M_exh * k.area * k.dz / max(mdot, 1e-5)


def feed_gas(lam: float, c0: float, k: TWCKinetics) -> tuple[float, float, float]:
    """Inlet ([O₂], [CO], C = [CO] + [CO₂]) in mol/m³ for λ (eq. 12 inverted; module notes)."""
    lam = max(lam, 0.5)
    if lam >= 1.0:
        carbon = k.y_c / (1.0 + k.y_c / k.y_o2_air * (lam - 1.0)) * c0
        return (lam - 1.0) * carbon, 0.0, carbon
    carbon = k.y_c * c0
    return 0.0, 2.0 * (1.0 - lam) * carbon, carbon


def lambda_of(o2: float, co: float, carbon: float) -> float:
    """λ from concentrations, eq. 12, with [CO₂] = C - [CO]."""
    co2 = carbon - co
    return (2.0 * (o2 + co2) + co) / (2.0 * (co + co2))


def rate_constants(T_kelvin: float, k: TWCKinetics) -> tuple[float, float, float, float]:
    """(k₁ᶠ, k₁ᵇ, k₂ᶠ, k₂ᵇ) at T: Arrhenius forward rates, backward = forward / K_j with
    K_j = exp(-ΔG_j / R T) (section III.B)."""
    rt = R_GAS * T_kelvin
    k1f = k.A1 * math.exp(-k.E1 / rt)
    k2f = k.A2 * math.exp(-k.E2 / rt)
    return k1f, k1f * math.exp(k.dG1 / rt), k2f, k2f * math.exp(k.dG2 / rt)


def storage_cell(phi: float, osc: float, o2_in: float, co_in: float, carbon: float, tau: float,
                 c0: float, rates: tuple[float, float, float, float]) -> tuple[float, float, float]:
    """One oxygen-storage cell: outlet [O₂], [CO] (eq. 17 solved for them) and dφ/dt (eq. 15).

    ``osc`` is the absolute capacity, mol/m³; ``rates`` from :func:`rate_constants`.
    """
    k1f, k1b, k2f, k2b = rates
    ce3 = (1.0 - phi) * osc
    ce4 = phi * osc
    a1 = k1f * ce3 * ce3
    b1 = k1b * ce4 * ce4 * c0
    o2 = (o2_in + tau * b1) / (1.0 + tau * a1)
    a2 = k2f * ce4 + k2b * ce3
    co = (co_in + tau * k2b * ce3 * carbon) / (1.0 + tau * a2)
    dphi = (2.0 * (o2_in - o2) - (co_in - co)) / (tau * osc)
    return o2, co, dphi


def efficiency(T_cat: float, th: TWCThermal) -> float:
    """S-shaped conversion efficiency η(T_cat) of eq. 4: a logistic in °C."""
    z = (T_cat - th.T_light_off) / th.light_off_width
    if z < -40.0:
        return 0.0
    return 1.0 / (1.0 + math.exp(-z))
