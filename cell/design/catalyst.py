"""``testcell design twc``: the λ sensors' response and the kinetics scale of the catalyst
observer, from a log of a catalyst in a known state.

What the paper leaves open, and the observer's OSC depends on most (issue 18), is how the
wide-band λ sensors respond in the fuel-cut → purge transients: their time constant, a dead
time, and whether the lag acts on λ or on the gas composition. The kinetics scale (A₁, A₂ of
eq. 16) moves the SOX estimate. Both are identified here, in named steps:

1. :func:`read_signals` — ``EXH_MASS_FLOW``, ``T_CAT``, ``LAMBDA_PRE``, ``LAMBDA_MID`` of
   the log at their frame rate, on a 10 ms grid (:func:`on_grid`).
2. :func:`fuel_cut_windows` — every exit from a fuel cut of a warm catalyst (λ_pre above
   ``cut_lambda`` for at least ``min_cut`` s, T_CAT above 350 °C), from ``lead_in`` s before
   the exit to ``after`` s after it. In fuel cut the catalyst fills with oxygen, so every
   window starts from a known state: φ = 1 in every cell, at the known OSC (``--osc``).
3. :func:`simulate` — for a candidate sensor model and kinetics scale: the engine-out λ from
   λ_pre with the sensor's lag undone, ṁ and T_CAT shifted by the dead time, the observer's
   own catalyst model (:mod:`cell.estimators.catalyst`) from φ = 1, and the sensor applied to
   its outlet: the λ_mid the sensor would show.
4. :func:`fit` — for the lag on λ and the lag on composition in turn: τ by
   :func:`scipy.optimize.least_squares` on λ_pre's step response at each exit (the engine's λ
   steps from the fuel cut's to the purge's; each exit has its own step time and purge λ,
   :func:`fit_sensor`), the lag whose steps fit better is taken; then the dead time (of λ
   against ṁ and T_CAT) and the kinetics scale by least squares on λ_mid, on the observer's
   measurement scale, through the catalyst. Fitted on the first two thirds of the windows;
   the last third is held out: its RMSE says how well the design predicts transients it was
   not fitted on.

A log with fewer than ``min_windows`` warm fuel cuts cannot identify this: the design is
refused (exit 2), naming why, and nothing is written.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cell.core.errors import ConfigError
from cell.core.registry import Experiment
from cell.estimators.catalyst import LAMBDA_LAGS, MODEL_KINETICS, SCALE_W
from cell.estimators.contract import DESIGN_FORMAT, write_design
from cell.plant.catalyst_model import TWCKinetics

SIGNALS = ("EXH_MASS_FLOW", "T_CAT", "LAMBDA_PRE", "LAMBDA_MID")
DT = 0.01
WARM = 350.0


@dataclass
class Window:
    """One fuel-cut exit on the 10 ms grid: the four signals from ``lead_in`` before it."""

    t_exit: float
    mdot: np.ndarray
    T_cat: np.ndarray
    lam_pre: np.ndarray
    lam_mid: np.ndarray
    start: int
    """Index of the first sample scored (the exit)."""


# -- 1. the log ---------------------------------------------------------------------------------
def read_signals(path: str | Path, progress: bool = False) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The catalyst observer's four signals in a CAN log, as (times, values)."""
    from cell.design.si_airpath import read_channels

    return read_channels(path, SIGNALS, progress=progress)


