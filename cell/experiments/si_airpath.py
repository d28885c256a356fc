r"""``testcell experiment airpath``: seed 003's Figures 1, 3, 5 and 6 on the emulated engine.

One ``throttle-steps`` run of the ``si-turbo`` engine (1800 rpm, twelve load steps) goes
through the runtime's bus decoding (frames at the plant rate, sampled at 100 Hz ticks); the
same sampled inputs then drive three copies of the air-path observer on the default model:

- the model alone, without feedback (Figure 1's "model", Figure 6's comparison);
- the constant-gain EKF without ΔC_ηvol (Figure 5);
- the augmented constant-gain EKF (Figure 6).

Numbers (all against simulator truth ``*_TRUE`` unless said otherwise):

- noise of P_IM_EST and of the measured P_IM about their segment means at steady state,
  their ratio, and the lag of each at the steps (the shift that best aligns it with the
  truth, :func:`_lag`); a causal first-order low-pass with the *same* noise reduction and
  its lag;
- per step case, the stationary error of P_IM_EST against the measured P_IM (the paper's
  criterion, "converges to measured") and against the truth, with and without ΔC_ηvol;
- N_TC_EST against N_TC_TRUE at steady state (feedback from P_IC and P_IM only);
- CAC_EST against CAC_TRUE, with and without ΔC_ηvol.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from cell.analysis.figures import format_table, output_folder, pyplot, save
from cell.core.errors import ConfigError
from cell.estimators.si_airpath import AirPathObserver, GainTable
from cell.core.registry import Experiment

#: Channels sampled at every tick.
CHANNELS = ("THROTTLE", "WASTEGATE", "ENGINE_SPEED", "SI_LOAD_DEMAND", "P_IC", "P_IM", "T_IM",
            "N_TC", "P_IC_TRUE", "P_IM_TRUE", "T_IM_TRUE", "P_EM_TRUE", "N_TC_TRUE", "CAC_TRUE")
#: Observer outputs recorded per variant.
EST = ("P_IC_EST", "P_IM_EST", "T_IM_EST", "P_EM_EST", "N_TC_EST", "CAC_EST", "DC_ETA_VOL_EST",
       "AIRPATH_POINT")
VARIANTS = ("model", "plain", "augmented")
#: Seconds after a step before the stationary window starts, and its length at the hold's end.
SETTLE, WINDOW = 4.0, 2.0


class OpenLoop(AirPathObserver):
    """The default model run without feedback (the observer with a zero gain)."""

    def _matrices(self, dt, augmented, feedback):
        M, K = super()._matrices(dt, augmented, feedback)
        return M, [np.zeros_like(k) for k in K]


def simulate(seed: int = 0, hold: float = 8.0, rate_hz: float = 100.0, progress: bool = False,
             cycle=None) -> dict[str, np.ndarray]:
    """One run through the simulator, the bus frames and the runtime's channels: every
    channel of :data:`CHANNELS` at every tick, as arrays (with ``t``)."""
    from cell.bus.dbc import load
    from cell.sim.lockstep import Lockstep
    from cell.plant.si_engine import throttle_steps_cycle
    from cell.plant.si_turbo import si_turbo
    from cell.runtime.scheduler import Rates, Runtime
    from cell.sim.simulator import Simulator

    cycle = cycle or throttle_steps_cycle(hold)
    db = load()
    plant = si_turbo(cycle, seed, crank=False)
    sim = Simulator(plant, db)
    rt = Runtime(db, rates=Rates(FAS=rate_hz, MED=rate_hz, SLO=1.0), history_s=1.0)
    rows: list[list[float]] = []

    def on_tick(t: float) -> None:
        ch = rt.channels
        row = [t]
        for name in CHANNELS:
            c = ch.get(name)
            row.append(math.nan if c is None or c.value is None else float(c.value))
        rows.append(row)

    steps = round(cycle.duration / sim.dt)
    stride = max(1, round(1.0 / rate_hz / sim.dt))
    bar = tqdm(total=round(cycle.duration), unit="s", desc="sim throttle-steps", disable=not progress)
    per_s = round(1.0 / sim.dt)
    for k, _ in Lockstep(sim, rt, stride=stride, on_tick=on_tick).steps(steps):
        if (k + 1) % per_s == 0:
            bar.update(1)
    bar.close()
    a = np.array(rows, dtype=float)
    out = {"t": a[:, 0]}
    for i, name in enumerate(CHANNELS):
        out[name] = a[:, i + 1]
    return out


def observe(run: dict[str, np.ndarray], variant: str, table: GainTable | None = None,
            feedback: Sequence[str] = ("P_IC", "P_IM")) -> dict[str, np.ndarray]:
    """Step one observer variant over the sampled inputs of a run, tick by tick, exactly as
    the runtime steps the block."""
    cls = OpenLoop if variant == "model" else AirPathObserver
    obs = cls("airpath", table, augmentation=variant == "augmented", feedback=feedback)
    names = obs.inputs
    cols = [run[n] for n in names]
    out = np.full((run["t"].size, len(EST)), np.nan)
    for k, t in enumerate(run["t"]):
        inputs = {n: float(c[k]) for n, c in zip(names, cols)}
        if any(math.isnan(v) for v in inputs.values()):
            continue
        o = obs.step(float(t), inputs)
        out[k] = [o[e] for e in EST]
    return {e: out[:, i] for i, e in enumerate(EST)}


def step_times(run: dict[str, np.ndarray]) -> list[float]:
    """Times at which the load demand steps."""
    load = run["SI_LOAD_DEMAND"]
    idx = np.flatnonzero(np.abs(np.diff(load)) > 0.02) + 1
    times: list[float] = []
    for i in idx:
        t = float(run["t"][i])
        if not times or t - times[-1] > 1.0:
            times.append(t)
    return times


def holds(run: dict[str, np.ndarray]) -> list[tuple[float, float]]:
    """(start, end) of each hold after its step (the first hold included)."""
    st = step_times(run)
    edges = [float(run["t"][0]) - SETTLE + 1.0, *st, float(run["t"][-1])]
    return list(zip(edges[:-1], edges[1:]))


def _lag(t: np.ndarray, y: np.ndarray, truth: np.ndarray, t_step: float, dt: float) -> float:
    r"""Delay of ``y`` behind ``truth`` at a step: the shift :math:`\tau` (a whole number of
    samples, -0.3 to 1.5 s) that minimises the mean square of
    :math:`y(t) - b - \mathrm{truth}(t - \tau)` over 0.5 s before to 1.5 s after the step,
    with :math:`b` the bias of ``y`` over the 0.5 s before it (a stationary error is not a lag)."""
    k0 = int(np.searchsorted(t, t_step))
    pre, post = round(0.5 / dt), round(1.5 / dt)
    if k0 - pre - round(1.5 / dt) < 0 or k0 + post > t.size:
        return math.nan
    b = float(np.nanmean(y[k0 - pre:k0] - truth[k0 - pre:k0]))
    seg = y[k0 - pre:k0 + post] - b
    best, best_s = math.inf, 0
    for s in range(-round(0.3 / dt), round(1.5 / dt) + 1):
        ref = truth[k0 - pre - s:k0 + post - s]
        err = float(np.nanmean((seg - ref) ** 2))
        if err < best:
            best, best_s = err, s
    return best_s * dt


def lowpass(y: np.ndarray, a: float) -> np.ndarray:
    """Causal first-order low-pass :math:`y_f[k] = y_f[k-1] + a (y[k] - y_f[k-1])`."""
    import scipy.signal

    ok = np.where(np.isfinite(y), y, np.nanmean(y))
    zi = scipy.signal.lfilter_zi([a], [1.0, a - 1.0]) * ok[0]
    return scipy.signal.lfilter([a], [1.0, a - 1.0], ok, zi=zi)[0]


def _noise(t: np.ndarray, err: np.ndarray, windows: list[tuple[float, float]]) -> float:
    """Std of ``err`` about its mean in each stationary window, pooled."""
    parts = []
    for a, b in windows:
        sel = (t >= a) & (t <= b) & np.isfinite(err)
        if sel.sum() > 10:
            parts.append(err[sel] - err[sel].mean())
    return float(np.std(np.concatenate(parts)))


@dataclass
class StepCase:
    """One step case: the stationary errors at the end of its hold, kPa (CAC in %)."""

    t_step: float
    load: float
    p_im_true: float
    plain_vs_meas: float
    augmented_vs_meas: float
    plain_vs_true: float
    augmented_vs_true: float
    model_vs_true: float
    cac_err_plain_pct: float
    cac_err_augmented_pct: float
    n_tc_err_pct: float


@dataclass
class Result:
    """What the experiment measured (see the module docstring)."""

    dt: float
    noise_meas_kpa: float
    noise_est_kpa: float
    noise_ratio: float
    lag_est_s: float
    lag_meas_s: float
    lpf_alpha: float
    lag_lpf_s: float
    lag_est_max_s: float
    lag_lpf_min_s: float
    lags_est_s: list[float]
    lags_lpf_s: list[float]
    n_tc_err_max_pct: float
    cac_rms_plain_pct: float
    cac_rms_augmented_pct: float
    cases: list[StepCase] = field(default_factory=list)

    def as_json(self) -> dict[str, Any]:
        return asdict(self)


def matched_lowpass(run: dict[str, np.ndarray], steady: list[tuple[float, float]],
                    ratio: float, n_meas: float) -> float:
    """The coefficient of the low-pass whose noise reduction is the observer's ``ratio``: it
    is linear, so its noise is the filtered measurement noise; bisection on the coefficient."""
    t = run["t"]
    noise = run["P_IM"] - run["P_IM_TRUE"]
    lo, hi = 1e-5, 1.0
    for _ in range(50):
        a = math.sqrt(lo * hi)
        r = _noise(t, lowpass(noise, a), steady) / n_meas
        lo, hi = (lo, a) if r > ratio else (a, hi)
    return math.sqrt(lo * hi)


def step_cases(run: dict[str, np.ndarray], est: dict[str, dict[str, np.ndarray]]
               ) -> list[StepCase]:
    """The stationary errors over the last :data:`WINDOW` s of every hold after a step."""
    t, truth = run["t"], run["P_IM_TRUE"]
    aug, plain, model = est["augmented"], est["plain"], est["model"]
    cases = []
    for a, b in holds(run)[1:]:
        sel = (t >= b - WINDOW) & (t <= b)

        def m(y, sel=sel):
            return float(np.nanmean(y[sel]))
        cac = m(run["CAC_TRUE"])
        cases.append(StepCase(
            t_step=a, load=m(run["SI_LOAD_DEMAND"]), p_im_true=m(truth),
            plain_vs_meas=m(plain["P_IM_EST"]) - m(run["P_IM"]),
            augmented_vs_meas=m(aug["P_IM_EST"]) - m(run["P_IM"]),
            plain_vs_true=m(plain["P_IM_EST"]) - m(truth),
            augmented_vs_true=m(aug["P_IM_EST"]) - m(truth),
            model_vs_true=m(model["P_IM_EST"]) - m(truth),
            cac_err_plain_pct=100.0 * (m(plain["CAC_EST"]) - cac) / cac,
            cac_err_augmented_pct=100.0 * (m(aug["CAC_EST"]) - cac) / cac,
            n_tc_err_pct=100.0 * (m(aug["N_TC_EST"]) - m(run["N_TC_TRUE"])) / m(run["N_TC_TRUE"])))
    return cases


def analyse(run: dict[str, np.ndarray], est: dict[str, dict[str, np.ndarray]]) -> Result:
    """The numbers of the experiment from a run and its three observer variants."""
    t = run["t"]
    dt = float(np.median(np.diff(t)))
    steady = [(a + SETTLE, b) for a, b in holds(run)]
    aug, plain = est["augmented"], est["plain"]
    truth = run["P_IM_TRUE"]
    n_meas = _noise(t, run["P_IM"] - truth, steady)
    n_est = _noise(t, aug["P_IM_EST"] - truth, steady)
    ratio = n_est / n_meas
    a_lpf = matched_lowpass(run, steady, ratio, n_meas)
    lpf = lowpass(run["P_IM"], a_lpf)
    lags_est, lags_lpf, lags_meas = [], [], []
    for t_step in step_times(run):
        lags_est.append(_lag(t, aug["P_IM_EST"], truth, t_step, dt))
        lags_lpf.append(_lag(t, lpf, truth, t_step, dt))
        lags_meas.append(_lag(t, run["P_IM"], truth, t_step, dt))
    cases = step_cases(run, est)
    ok = np.isfinite(aug["CAC_EST"]) & (t > holds(run)[1][0])  # after the first hold

    def rms_pct(y):
        cac = run["CAC_TRUE"][ok]
        return float(100.0 * np.sqrt(np.mean(((y[ok] - cac) / cac) ** 2)))
    return Result(
        dt=dt, noise_meas_kpa=n_meas, noise_est_kpa=n_est, noise_ratio=ratio,
        lag_est_s=float(np.nanmedian(lags_est)), lag_meas_s=float(np.nanmedian(lags_meas)),
        lpf_alpha=a_lpf, lag_lpf_s=float(np.nanmedian(lags_lpf)),
        lag_est_max_s=float(np.nanmax(lags_est)), lag_lpf_min_s=float(np.nanmin(lags_lpf)),
        lags_est_s=lags_est, lags_lpf_s=lags_lpf,
        n_tc_err_max_pct=float(max(abs(c.n_tc_err_pct) for c in cases)),
        cac_rms_plain_pct=rms_pct(plain["CAC_EST"]), cac_rms_augmented_pct=rms_pct(aug["CAC_EST"]),
        cases=cases)


# -- the experiment ----------------------------------------------------------------------------
def run_experiment(seed: int = 0, hold: float = 8.0, table: GainTable | None = None,
                   progress: bool = False) -> tuple[dict, dict, Result]:
    """Record one run, step the three observer variants over it, score them."""
    run = simulate(seed, hold, progress=progress)
    est = {v: observe(run, v, table) for v in tqdm(VARIANTS, desc="observers", disable=not progress)}
    return run, est, analyse(run, est)


# -- figures -----------------------------------------------------------------------------------
def _step_window(run: dict, case: int = 1) -> np.ndarray:
    """The ticks from 2 s before the step of hold ``case`` to 6 s after it."""
    a, _ = holds(run)[case]
    return (run["t"] >= a - 2.0) & (run["t"] <= a + 6.0)


#: Line styles of the figures' traces.
MEASURED = {"color": "0.6", "lw": 0.8, "label": "measured"}
MODEL = {"color": "C0", "ls": ":", "lw": 1.2, "label": "model"}
OBSERVER = {"color": "C3", "lw": 1.4, "label": "observer"}
AUGMENTED = {"color": "C2", "lw": 1.5, "label": "augmented observer"}


def _lines(ax, t: np.ndarray, lines, label: str) -> None:
    """``(y, style)`` lines on ``ax`` (``style``: the keywords of ``plot``), its y label and
    grid."""
    for y, style in lines:
        ax.plot(t, y, **style)
    ax.set_ylabel(label)
    ax.grid(alpha=0.3)


def plot_figure1(path: Path, run: dict, est: dict, case: int = 1) -> Path:
    """Figure 1: the default model alone against the engine on a step."""
    plt = pyplot()
    sel = _step_window(run, case)
    t, m = run["t"][sel], est["model"]
    fig, ax = plt.subplots(2, 2, figsize=(10, 6.5))
    panels = (("P_IM", "p_im [kPa]", 0, 0), ("T_IM", "T_im [°C]", 0, 1), ("P_IC", "p_ic [kPa]", 1, 0),
              ("N_TC", "N_tc [rpm]", 1, 1))
    for name, label, i, j in panels:
        _lines(ax[i][j], t, ((run[name][sel], MEASURED),
                             (run[name + "_TRUE"][sel],
                              {"color": "k", "ls": "--", "lw": 1.0, "label": "engine (truth)"}),
                             (m[name + "_EST"][sel], MODEL | {"ls": "-", "lw": 1.4})), label)
    ax[0][0].legend(fontsize=8)
    ax[1][0].set_xlabel("time [s]")
    ax[1][1].set_xlabel("time [s]")
    fig.suptitle("Seed 003, Figure 1: the default model against the engine on a throttle step at 1800 rpm")
    return save(fig, path)


def plot_figure3(path: Path, table: GainTable) -> Path:
    """Figure 3: feedback gains of the table over the air mass flow of its points."""
    from cell.plant.si_airpath import MODEL_PARAMS, flows

    plt = pyplot()
    w = np.array([flows(p.x, p.u, MODEL_PARAMS).w_ac for p in table.points])
    K = np.array([p.K["plain"] for p in table.points])  # (points, 5, 2): feedback P_IC, P_IM
    speed = np.array([p.speed for p in table.points])
    fig, ax = plt.subplots(2, 2, figsize=(10, 7), constrained_layout=True)
    panels = ((0, 0, "p_ic from measured p_ic [-]"), (1, 1, "p_im from measured p_im [-]"),
              (1, 0, "p_im from measured p_ic [-]"), (4, 0, "ω_tc from measured p_ic [rad/s per Pa]"))
    for k, (row, col, title) in enumerate(panels):
        axx = ax[k // 2][k % 2]
        sc = axx.scatter(w, K[:, row, col], c=speed, cmap="viridis", s=25)
        axx.set_title(title, fontsize=9)
        axx.set_xlabel("air mass flow [kg/s]")
        axx.grid(alpha=0.3)
    fig.colorbar(sc, ax=ax, label="engine speed [rpm]")
    fig.suptitle(f"Seed 003, Figure 3: feedback gains over the operating points (dt = {table.dt:g} s)")
    return save(fig, path)


def plot_figure5(path: Path, run: dict, est: dict, case: int = 1) -> Path:
    """Figure 5: the observer without ΔCη_vol on a step."""
    plt = pyplot()
    sel = _step_window(run, case)
    t = run["t"][sel]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for axx, name, label in ((ax[0], "P_IC", "p_ic [kPa]"), (ax[1], "P_IM", "p_im [kPa]")):
        _lines(axx, t, ((run[name][sel], MEASURED), (est["model"][name + "_EST"][sel], MODEL),
                        (est["plain"][name + "_EST"][sel], OBSERVER),
                        (run[name + "_TRUE"][sel],
                         {"color": "k", "ls": "--", "lw": 0.9, "label": "truth"})), label)
        axx.set_xlabel("time [s]")
    ax[1].legend(fontsize=8)
    fig.suptitle("Seed 003, Figure 5: the observer without ΔCη_vol (a stationary error remains)")
    return save(fig, path)


def plot_figure6(path: Path, run: dict, est: dict, case: int = 1) -> Path:
    """Figure 6: the augmented observer on a step: p_im, CAC, ΔCη_vol and N_tc."""
    plt = pyplot()
    sel = _step_window(run, case)
    t = run["t"][sel]
    aug, plain, model = est["augmented"], est["plain"], est["model"]
    observer = OBSERVER | {"ls": "--", "lw": 1.0}
    fig, ax = plt.subplots(2, 2, figsize=(10, 6.5))
    _lines(ax[0][0], t, ((run["P_IM"][sel], MEASURED), (model["P_IM_EST"][sel], MODEL),
                         (plain["P_IM_EST"][sel], observer), (aug["P_IM_EST"][sel], AUGMENTED)),
           "p_im [kPa]")
    _lines(ax[0][1], t, ((run["CAC_TRUE"][sel], {"color": "k", "ls": "--", "lw": 1.0,
                                                  "label": "truth"}),
                         (plain["CAC_EST"][sel], observer), (aug["CAC_EST"][sel], AUGMENTED)),
           "CAC [mg/cyl/cycle]")
    _lines(ax[1][0], t, ((aug["DC_ETA_VOL_EST"][sel], {"color": "C2", "lw": 1.5}),), "ΔCη_vol [-]")
    _lines(ax[1][1], t, ((run["N_TC"][sel], MEASURED), (model["N_TC_EST"][sel], MODEL),
                         (aug["N_TC_EST"][sel], AUGMENTED)), "N_tc [rpm]")
    for x in (ax[0][0], ax[0][1], ax[1][1]):
        x.legend(fontsize=8)
    for row in ax:
        for x in row:
            x.set_xlabel("time [s]")
    fig.suptitle("Seed 003, Figure 6: the augmented observer (feedback from p_ic and p_im)")
    return save(fig, path)


def figures(out: Path, run: dict, est: dict, table: GainTable) -> list[Path]:
    """Seed 003's Figures 1, 3, 5 and 6 in ``out``."""
    return [plot_figure1(out / "figure1_model.png", run, est),
            plot_figure3(out / "figure3_gains.png", table),
            plot_figure5(out / "figure5_observer.png", run, est),
            plot_figure6(out / "figure6_augmented.png", run, est)]


