r"""``testcell design imbalance LOG... --known-offset CYL:OFFSET``: the UEGO observer's exhaust
phase and sensor lags from a run with a known fuel offset on one cylinder (seed 001).

The ``afr_inversion`` observer inverts two first-order UEGO lags and averages the
reconstructed manifold AFR over each cylinder's exhaust window. Neither the lags nor where
a cylinder's gas reaches the sensor (the exhaust transport phase, crank degrees after the
cylinder's firing TDC) are known on an engine the observer was not written against. A run
with a known offset on one cylinder identifies both:

1. **Cycles.** The 6 deg ``AFR_UEGO`` samples of the log are cut into whole engine cycles
   (angle index 0..119 without a gap); each cycle gets its engine speed (``ENGINE_SPEED`` at
   its middle), its mean and its Fourier coefficients :math:`c_k`, :math:`k = 1..K`, over the
   720 deg cycle.
2. **The step.** The offset makes :math:`c_1..c_3` the same every cycle at a speed; noise
   and the λ control's limit cycle do not. In each speed band (step 4) the step is the
   split of the band's cycles that best separates
   the mean coefficients before and after it (a change-point test against the cycles'
   scatter, :data:`STEP_LEVEL`; none: the offset is on from the start), so a log whose
   offset starts part-way through is fine; the first :data:`SKIP_CYCLES` after it, and at
   least :data:`SKIP_SECONDS`, are dropped (the sensor's transient); the earliest band's
   step counts. A log none of whose bands shares a pattern after its step (the mean
   coefficients' energy below :data:`STEP_LEVEL` times its standard error) is refused: it
   does not carry the known offset.
3. **The model.** With the λ control keeping the mean fuel, cylinder :math:`C` at offset
   :math:`o` runs at :math:`\mathrm{AFR}_C = \bar a \cdot 4/(1+o) / (3 + 1/(1+o))` and the
   others at :math:`\bar a \cdot 4 / (3 + 1/(1+o))` (:math:`\bar a` the cycle's mean AFR),
   so the manifold AFR is a known pulse of 180 deg starting :math:`\varphi` after cylinder
   :math:`C`'s firing TDC. Behind two lags its coefficients are
   :math:`c_k = W_k(\varphi) / ((1 + j\Omega_k\tau_1)(1 + j\Omega_k\tau_2))`,
   :math:`\Omega_k = 2\pi k\,\mathrm{rpm}/120`.
4. **The fit.** Cycles are grouped in speed bands of :data:`BAND` (5 %); a band needs
   :data:`MIN_CYCLES` cycles. The first 70 % of each band's cycles (in time) fit, by
   nonlinear least squares on the band-averaged coefficients, one :math:`\varphi` per band
   and one pair :math:`\tau_1 \ge \tau_2` for all (the observer runs one pair of lags); the
   last 30 % are held out, and the design reports how much of their coefficients' energy
   the model explains. A fit that explains less than :data:`MIN_EXPLAINED` of the held-out
   part is refused.

The design file (JSON, the observer contract's design format) names its observer
(``afr_inversion``) and carries the lags as its ``params``, the logs, the known offset,
where the step was found, what it identified (``identified.points``: rpm, ``phase_deg`` per
band; ``identified.tau1``, ``tau2``) and the held-out fit. Nothing is written unless the
whole design succeeds; a refusal exits 2 naming why.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np
from scipy.optimize import least_squares

from cell.core.errors import ConfigError
from cell.core.files import write_text_atomic
from cell.core.registry import Experiment
from cell.estimators.contract import DESIGN_FORMAT
from cell.estimators.cylinders import FIRING_ORDER, check_design
from cell.plant.cylinders import N_CYL

#: samples per engine cycle (6 deg) and harmonics fitted
CYCLE = 120
K = 7
#: level of the step test and of the coherence of the cycles' first three coefficients that
#: shows the offset (both about 1 for noise alone; a balanced engine's λ limit cycle gives
#: less than 0.1)
STEP_LEVEL = 16.0
#: cycles a band (and the log) needs, and cycles dropped after the step
MIN_CYCLES = 12
SKIP_CYCLES = 3
#: and the least time dropped after the step, s (a slow sensor's transient: two lags of
#: 50 ms settle to 2 % in about 0.3 s)
SKIP_SECONDS = 0.35
#: width of a speed band (relative) and the held-out share of each band
BAND = 0.05
HOLD_OUT = 0.3
#: least share of the held-out coefficients' energy the model must explain
MIN_EXPLAINED = 0.5
#: bounds of the lags fitted, s
TAU_BOUNDS = (0.002, 0.3)


@dataclass
class Cycles:
    """Whole engine cycles of a log: time at the middle, rpm, mean AFR, coefficients (n, K)."""

    t: np.ndarray
    rpm: np.ndarray
    mean: np.ndarray
    coef: np.ndarray

    @property
    def energy(self) -> np.ndarray:
        return np.abs(self.coef[:, :3]).sum(axis=1)

    def select(self, sel: np.ndarray) -> Cycles:
        return Cycles(self.t[sel], self.rpm[sel], self.mean[sel], self.coef[sel])


def parse_known_offset(text: str) -> tuple[int, float]:
    """``"2:+0.15"`` -> ``(2, 0.15)``; :class:`ConfigError` naming what is wrong."""
    cyl, sep, off = str(text).partition(":")
    try:
        c, o = int(cyl), float(off)
    except ValueError:
        raise ConfigError(f"--known-offset {text!r} is not CYL:OFFSET (e.g. 2:+0.15)") from None
    if not sep or not 1 <= c <= N_CYL:
        raise ConfigError(f"--known-offset {text!r}: the cylinder must be 1..{N_CYL}")
    if not math.isfinite(o) or not 0.03 <= abs(o) <= 0.5:
        raise ConfigError(f"--known-offset {text!r}: the offset must be a fuel fraction of "
                          "0.03..0.5 either way (smaller ones do not identify the phase)")
    return c, o


# -- read -----------------------------------------------------------------------------------
def read_cycles(path: str | Path | Iterable[can.Message], db=None, progress: bool = False
                ) -> Cycles:
    """The whole engine cycles of ``AFR_UEGO`` in a CAN log, or in its frames (module
    docstring, step 1)."""
    from cell.bus.dbc import FrameDecodeError, load
    from cell.runtime.replay import read_log
    from cell.runtime.samples import find_sample_streams

    db = db or load()
    layout = find_sample_streams(db.messages).get("AFR_UEGO")
    if layout is None:
        raise ConfigError("the DBC files define no AFR_UEGO sample stream")
    afr_id = db.message(layout.message).frame_id
    speed_id = db.message_for("ENGINE_SPEED").frame_id
    samples: list[tuple[float, int, np.ndarray]] = []
    st: list[float] = []
    sv: list[float] = []
    frames = (read_log(path, progress=None if progress else False)
              if isinstance(path, (str, Path)) else path)
    if not isinstance(path, (str, Path)):
        path = "the frames"
    for msg in frames:
        if msg.arbitration_id not in (afr_id, speed_id):
            continue
        try:
            _, values = db.decode(msg)
        except FrameDecodeError:
            continue
        if msg.arbitration_id == afr_id:
            idx, vals = layout.unpack(values)
            samples.append((msg.timestamp, idx, vals))
        elif "ENGINE_SPEED" in values:
            st.append(msg.timestamp)
            sv.append(values["ENGINE_SPEED"])
    if not samples:
        raise ConfigError(f"{path}: no AFR_UEGO sample frames (a log of the si-turbo engine with "
                          "its crank-resolved plant, --crank on)")
    if not st:
        raise ConfigError(f"{path}: no ENGINE_SPEED frames")
    samples.sort(key=lambda s: s[0])
    ts, tv = np.asarray(st), np.asarray(sv)
    basis = np.exp(-2j * np.pi * np.outer(np.arange(1, K + 1), np.arange(CYCLE)) / CYCLE) / CYCLE
    t_out, rpm, mean, coef = [], [], [], []
    buf: list[float] = []
    expect = 0
    t_first = None
    for t, idx, vals in samples:
        if idx != expect or (not buf and idx != 0):
            buf = []  # a gap or a start inside a cycle: wait for the next cycle's start
            if idx != 0:
                expect = (idx + len(vals)) % CYCLE
                continue
        if not buf:
            t_first = t
        buf.extend(vals.tolist())
        expect = (idx + len(vals)) % CYCLE
        if len(buf) >= CYCLE:
            y = np.asarray(buf[:CYCLE])
            tm = 0.5 * (t_first + t)
            t_out.append(tm)
            rpm.append(float(np.interp(tm, ts, tv)))
            mean.append(float(y.mean()))
            coef.append(basis @ y)
            buf = []
    if not t_out:
        raise ConfigError(f"{path}: no whole engine cycle of AFR_UEGO samples")
    return Cycles(np.asarray(t_out), np.asarray(rpm), np.asarray(mean), np.asarray(coef))


# -- the step -------------------------------------------------------------------------------
def find_step(c: Cycles, cyl: int, path: str = "the log") -> float:
    """Time of the first cycle of the offset (module docstring, step 2), searched in each
    speed band on its own (the pattern differs with speed); refuses a log that does not
    carry it."""
    key = _band_keys(c.rpm)
    held = [b for b in np.unique(key) if np.count_nonzero(key == b) >= MIN_CYCLES]
    if not held:
        raise ConfigError(f"{path}: {len(c.t)} whole engine cycles of AFR_UEGO samples, but no "
                          f"speed held (within {BAND:.0%}) for {MIN_CYCLES} of them")
    found, best_coh = [], 0.0
    for b in held:
        idx = np.nonzero(key == b)[0]
        idx = idx[np.argsort(c.t[idx])]
        start, coh = _change_point(c.coef[idx, :3])
        best_coh = max(best_coh, coh)
        if coh >= STEP_LEVEL:
            found.append(float(c.t[idx[start]]))
    if not found:
        raise ConfigError(
            f"{path} does not carry the known offset on cylinder {cyl}: the UEGO has no pattern "
            f"that repeats every engine cycle at any speed held for {MIN_CYCLES} cycles "
            f"(coherence {best_coh:.1f}, needs {STEP_LEVEL:g}); record a run with `testcell "
            f"scenario fuel_offset_cyl_{cyl}=...` or --imbalance {cyl}:OFFSET")
    return min(found)


def _band_keys(rpm: np.ndarray) -> np.ndarray:
    return np.round(np.log(rpm) / math.log(1.0 + BAND)).astype(int)


def _change_point(z: np.ndarray) -> tuple[int, float]:
    """The split of the cycles ``z`` (n, 3) that best separates their mean coefficients
    before and after (0: none passes :data:`STEP_LEVEL`), and the coherence after it: the
    energy of the mean coefficients over their standard error."""
    n = len(z)
    csum = np.cumsum(z, axis=0)
    s = np.arange(max(2, MIN_CYCLES // 2), n - MIN_CYCLES // 2 + 1)
    start = 0
    if len(s):
        before = csum[s - 1] / s[:, None]
        after = (csum[-1] - csum[s - 1]) / (n - s)[:, None]
        score = (s * (n - s) / n) * np.sum(np.abs(after - before) ** 2, axis=1)
        best = int(np.argmax(score))
        var = _scatter(z[: s[best]]) + _scatter(z[s[best]:])
        if score[best] / max(var, 1e-12) > STEP_LEVEL:
            start = int(s[best])
    on = z[start:]
    coherence = float(np.sum(np.abs(on.mean(axis=0)) ** 2) / max(_scatter(on) / len(on), 1e-12))
    return start, coherence


def _scatter(z: np.ndarray) -> float:
    """Mean squared deviation of the cycles' coefficients from their mean (summed over k)."""
    if len(z) < 2:
        return 0.0
    return float(np.sum(np.abs(z - z.mean(axis=0)) ** 2) / (len(z) - 1))