def on_grid(data: Mapping[str, tuple[np.ndarray, np.ndarray]], dt: float = DT
            ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Every signal held (latest value at or before) on one grid of period ``dt``."""
    missing = [s for s in SIGNALS if s not in data or len(data[s][0]) < 2]
    if missing:
        raise ConfigError(f"the log has no {', '.join(missing)} frames: it is not a log of the "
                          "si-turbo catalyst (testcell sim --engine si-turbo --out LOG)")
    t0 = max(float(data[s][0][0]) for s in SIGNALS)
    t1 = min(float(data[s][0][-1]) for s in SIGNALS)
    t = np.arange(t0, t1, dt)
    out = {}
    for s in SIGNALS:
        ts, vs = data[s]
        idx = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, len(ts) - 1)
        out[s] = vs[idx]
    return t, out


# -- 2. the transients --------------------------------------------------------------------------
def fuel_cut_windows(t: np.ndarray, sig: Mapping[str, np.ndarray], *, cut_lambda: float = 3.0,
                     min_cut: float = 1.0, lead_in: float = 0.5, after: float = 5.0,
                     dt: float = DT) -> list[Window]:
    """Every warm fuel-cut exit (see the module notes)."""
    pre = sig["LAMBDA_PRE"]
    cut = pre > cut_lambda
    edges = np.flatnonzero(cut[:-1] & ~cut[1:]) + 1  # first sample out of the cut
    n_lead, n_after, n_min = round(lead_in / dt), round(after / dt), round(min_cut / dt)
    out = []
    for e in edges.tolist():
        i0, i1 = e - n_lead, e + n_after
        if i0 - n_min < 0 or i1 > t.size or not cut[i0 - n_min:e].all():
            continue
        if cut[e:i1].any() or sig["T_CAT"][i0:i1].min() < WARM:
            continue  # another cut inside, or a cold catalyst: the kinetics hide OSC
        out.append(Window(float(t[e]), sig["EXH_MASS_FLOW"][i0:i1], sig["T_CAT"][i0:i1],
                          pre[i0:i1], sig["LAMBDA_MID"][i0:i1], n_lead))
    return out


# -- 3. the model of the windows ------------------------------------------------------------------
def _feed(lam: np.ndarray, c0: np.ndarray, k: TWCKinetics):
    """Feed gas of :func:`cell.plant.catalyst_model.feed_gas`, over arrays."""
    lam = np.maximum(lam, 0.5)
    lean = lam >= 1.0
    carbon = np.where(lean, k.y_c / (1.0 + k.y_c / k.y_o2_air * (lam - 1.0)), k.y_c) * c0
    o2 = np.where(lean, (lam - 1.0) * carbon, 0.0)
    co = np.where(lean, 0.0, 2.0 * (1.0 - lam) * carbon)
    return o2, co, carbon


def _undo(m, Np, Dp, a, k):
    """:func:`cell.estimators.catalyst.undo_composition_lag` over arrays."""
    r = (1.0 - a) * (m * Dp - Np) / (a * 2.0 * k.y_c)
    lam = m + r
    c = k.y_c / k.y_o2_air
    den = 1.0 - r * c
    lean = np.where(den > 1e-9, (m + r * (1.0 - c)) / np.where(den > 1e-9, den, 1.0), 16.0)
    lam = np.clip(np.where(lam > 1.0, lean, lam), 0.5, 16.0)
    D = 2.0 * _feed(lam, 1.0, k)[2]
    return lam, Np + a * (lam * D - Np), Dp + a * (D - Dp)


def stack(windows: Sequence[Window]) -> dict[str, np.ndarray]:
    """The windows' signals as (samples, windows) arrays (they have one length)."""
    return {name: np.stack([getattr(w, name) for w in windows], axis=1)
            for name in ("mdot", "T_cat", "lam_pre", "lam_mid")}


def simulate(batch: Mapping[str, np.ndarray], lag: str, tau: float, dead: float,
             kin_scale: float, osc: float, kinetics: TWCKinetics = MODEL_KINETICS,
             dt: float = DT) -> np.ndarray:
    """The λ_mid the sensor would show over each window (columns of :func:`stack`), for one
    sensor model: the observer's equations (:mod:`cell.estimators.catalyst`, eqs. 15-17 and
    12) from φ = 1, in explicit Euler at ``dt``."""
    k = kinetics.scaled(A1=kin_scale, A2=kin_scale)
    a = -math.expm1(-dt / max(tau, 1e-4))
    pre, mid = batch["lam_pre"], batch["lam_mid"]
    n, nw = pre.shape
    j = np.arange(n) - dead / dt
    grid = np.arange(n)
    mdot = np.stack([np.interp(j, grid, batch["mdot"][:, c]) for c in range(nw)], axis=1)
    T_cat = np.stack([np.interp(j, grid, batch["T_cat"][:, c]) for c in range(nw)], axis=1)
    T = T_cat + 273.15
    c0 = k.pressure / (8.314 * T)
    tau_res = c0 * k.M_exh * k.area * k.dz / np.maximum(mdot, 1e-5)
    rt = 8.314 * T
    k1f = k.A1 * np.exp(-k.E1 / rt)
    k2f = k.A2 * np.exp(-k.E2 / rt)
    k1b, k2b = k1f * np.exp(k.dG1 / rt), k2f * np.exp(k.dG2 / rt)
    composition = lag == "composition"
    if composition:
        Dp = 2.0 * _feed(pre[0], 1.0, k)[2]
        Np = pre[0] * Dp
        Dm, Nm = Dp.copy(), mid[0] * Dp
        lam_in = np.empty_like(pre)
        for i in range(n):
            lam_in[i], Np, Dp = _undo(pre[i], Np, Dp, a, k)
    else:
        lam_in = np.clip(np.vstack([pre[:1], pre[:-1] + (pre[1:] - pre[:-1]) / a]), 0.5, 16.0)
        ym = mid[0].copy()
    o2_all, co_all, C_all = _feed(lam_in, c0, k)
    oscv = osc * k.osc_fresh
    phi = np.ones((3, nw))
    y = np.empty_like(pre)
    for i in range(n):
        o2, co, C, tr, cc = o2_all[i], co_all[i], C_all[i], tau_res[i], c0[i]
        for c in range(3):
            ce3 = (1.0 - phi[c]) * oscv
            ce4 = phi[c] * oscv
            o2n = (o2 + tr * k1b[i] * cc * ce4 * ce4) / (1.0 + tr * k1f[i] * ce3 * ce3)
            con = (co + tr * k2b[i] * C * ce3) / (1.0 + tr * (k2f[i] * ce4 + k2b[i] * ce3))
            phi[c] = np.clip(phi[c] + dt * (2.0 * (o2 - o2n) - (co - con)) / (tr * oscv), 0.0, 1.0)
            o2, co = o2n, con
        if composition:
            Nm = Nm + a * ((2.0 * o2 + 2.0 * C - co) / cc - Nm)
            Dm = Dm + a * (2.0 * C / cc - Dm)
            y[i] = Nm / Dm
        else:
            ym = ym + a * ((2.0 * o2 + 2.0 * C - co) / (2.0 * C) - ym)
            y[i] = ym
    return y


def _scale(v: np.ndarray) -> np.ndarray:
    return 1.0 + SCALE_W * np.tanh((v - 1.0) / SCALE_W)


def residuals(batch: Mapping[str, np.ndarray], start: int, lag: str, p: Sequence[float],
              osc: float) -> np.ndarray:
    """λ_mid predicted minus measured, on the observer's measurement scale, after each exit."""
    tau, dead, ks = p
    y = simulate(batch, lag, tau, dead, ks, osc)
    return (_scale(y[start:]) - _scale(batch["lam_mid"][start:])).ravel()


# -- 4. the fit -----------------------------------------------------------------------------------
@dataclass
class Fit:
    lag: str
    tau: float
    dead: float
    kinetics_scale: float
    rmse_fit: float
    rmse_check: float
    cost: float


def step_response(t: np.ndarray, lag: str, tau: float, t0: float, lam_hi: float, lam_lo: float,
                  k: TWCKinetics = MODEL_KINETICS) -> np.ndarray:
    """A λ sensor's reading after the engine's λ steps from ``lam_hi`` (fuel cut) to
    ``lam_lo`` (purge) at ``t0``: exponential in λ, or in the gas's N and D of eq. 12 (then
    λ = N / D), exact between samples."""
    e = np.exp(-np.maximum(t - t0, 0.0) / tau)
    if lag == "lambda":
        return lam_lo + (lam_hi - lam_lo) * e
    d_hi = 2.0 * _feed(np.array(lam_hi), 1.0, k)[2]
    d_lo = 2.0 * _feed(np.array(lam_lo), 1.0, k)[2]
    N = lam_lo * d_lo + (lam_hi * d_hi - lam_lo * d_lo) * e
    D = d_lo + (d_hi - d_lo) * e
    return N / D


def fit_sensor(windows: Sequence[Window], lag: str, dt: float = DT,
               span: tuple[float, float] = (-0.3, 1.0)):
    """τ of one lag from λ_pre's step at every fuel-cut exit (each with its own step time and
    purge λ): :func:`scipy.optimize.least_squares`; returns (τ, cost, RMSE, per-window t0)."""
    from scipy.optimize import least_squares

    parts = []
    for w in windows:
        i0, i1 = w.start + round(span[0] / dt), w.start + round(span[1] / dt)
        tt = (np.arange(i0, i1) - w.start) * dt
        hi = float(np.median(w.lam_pre[max(i0 - 30, 0):i0]))
        parts.append((tt, w.lam_pre[i0:i1], hi, float(np.median(w.lam_pre[i1 - 20:i1]))))
    nw = len(parts)

    def res(p):
        tau = p[0]
        out = [step_response(tt, lag, tau, p[1 + j], hi, p[1 + nw + j]) - y
               for j, (tt, y, hi, _) in enumerate(parts)]
        return np.concatenate(out)

    x0 = [0.1, *([-0.05] * nw), *[lo for *_, lo in parts]]
    lo_b = [0.01, *([span[0]] * nw), *([0.6] * nw)]
    hi_b = [1.0, *([0.2] * nw), *([1.5] * nw)]
    sol = least_squares(res, x0=x0, bounds=(lo_b, hi_b), max_nfev=200)
    return float(sol.x[0]), float(sol.cost), float(np.sqrt(np.mean(sol.fun ** 2)))


def fit(windows: Sequence[Window], osc: float, lags: Sequence[str] = LAMBDA_LAGS,
        check_share: float = 1 / 3) -> tuple[Fit, dict[str, Fit]]:
    """For each lag: τ from λ_pre's steps (:func:`fit_sensor`), then (dead time, kinetics
    scale) from λ_mid through the catalyst, on the first windows; checked on the held-out last
    ``check_share``. The lag whose λ_pre steps fit better is taken; returns it and every
    lag's fit."""
    from scipy.optimize import least_squares

    n_check = max(1, round(len(windows) * check_share))
    train_w = list(windows[:-n_check])
    train, check = stack(train_w), stack(windows[-n_check:])
    start = windows[0].start
    fits = {}
    for lag in lags:
        tau, cost, _ = fit_sensor(train_w, lag)
        sol = least_squares(lambda p, lag=lag, tau=tau: residuals(train, start, lag, (tau, *p), osc),
                            x0=[0.02, 1.0], bounds=([0.0, 0.1], [0.5, 10.0]),
                            x_scale=[0.05, 0.5], diff_step=[0.5, 0.05], max_nfev=30)
        r_fit = sol.fun
        r_check = residuals(check, start, lag, (tau, *sol.x), osc)
        fits[lag] = Fit(lag, tau, float(sol.x[0]), float(sol.x[1]),
                        float(np.sqrt(np.mean(r_fit ** 2))), float(np.sqrt(np.mean(r_check ** 2))),
                        cost)
    best = min(fits.values(), key=lambda f: f.cost)
    return best, fits


def design(data: Mapping[str, tuple[np.ndarray, np.ndarray]], osc: float = 1.0, *,
           min_windows: int = 3, max_windows: int = 12, source: str = "log") -> dict[str, Any]:
    """The design object of the ``twc`` observer from the signals of a log (steps 1-4);
    :class:`ConfigError` when the log cannot identify it."""
    if not (math.isfinite(osc) and 0.05 <= osc <= 2.0):
        raise ConfigError(f"--osc must be in [0.05, 2] (normalised to fresh), got {osc}")
    t, sig = on_grid(data)
    windows = fuel_cut_windows(t, sig)
    if len(windows) < min_windows:
        raise ConfigError(
            f"{source}: {len(windows)} warm fuel cut(s) (λ_pre above 3 for 1 s, then a purge, "
            f"T_CAT above {WARM:g} °C); the λ sensors' response and the kinetics are identified "
            f"on the fuel-cut -> purge transients, and at least {min_windows} are needed: "
            "record a drive with overrun fuel cuts (--duty ftp)")
    if len(windows) > max_windows:  # spread over the log
        pick = np.linspace(0, len(windows) - 1, max_windows).round().astype(int)
        windows = [windows[i] for i in pick]
    best, fits = fit(windows, osc)
    return {
        "format": DESIGN_FORMAT,
        "observer": "twc",
        "identified": {"lambda_lag": best.lag, "tau_lambda": round(best.tau, 5),
                       "dead_time": round(best.dead, 5),
                       "kinetics_scale": round(best.kinetics_scale, 5)},
        "fit": {
            "what": "λ_mid on the measurement scale after each fuel-cut exit, the catalyst "
                    "full at the exit, at the known OSC",
            "osc_known": osc, "windows": len(windows),
            "windows_held_out": max(1, round(len(windows) / 3)),
            "rmse_fit": best.rmse_fit, "rmse_held_out": best.rmse_check,
            "by_lag": {lag: {"cost": f.cost, "rmse_fit": f.rmse_fit,
                             "rmse_held_out": f.rmse_check, "tau_lambda": f.tau,
                             "dead_time": f.dead, "kinetics_scale": f.kinetics_scale}
                       for lag, f in fits.items()},
        },
        "source": source,
    }


def design_logs(logs: Sequence[str | Path], out: str | Path | None, osc: float = 1.0,
                progress: bool = False) -> dict[str, Any]:
    """Read the logs, design, and (with ``out``) write the file; nothing is written when the
    design is refused."""
    data: dict[str, tuple[list[np.ndarray], list[np.ndarray]]] = {}
    offset = 0.0
    for log in logs:
        one = read_signals(log, progress)
        end = 0.0
        for k, (ts, vs) in one.items():  # logs end to end, one second apart
            data.setdefault(k, ([], []))[0].append(ts - ts[0] + offset)
            data[k][1].append(vs)
            end = max(end, float(ts[-1] - ts[0]))
        offset += end + 1.0
    merged = {k: (np.concatenate(ts), np.concatenate(vs)) for k, (ts, vs) in data.items()}
    d = design(merged, osc, source=", ".join(str(x) for x in logs))
    if out is not None:
        write_design(d, out)
    return d


# -- command line -------------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", metavar="LOG",
                        help="CAN log(s) of the si-turbo catalyst in a known state, with fuel "
                             "cuts (testcell sim --engine si-turbo --duty ftp --out LOG)")
    parser.add_argument("--out", required=True, metavar="FILE", help="design file to write (JSON)")
    parser.add_argument("--osc", type=float, default=1.0, metavar="X",
                        help="the catalyst's known OSC, normalised to fresh (default 1: fresh)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def main(args: argparse.Namespace) -> int:
    d = design_logs(args.logs, args.out, args.osc, progress=not args.quiet)
    i, f = d["identified"], d["fit"]
    print(f"wrote {args.out}: λ sensor lag on {i['lambda_lag']}, τ {i['tau_lambda']:.3f} s, "
          f"dead time {i['dead_time']:.3f} s, kinetics x{i['kinetics_scale']:.2f}; "
          f"{f['windows']} fuel cuts, RMSE {f['rmse_fit']:.4f} (fit), "
          f"{f['rmse_held_out']:.4f} (held out)")
    return 0


TWC_DESIGN = Experiment(
    "twc", "λ sensor response and kinetics scale of the catalyst observer from a log",
    add_arguments, main, seed="seed 000, issue 18",
    description=__doc__.split("\n\n")[0] if __doc__ else "")
