r"""Cylinders, exhaust manifold, UEGO sensor and crankshaft, resolved in crank angle (seed 001).

The :class:`Cylinders` plant turns the mean-value engine (``ENGINE_SPEED``,
``LAMBDA_ENGINE_TRUE``, ``ENGINE_TORQUE``) into what the cylinders do one by one:

- **Per-cylinder fuel and IMEP.** Cylinder ``i`` gets a relative fuel offset :math:`o_i`
  (``--imbalance 1:+0.25`` or the ``FUEL_OFFSET_CMD`` scenario frame). The λ controller keeps
  the *mean* fuel, so the mean λ stays the engine's (which is why the slow UEGO's mean does
  not show the imbalance, seed 001 introduction):
  :math:`\lambda_i = \lambda \, \overline{(1+o)} / (1+o_i)`. Each cylinder's IMEP is the mean
  IMEP (from ``ENGINE_TORQUE`` and a friction MEP) times its relative combustion work
  :func:`relative_work`, normalised so the mean IMEP is kept.
- **Exhaust and UEGO.** Each cylinder's exhaust enters the manifold during its exhaust phase
  (firing order 1-3-4-2, 180 deg each, from exhaust-valve opening); the manifold mixes it
  (a first-order lag in time) and the gas reaches the UEGO after a transport delay. That
  delayed manifold AFR is the truth ``AFR_MANIFOLD_TRUE`` (the sensor's input :math:`w`).
  The sensor is the cascade of two first-order lags, :math:`\tau_1` = 25 ms and
  :math:`\tau_2` = 20 ms (seed 001, Figure 2), plus white noise: ``AFR_UEGO``.
- **Crankshaft.** The combustion torque of each cylinder is a pulse after its firing TDC
  whose integral over the cycle is its work :math:`W_i = \mathrm{IMEP}_i V_d / n_{cyl}`;
  the load takes the mean. The kinetic energy of the crank next to the cylinders then
  follows :math:`J \omega \, d\omega/d\alpha = T(\alpha) - \bar T`, which gives the truth
  ``N_CYL_TRUE`` (:math:`x_2`). The speed sensor sits at the far end of the transmission
  rod of seed 001 (Figure 10), a second-order coupling in the angle domain,

  .. math:: x_1'' + 2\bar\xi\bar\omega x_1' + \bar\omega^2 x_1 = 2\bar\xi\bar\omega x_2'
            + \bar\omega^2 x_2 \triangleq w_0,

  with :math:`\bar\xi` = 0.15 and :math:`\bar\omega` (per radian of crank angle) a parameter;
  ``N_CRANK`` is :math:`x_1` plus noise. (The paper writes :math:`w_0` with :math:`x_2''` in
  it too, which would make :math:`x_1 = x_2`; the spring-damper coupling of its Figure 10 is
  the form above.)

The plant steps at its ``period`` (10 ms, like the other plants) and integrates inside each
step on a fine angle grid (``sub_deg``, 1 deg), so no other plant has to step finely. Every
6 deg sample of the step is handed out through :meth:`Cylinders.take_samples` (streams
``AFR_UEGO``, ``N_CRANK`` and their truth ``AFR_MANIFOLD_TRUE``, ``N_CYL_TRUE``); the
simulator packs them four to a frame (``dbc/crank.dbc``). Angle 0 is cylinder 1's firing TDC.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import expm
from scipy.signal import lfilter, lfilter_zi, ss2tf

from cell.core.errors import ConfigError
from cell.core.options import Option
from cell.plant.base import Plant

#: stoichiometric AFR of gasoline
STOICH_AFR = 14.7
#: cylinders of the si-turbo engine
N_CYL = 4


@dataclass(frozen=True)
class CylinderParams:
    """Constants of the crank-resolved plant (a 2 L, 4-cylinder engine)."""

    period: float = 0.01
    """Step period, s (the samples are integrated inside it)."""
    displacement: float = 2.0e-3
    """Swept volume of the engine, m³."""
    firing_order: tuple[int, ...] = (1, 3, 4, 2)
    evo_deg: float = 140.0
    """Exhaust-valve opening after firing TDC, deg CA: the start of the exhaust phase."""
    tau_mix: float = 0.003
    """Manifold mixing time constant, s."""
    delay: float = 0.006
    """Transport delay from the manifold to the UEGO, s."""
    tau1: float = 0.025
    """UEGO first lag, s (seed 001)."""
    tau2: float = 0.020
    """UEGO second lag, s (seed 001)."""
    afr_noise: float = 0.02
    """UEGO noise std, AFR."""
    inertia: float = 0.12
    """Crank inertia next to the cylinders, kg m²."""
    fmep: float = 1.0
    """Friction mean effective pressure, bar (IMEP = BMEP + FMEP)."""
    burn_deg: float = 35.0
    """Angle after TDC of the combustion torque's peak, deg CA."""
    xi: float = 0.15
    """Damping of the transmission rod (seed 001)."""
    omega_bar: float = 3.0
    """Natural frequency of the transmission rod, per radian of crank angle."""
    speed_noise: float = 0.3
    """Crank speed sensor noise std, rpm."""
    sample_deg: float = 6.0
    sub_deg: float = 1.0
    rich_gain: float = 0.3
    """Relative IMEP gained per unit of λ below 1 (a rich cylinder burns a little more air)."""
    exhaust_phase_deg: float = 0.0
    """Extra exhaust transport phase, deg CA (a plant variant, ±60): each cylinder's gas
    reaches the manifold this much later (earlier when negative) than its exhaust phase."""