# -- the model ------------------------------------------------------------------------------
def _window(phase_deg: np.ndarray | float, cyl: int) -> np.ndarray:
    """Coefficients (…, K) of a unit pulse of 180 deg starting ``phase_deg`` after
    cylinder ``cyl``'s firing TDC, sampled like the UEGO (1 deg grid, averaged)."""
    tdc = FIRING_ORDER.index(cyl) * 720.0 / N_CYL
    k = np.arange(1, K + 1)
    start = np.asarray(phase_deg, dtype=float)[..., None] + tdc
    # the integral of exp(-i k 2pi theta/720) over [start, start + 180], over 720
    w = 2.0 * np.pi * k / 720.0
    return (np.exp(-1j * w * start) - np.exp(-1j * w * (start + 180.0))) / (1j * w * 720.0)


def _lags(rpm: np.ndarray | float, tau1: float, tau2: float) -> np.ndarray:
    om = 2.0 * np.pi * np.arange(1, K + 1) * np.asarray(rpm, dtype=float)[..., None] / 120.0
    return 1.0 / ((1.0 + 1j * om * tau1) * (1.0 + 1j * om * tau2))


def amplitude(mean_afr: np.ndarray | float, offset: float) -> np.ndarray:
    """AFR of the offset cylinder less the others', from the cycle's mean AFR."""
    r = 1.0 / (1.0 + offset)
    return np.asarray(mean_afr, dtype=float) * 4.0 * (r - 1.0) / (3.0 + r)