# -- report ------------------------------------------------------------------------------------
#: Widths of the step-case table's columns (two spaces apart; a wider gap is in the width).
CASE_WIDTHS = (4, 6, 4, 5, 7, 10, 11, 9, 10, 10, 6, 9)


def format_report(r: Result) -> str:
    """The printed numbers: noise, lag, N_TC and CAC, then the step cases."""
    lines = [
        f"P_IM noise at steady state (std about segment means, vs truth): measured "
        f"{r.noise_meas_kpa:.2f} kPa, observer {r.noise_est_kpa:.2f} kPa (ratio {r.noise_ratio:.2f})",
        f"lag behind the truth at the steps (best-aligning shift, median): observer "
        f"{r.lag_est_s * 1000:.0f} ms "
        f"(max {r.lag_est_max_s * 1000:.0f} ms, one sample = {r.dt * 1000:.0f} ms), measured "
        f"{r.lag_meas_s * 1000:.0f} ms, low-pass with the same noise reduction (a = {r.lpf_alpha:.3f}) "
        f"{r.lag_lpf_s * 1000:.0f} ms (min {r.lag_lpf_min_s * 1000:.0f} ms)",
        f"N_TC_EST vs truth at steady state (feedback P_IC, P_IM): max {r.n_tc_err_max_pct:.2f} %",
        f"CAC_EST vs CAC_TRUE from the first step on, RMS: without dC_eta_vol {r.cac_rms_plain_pct:.2f} %, "
        f"with {r.cac_rms_augmented_pct:.2f} %",
        "",
        "case  t_step  load  p_im   P_IM_EST - P_IM (meas)   P_IM_EST - truth        model-truth  "
        "CAC error %        N_TC err",
        "                   kPa    plain     augmented      plain     augmented     kPa          "
        "plain  augmented   %",
    ]
    rows = [[f"{i:d}", f"{c.t_step:.1f}", f"{c.load:.2f}", f"{c.p_im_true:.1f}",
             *(f"{v:+.2f}" for v in (c.plain_vs_meas, c.augmented_vs_meas, c.plain_vs_true,
                                     c.augmented_vs_true, c.model_vs_true, c.cac_err_plain_pct,
                                     c.cac_err_augmented_pct, c.n_tc_err_pct))]
            for i, c in enumerate(r.cases, 1)]
    if rows:
        lines.append(format_table(rows, widths=CASE_WIDTHS))
    return "\n".join(lines)