def cylinder_lambdas(lam: float, offsets: Sequence[float]) -> np.ndarray:
    """λ of each cylinder when the λ control keeps the mean fuel of the offset injectors."""
    o = 1.0 + np.asarray(offsets, dtype=float)
    return lam * float(np.mean(o)) / o


def relative_work(lam: np.ndarray, rich_gain: float = 0.3) -> np.ndarray:
    """Combustion work per unit of air, relative to λ = 1: fuel-limited when lean (1/λ),
    slightly above 1 when rich."""
    lam = np.clip(np.asarray(lam, dtype=float), 0.5, 5.0)
    return np.where(lam >= 1.0, 1.0 / lam, 1.0 + rich_gain * (1.0 - lam))


def parse_imbalance(spec: str | None) -> tuple[float, ...]:
    """``1:+0.25,4:-0.25`` -> per-cylinder fuel offsets ``(0.25, 0, 0, -0.25)``.

    Raises :class:`ConfigError` naming the bad item.
    """
    out = [0.0] * N_CYL
    if spec is None or not str(spec).strip():
        return tuple(out)
    for item in str(spec).split(","):
        item = item.strip()
        cyl, sep, text = item.partition(":")
        if not sep:
            raise ConfigError(f"--imbalance {spec!r}: item {item!r} is not CYLINDER:OFFSET "
                              "(e.g. 1:+0.25)")
        try:
            i = int(cyl)
        except ValueError:
            raise ConfigError(f"--imbalance {spec!r}: cylinder {cyl!r} is not a number 1..4") from None
        if not 1 <= i <= N_CYL:
            raise ConfigError(f"--imbalance {spec!r}: cylinder {i} is not one of 1..{N_CYL}")
        try:
            v = float(text)
        except ValueError:
            raise ConfigError(f"--imbalance {spec!r}: offset {text!r} of cylinder {i} is not a "
                              "number") from None
        if not math.isfinite(v) or not -0.5 <= v <= 0.5:
            raise ConfigError(f"--imbalance {spec!r}: offset of cylinder {i} must be in "
                              f"-0.5..+0.5 (a fraction of the fuel), got {text}")
        out[i - 1] = v
    return tuple(out)


def torque_pulse(theta_deg: np.ndarray, burn_deg: float) -> np.ndarray:
    """One cylinder's combustion torque shape over the cycle, per radian, integrating to 1.

    A pulse :math:`(\\theta/\\theta_p) e^{1-\\theta/\\theta_p}` over the expansion stroke
    (0..180 deg after firing TDC), zero elsewhere.
    """
    th = np.asarray(theta_deg, dtype=float) % 720.0
    x = th / burn_deg
    g = np.where(th < 180.0, x * np.exp(1.0 - x), 0.0)
    grid = np.arange(0.0, 180.0, 0.01)
    norm = np.sum((grid / burn_deg) * np.exp(1.0 - grid / burn_deg)) * math.radians(0.01)
    return g / norm