def predict(rpm: float, mean_afr: float, offset: float, cyl: int, phase_deg: float,
            tau1: float, tau2: float) -> np.ndarray:
    """The model's coefficients c_1..K of the UEGO over one cycle."""
    return amplitude(mean_afr, offset) * _window(phase_deg, cyl) * _lags(rpm, tau1, tau2)


@dataclass
class Band:
    rpm: float
    fit: Cycles
    held: Cycles

    def averaged(self, part: Cycles) -> tuple[float, float, np.ndarray]:
        return float(part.rpm.mean()), float(part.mean.mean()), part.coef.mean(axis=0)


def bands(c: Cycles) -> list[Band]:
    """Speed bands of :data:`BAND` with at least :data:`MIN_CYCLES` cycles each, split in
    time into a fitted and a held-out part."""
    key = _band_keys(c.rpm)
    out = []
    for b in np.unique(key):
        idx = np.nonzero(key == b)[0]
        if len(idx) < MIN_CYCLES:
            continue
        idx = idx[np.argsort(c.t[idx])]
        cut = max(1, int(round(len(idx) * (1.0 - HOLD_OUT))))
        out.append(Band(float(np.median(c.rpm[idx])), c.select(idx[:cut]), c.select(idx[cut:])))
    return out


def fit(bands_: Sequence[Band], cyl: int, offset: float) -> tuple[list[float], float, float]:
    """Phase per band (deg) and the common lags (s), least squares on the band averages of
    the fitted parts."""
    avg = [b.averaged(b.fit) for b in bands_]
    scale = max(float(np.mean([np.abs(a[2]).sum() for a in avg])), 1e-9)

    def residual(p: np.ndarray) -> np.ndarray:
        t1, t2 = p[0], p[1]
        r = []
        for (rpm, mean, coef), ph in zip(avg, p[2:], strict=True):
            e = (coef - predict(rpm, mean, offset, cyl, ph, t1, t2)) / scale
            r.extend([e.real, e.imag])
        return np.concatenate(r)

    # a start per band from a phase grid at the nominal lags, then all together
    phases0 = []
    for rpm, mean, coef in avg:
        grid = np.arange(0.0, 720.0, 6.0)
        pred = amplitude(mean, offset) * _window(grid, cyl) * _lags(rpm, 0.025, 0.02)
        phases0.append(float(grid[np.argmin(np.abs(pred - coef).sum(axis=1))]))
    best = None
    for t0 in ((0.025, 0.02), (0.06, 0.01), (0.012, 0.005), (0.05, 0.04), (0.1, 0.03)):
        x0 = np.array([*t0, *phases0])
        lo = [TAU_BOUNDS[0]] * 2 + [p - 360.0 for p in phases0]
        hi = [TAU_BOUNDS[1]] * 2 + [p + 360.0 for p in phases0]
        r = least_squares(residual, x0, bounds=(lo, hi))
        if best is None or r.cost < best.cost:
            best = r
    t1, t2 = sorted(best.x[:2], reverse=True)
    return [float(p % 720.0) for p in best.x[2:]], float(t1), float(t2)