# -- command line ------------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="airpath-out", metavar="DIR",
                        help="folder for the figures (default airpath-out)")
    parser.add_argument("--json", action="store_true", help="print the numbers as JSON")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--hold", type=float, default=8.0,
                        help="seconds each load level is held (default 8)")
    parser.add_argument("--table", default=None, metavar="FILE",
                        help="gain table (default: the shipped one)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def main(args: argparse.Namespace) -> int:
    if not (math.isfinite(args.hold) and args.hold >= SETTLE + WINDOW):
        raise ConfigError(f"--hold must be at least {SETTLE + WINDOW:g} s, got {args.hold}")
    table = GainTable.load(args.table) if args.table else GainTable.load()
    out = output_folder(args.out)
    run, est, result = run_experiment(args.seed, args.hold, table, progress=not args.quiet)
    figs = figures(out, run, est, table)
    if args.json:
        print(json.dumps(result.as_json() | {"figures": [str(f) for f in figs]}, indent=1))
    else:
        print(format_report(result))
        print("\nfigures: " + ", ".join(str(f) for f in figs))
    return 0


AIRPATH = Experiment(
    "airpath", "SI air-path observer on throttle steps: noise, lag, ΔCη_vol, N_TC, CAC",
    add_arguments, main, seed="seed 003, Figures 1, 3, 5, 6",
    description=__doc__.split("\n\n")[0] if __doc__ else "")