def rod_matrices(xi: float, omega_bar: float, d_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact discretisation over ``d_rad`` of the rod (seed 001, Figure 10) for a held
    :math:`w_0`: state :math:`(x_1, x_1')`, :math:`A = [[0, 1], [-\\bar\\omega^2,
    -2\\bar\\xi\\bar\\omega]]`, :math:`A_0 = [0, 1]^T`."""
    a = np.array([[0.0, 1.0], [-omega_bar**2, -2.0 * xi * omega_bar]])
    m = expm(np.block([[a, np.array([[0.0], [1.0]])], [np.zeros((1, 3))]]) * d_rad)
    return m[:2, :2], m[:2, 2:]


class _Lag:
    """A first-order lag on a non-uniform time grid (uniform within one call), via lfilter."""

    def __init__(self, tau: float, y0: float) -> None:
        self.tau, self.y = tau, float(y0)

    def __call__(self, x: np.ndarray, dt: float) -> np.ndarray:
        a = math.exp(-dt / self.tau)
        y, _ = lfilter([1.0 - a], [1.0, -a], x, zi=[a * self.y])
        self.y = float(y[-1])
        return y


class Cylinders(Plant):
    """The crank-resolved cylinders, exhaust, UEGO and crankshaft (module docstring).

    Parameters
    ----------
    params:
        The plant's constants.
    imbalance:
        Per-cylinder fuel offsets held until a ``FUEL_OFFSET_CMD`` frame sets them.
    seed:
        Noise seed.
    """

    inputs = ("ENGINE_SPEED", "LAMBDA_ENGINE_TRUE", "ENGINE_TORQUE",
              *(f"FUEL_OFFSET_CYL_{i}" for i in range(1, N_CYL + 1)))
    outputs = (*(f"AFR_CYL_{i}_TRUE" for i in range(1, N_CYL + 1)),
               *(f"IMEP_CYL_{i}_TRUE" for i in range(1, N_CYL + 1)),
               *(f"FUEL_OFFSET_CYL_{i}_TRUE" for i in range(1, N_CYL + 1)))
    streams = ("AFR_UEGO", "N_CRANK", "AFR_MANIFOLD_TRUE", "N_CYL_TRUE")

    def __init__(self, params: CylinderParams | None = None, imbalance: Sequence[float] = (),
                 seed: int = 0, name: str = "cylinders") -> None:
        p = self.params = params or CylinderParams()
        super().__init__(name, p.period)
        if sorted(p.firing_order) != list(range(1, N_CYL + 1)):
            raise ConfigError(f"plant {name}: firing order {p.firing_order} is not a permutation "
                              f"of 1..{N_CYL}")
        per = round(p.sample_deg / p.sub_deg)
        if abs(per * p.sub_deg - p.sample_deg) > 1e-9 or abs(720.0 / p.sample_deg
                                                              - round(720.0 / p.sample_deg)) > 1e-9:
            raise ConfigError(f"plant {name}: the sample step must divide 720 deg and be a whole "
                              "number of sub-steps")
        self._sub_per_sample = per
        self.default_offsets = tuple(float(v) for v in (tuple(imbalance) + (0.0,) * N_CYL)[:N_CYL])
        self._rng = np.random.default_rng([seed, 0x001])
        #: firing TDC of each cylinder (index 0 = cylinder 1), deg CA
        self.firing_deg = np.zeros(N_CYL)
        for pos, cyl in enumerate(p.firing_order):
            self.firing_deg[cyl - 1] = pos * 720.0 / N_CYL
        grid = np.arange(0.0, 720.0, p.sub_deg)
        # exhaust owner of each grid angle; combustion torque and its cumulative integral
        phase = (grid[None, :] - self.firing_deg[:, None] - p.evo_deg - p.exhaust_phase_deg) % 720.0
        self._owner = np.argmax(phase < 720.0 / N_CYL, axis=0)
        th = (grid[None, :] - self.firing_deg[:, None]) % 720.0
        self._pulse = torque_pulse(th, p.burn_deg)  # (cyl, grid), per rad
        d_rad = math.radians(p.sub_deg)
        cum = np.cumsum(self._pulse, axis=1) * d_rad - (grid[None, :] + p.sub_deg) / 720.0
        self._energy = cum - cum.mean(axis=1, keepdims=True)  # per unit work, zero mean
        phi, gam = rod_matrices(p.xi, p.omega_bar, d_rad)
        self._rod_b, self._rod_a = (np.atleast_1d(np.squeeze(v)) for v in
                                    ss2tf(phi, gam, np.array([[1.0, 0.0]]), np.zeros((1, 1))))
        self._rod_zi: np.ndarray | None = None
        self.k_sub = 0  # fine-grid points integrated so far (angle = k_sub * sub_deg)
        self.offsets = np.array(self.default_offsets)
        self.lam = np.ones(N_CYL)
        self.imep = np.zeros(N_CYL)
        self._mix = self._lag1 = self._lag2 = None
        self._hist = np.full(2048, STOICH_AFR)  # the mixed manifold AFR on the fine grid
        self._x2_prev = None
        self._out: dict[str, list] = {s: [] for s in self.streams}
        self._first: dict[str, int | None] = {s: None for s in self.streams}
        self._times: list[np.ndarray] = []

    # -- per-cylinder fuel and work --------------------------------------------------------
    def _cylinders(self, u: Mapping[str, float]) -> None:
        p = self.params
        self.offsets = np.array([u.get(f"FUEL_OFFSET_CYL_{i + 1}", self.default_offsets[i])
                                 for i in range(N_CYL)], dtype=float)
        lam = float(u.get("LAMBDA_ENGINE_TRUE", 1.0))
        self.lam = cylinder_lambdas(min(max(lam, 0.5), 5.0), self.offsets)
        torque = float(u.get("ENGINE_TORQUE", 0.0))
        imep_mean = max(0.0, 4.0 * math.pi * torque / p.displacement / 1e5 + p.fmep)
        work = relative_work(self.lam, p.rich_gain)
        self.imep = imep_mean * work / float(np.mean(work))

    def start(self, u: Mapping[str, float]) -> None:
        self._cylinders(u)

    # -- stepping -------------------------------------------------------------------------
    def step(self, t: float, u: Mapping[str, float]) -> None:
        p = self.params
        self._cylinders(u)
        rpm = float(u.get("ENGINE_SPEED", 0.0))
        if not rpm > 50.0:
            return  # the crank stands still: no samples
        deg_s = 6.0 * rpm
        a0 = self.k_sub * p.sub_deg
        a1 = a0 + deg_s * p.period
        n = int(math.floor(a1 / p.sub_deg + 1e-9)) - self.k_sub
        if n <= 0:
            return
        k = self.k_sub + 1 + np.arange(n)
        angle = k * p.sub_deg
        times = (t - p.period) + (angle - a0) / deg_s
        dt = p.sub_deg / deg_s
        g = k % round(720.0 / p.sub_deg)
        # exhaust: the owner's AFR, mixed in the manifold, delayed to the sensor, measured
        afr_cyl = STOICH_AFR * self.lam
        afr_in = afr_cyl[self._owner[g]]
        if self._mix is None:
            mean = float(np.mean(afr_cyl))
            self._mix, self._lag1, self._lag2 = (_Lag(p.tau_mix, mean), _Lag(p.tau1, mean),
                                                 _Lag(p.tau2, mean))
            self._hist[:] = mean
        mixed = self._mix(afr_in, dt)
        self._hist = np.concatenate([self._hist, mixed])[-max(2048, 4 * n):]
        lag = p.delay / dt
        pos = len(self._hist) - n + np.arange(n) - lag
        afr_w = np.interp(pos, np.arange(len(self._hist)), self._hist)
        afr_s = self._lag2(self._lag1(afr_w, dt), dt)
        # crankshaft: energy of the combustion pulses -> speed next to the cylinders -> rod
        work = self.imep * 1e5 * p.displacement / N_CYL  # J per cylinder and cycle
        omega_m = rpm * math.pi / 30.0
        d_e = work @ self._energy[:, g]
        omega = np.sqrt(np.maximum(omega_m**2 + 2.0 * d_e / p.inertia, (0.5 * omega_m) ** 2))
        torque = work @ self._pulse[:, g] - work.sum() / (4.0 * math.pi)
        x2 = omega * 30.0 / math.pi  # rpm
        dx2 = torque / (p.inertia * omega) * 30.0 / math.pi  # rpm per rad
        w0 = 2.0 * p.xi * p.omega_bar * dx2 + p.omega_bar**2 * x2
        if self._rod_zi is None:
            self._rod_zi = lfilter_zi(self._rod_b, self._rod_a) * w0[0]
        x1, self._rod_zi = lfilter(self._rod_b, self._rod_a, w0, zi=self._rod_zi)
        self.k_sub += n
        # the 6 deg samples of this step
        at = np.nonzero(k % self._sub_per_sample == 0)[0]
        if len(at):
            first = int(k[at[0]] // self._sub_per_sample)
            m = len(at)
            vals = {
                "AFR_UEGO": afr_s[at] + self._rng.normal(0.0, p.afr_noise, m),
                "N_CRANK": x1[at] + self._rng.normal(0.0, p.speed_noise, m),
                "AFR_MANIFOLD_TRUE": afr_w[at],
                "N_CYL_TRUE": x2[at],
            }
            for s, v in vals.items():
                if self._first[s] is None:
                    self._first[s] = first
                self._out[s].append(v)
            self._times.append(times[at])
            if sum(len(v) for v in self._times) > 200_000:  # nobody takes them: keep the newest
                self.take_samples()

    def take_samples(self) -> dict[str, tuple[int, np.ndarray, np.ndarray]]:
        if not self._times:
            return {}
        times = np.concatenate(self._times)
        out = {s: (int(self._first[s]), np.concatenate(v), times) for s, v in self._out.items()}
        self._out = {s: [] for s in self.streams}
        self._first = {s: None for s in self.streams}
        self._times = []
        return out

    def output(self) -> dict[str, float]:
        out = {}
        for i in range(N_CYL):
            out[f"AFR_CYL_{i + 1}_TRUE"] = float(STOICH_AFR * self.lam[i])
            out[f"IMEP_CYL_{i + 1}_TRUE"] = float(self.imep[i])
            out[f"FUEL_OFFSET_CYL_{i + 1}_TRUE"] = float(self.offsets[i])
        return out


# -- plant variants (what an observer cannot know) -------------------------------------------
#: Bounds of the variant options: the exhaust transport phase, deg CA; each UEGO lag, s; the
#: manifold mixing time constant, s.
PHASE_RANGE = (-60.0, 60.0)
LAG_RANGE = (0.005, 0.2)
MIX_RANGE = (0.0005, 0.05)


def parse_lags(text: str | Sequence[float]) -> tuple[float, float]:
    """``"0.03,0.02"`` (s) -> ``(0.03, 0.02)``, the UEGO's two lags; :class:`ConfigError`
    naming the bad part."""
    parts = [p.strip() for p in text.split(",")] if isinstance(text, str) else list(text)
    if len(parts) != 2:
        raise ConfigError(f"--uego-lags {text!r}: two time constants TAU1,TAU2 in s, e.g. 0.025,0.020")
    out = []
    for part in parts:
        try:
            v = float(part)
        except ValueError:
            raise ConfigError(f"--uego-lags {text!r}: {part!r} is not a number") from None
        if not math.isfinite(v) or not LAG_RANGE[0] <= v <= LAG_RANGE[1]:
            raise ConfigError(f"--uego-lags {text!r}: each lag must be in {LAG_RANGE[0]:g}.."
                              f"{LAG_RANGE[1]:g} s, got {part}")
        out.append(v)
    return out[0], out[1]


def _in(lo: float, hi: float, unit: str):
    def check(v: float) -> str | None:
        if not math.isfinite(v) or not lo <= v <= hi:
            return f"must be in [{lo:g}, {hi:g}] {unit}, got {v}"
        return None
    return check


def _lags_check(v: str) -> str | None:
    try:
        parse_lags(v)
    except ConfigError as exc:
        return str(exc).split(": ", 1)[-1]
    return None


#: The crank-resolved plant's variant options (an engine profile splices them into its own).
VARIANT_OPTIONS = (
    Option("exhaust_phase", "--exhaust-phase", float, metavar="DEG", check=_in(*PHASE_RANGE, "deg"),
           help="extra exhaust transport phase to the UEGO, deg crank angle (default 0; ±60)"),
    Option("uego_lags", "--uego-lags", str, metavar="TAU1,TAU2", check=_lags_check,
           help="the UEGO's two first-order lags, s (default 0.025,0.020)"),
    Option("mixing", "--mixing", float, metavar="S", check=_in(*MIX_RANGE, "s"),
           help="exhaust manifold mixing time constant, s (default 0.003)"),
)


def variant_params(plant: Mapping[str, object], base: CylinderParams | None = None) -> CylinderParams:
    """The plant's constants with the variant options of ``plant`` (settings keys of
    :data:`VARIANT_OPTIONS`; absent ones keep ``base``, default :class:`CylinderParams`)."""
    p = base or CylinderParams()
    kw: dict[str, float] = {}
    if plant.get("exhaust_phase") is not None:
        kw["exhaust_phase_deg"] = float(plant["exhaust_phase"])  # type: ignore[arg-type]
    if plant.get("uego_lags") is not None:
        kw["tau1"], kw["tau2"] = parse_lags(plant["uego_lags"])  # type: ignore[arg-type]
    if plant.get("mixing") is not None:
        kw["tau_mix"] = float(plant["mixing"])  # type: ignore[arg-type]
    return replace(p, **kw) if kw else p


__all__ = ["CylinderParams", "Cylinders", "VARIANT_OPTIONS", "parse_lags", "variant_params",
           "STOICH_AFR", "cylinder_lambdas", "parse_imbalance",
           "relative_work", "rod_matrices", "torque_pulse"]