def explained(b: Band, part: Cycles, cyl: int, offset: float, phase: float, tau1: float,
              tau2: float) -> float:
    """Share of the averaged coefficients' energy of ``part`` the model explains."""
    rpm, mean, coef = b.averaged(part)
    pred = predict(rpm, mean, offset, cyl, phase, tau1, tau2)
    return float(1.0 - np.sum(np.abs(coef - pred) ** 2) / np.sum(np.abs(coef) ** 2))


# -- the design -----------------------------------------------------------------------------
def design_logs(logs: Sequence[str | Path | Sequence[can.Message]], known: tuple[int, float], *, db=None,
                progress: bool = False) -> dict[str, Any]:
    """The design (module docstring) of ``logs`` with the known offset ``(cylinder,
    offset)``; :class:`ConfigError` naming why a log cannot identify it."""
    cyl, offset = known
    parts, steps = [], []
    names = [str(log) if isinstance(log, (str, Path)) else f"frames {i + 1}"
             for i, log in enumerate(logs)]
    for log, name in zip(logs, names, strict=True):
        c = read_cycles(log, db=db, progress=progress)
        t_step = find_step(c, cyl, name)
        k = int(np.searchsorted(c.t, t_step))
        steps.append({"log": name, "t": round(t_step, 4), "cycle": k, "cycles": int(len(c.t))})
        after = np.arange(k + SKIP_CYCLES, len(c.t))
        parts.append(c.select(after[c.t[after] >= t_step + SKIP_SECONDS]))
    allc = Cycles(*(np.concatenate([getattr(p, f) for p in parts])
                    for f in ("t", "rpm", "mean", "coef")))
    bs = bands(allc)
    if not bs:
        raise ConfigError(f"no speed band of {BAND:.0%} holds {MIN_CYCLES} engine cycles with the "
                          "offset: hold the engine at a speed for longer")
    phases, tau1, tau2 = fit(bs, cyl, offset)
    points, fits = [], []
    for b, ph in zip(bs, phases, strict=True):
        points.append({"rpm": round(b.rpm, 1), "phase_deg": round(ph, 2),
                       "cycles": int(len(b.fit.t) + len(b.held.t))})
        fits.append({"rpm": round(b.rpm, 1),
                     "explained_fit": round(explained(b, b.fit, cyl, offset, ph, tau1, tau2), 4),
                     "explained_held_out": round(explained(b, b.held, cyl, offset, ph, tau1, tau2), 4),
                     "held_out_cycles": int(len(b.held.t))})
    worst = min(f["explained_held_out"] for f in fits)
    if not worst >= MIN_EXPLAINED:
        raise ConfigError(f"the model explains only {worst:.0%} of the held-out cycles (needs "
                          f"{MIN_EXPLAINED:.0%}): is the offset on cylinder {cyl}, and the speed "
                          "steady in each band?")
    out = {
        "format": DESIGN_FORMAT,
        "observer": "afr_inversion",
        "design": "imbalance",
        "params": {"tau1": round(tau1, 6), "tau2": round(tau2, 6)},
        "source": names,
        "known_offset": {"cylinder": cyl, "offset": offset},
        "steps": steps,
        "identified": {
            "points": points, "tau1": round(tau1, 6), "tau2": round(tau2, 6),
            "about": "phase_deg: crank angle after each cylinder's firing TDC where its exhaust "
                     "window at the UEGO begins; tau1, tau2: the UEGO's two lags, s",
        },
        "fit": {"held_out": HOLD_OUT, "explained_held_out": worst, "per_speed": fits},
    }
    check_design(out)  # what the observer will load
    return out


def write(design: dict[str, Any], out: str | Path) -> Path:
    out = Path(out)
    write_text_atomic(out, json.dumps(design, indent=2) + "\n")
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", metavar="LOG",
                        help="CAN logs of the si-turbo engine with a known offset on one cylinder "
                             "(testcell sim --engine si-turbo --duty steady --imbalance 2:+0.15 "
                             "--out imb.log, or testcell scenario fuel_offset_cyl_2=0.15 mid-run)")
    parser.add_argument("--known-offset", required=True, metavar="CYL:OFFSET",
                        help="the cylinder and fuel offset of the run, e.g. 2:+0.15")
    parser.add_argument("--out", default="imbalance_design.json", metavar="FILE",
                        help="design file to write, JSON (default imbalance_design.json)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def main(args: argparse.Namespace) -> int:
    known = parse_known_offset(args.known_offset)
    d = design_logs(args.logs, known, progress=not args.quiet)
    write(d, args.out)
    ident = d["identified"]
    pts = ", ".join(f"{p['rpm']:g} rpm: {p['phase_deg']:g} deg" for p in ident["points"])
    print(f"wrote {args.out}: exhaust phase {pts}; UEGO lags {ident['tau1'] * 1e3:.1f} ms, "
          f"{ident['tau2'] * 1e3:.1f} ms; held-out fit explains "
          f"{d['fit']['explained_held_out']:.1%}")
    return 0


IMBALANCE_DESIGN = Experiment(
    "imbalance", "exhaust phase and UEGO lags of afr_inversion from a run with a known offset",
    add_arguments, main, seed="seed 001",
    description="Find where a known fuel offset on one cylinder starts in LOG, fit the exhaust "
                "transport phase (crank degrees, per engine speed) and the UEGO's two lags to "
                "the UEGO's Fourier coefficients per engine cycle, check the fit on a held-out "
                "part, and write the design file the afr_inversion observer loads.")
