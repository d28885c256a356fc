"""``testcell experiment closed-loop``: seed 004's Figure 10, with numbers.

Seed 004 ("Practical application") starts a 60 L engine at rated speed and load with the
back-pressure valve 100 % open in open loop, switches a PI loop on to 680 mmH2O and compares
three feedbacks: raw (unstable; an engine limit shut the engine down), the moving average
(steady after 150 s) and the Kalman filter (steady after 110 s, "3.34-6.67 L" of fuel
saved). This module reruns that experiment on the emulated cell, over several noise seeds,
with a fourth feedback, the adaptive filter of :mod:`cell.estimators.backpressure_adaptive`
(the paper's "future work"), and measures rather than asserts the Kalman filter's advantage.

Lockstep
--------
The engine (:func:`cell.plant.large_diesel`) and a :class:`~cell.runtime.scheduler.Runtime` run in one
process with no bus, through the one lockstep loop (:class:`cell.sim.lockstep.Lockstep`): at
every plant step the simulator's frames (stamped with simulation time, which is the bus
time) go to the runtime, the runtime runs its ticks up to that time, and the
``VALVE_DEMAND`` frames in its outbox go back to the simulator, before the plants step.
Only CAN frames pass between the two, as on the live bus. Because every block here ticks at
``MED`` (10 Hz) and every SIM message's cycle time divides 0.1 s, the frames of the steps
between two ticks are overwritten before any tick reads them; by default only the steps on
the tick grid are exchanged (``stride``), which gives the same numbers ten times faster (a
test checks this against ``stride=1``).

Start at rated
--------------
Each case builds the plant *at* rated (a one-knot duty cycle holding rated speed and full
load, in which the plant starts in steady state) with ``initial_valve=100``: the engine is at
rated and the valve fully open, 250 mmH2O. The controllers start disabled (open loop: they
track the valve position, 100 %), the filters run for ``t_enable`` (default 20 s, so the
30-sample moving average is full and the Kalman gain has converged), then both banks switch
to closed loop. Times are reported from that switch.

Metrics (per seed, both banks)
------------------------------
- settling time: from the switch until the true back-pressure of *both* banks is within
  ±3 % of the setpoint and stays there for 10 s (None if it never does);
- overshoot: the largest true back-pressure above the setpoint after the switch, % of it;
- IAE: ∫|true - setpoint| dt over the closed-loop run, mmH2O·s, mean of the banks;
- valve travel: Σ|Δdemand| over the closed-loop run, %, mean of the banks (the paper's
  "controller energy");
- tripped: the engine protection (1200 mmH2O on either bank) shut the engine down;
- fuel: ∫FUEL_RATE dt from the switch until settled, L (None if it never settles).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
from collections.abc import Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cell.analysis.figures import (
    format_table,
    format_value,
    output_folder,
    pyplot,
    save,
    write_csv,
)
from cell.bus import dbc as dbc_mod
from cell.bus.dbc import CellDatabase
from cell.control.backpressure import DEFAULT_KI, DEFAULT_KP, FEEDBACK, PIController, controllers
from cell.core import registry
from cell.core.errors import ConfigError
from cell.estimators.backpressure import native_filters
from cell.estimators.backpressure_adaptive import adaptive_filters
from cell.plant import BANKS, TRIPPED, DutyCycle, EngineParams, ExhaustParams, large_diesel
from cell.runtime.scheduler import Runtime
from cell.sim.lockstep import Lockstep
from cell.sim.simulator import Simulator

FEEDBACKS = tuple(FEEDBACK)  # raw, maf, kalman, adaptive
SETPOINT = 680.0
BAND = 0.03
HOLD_S = 10.0


@dataclass
class CaseResult:
    """One closed-loop run: one feedback, one seed, one pair of gains.

    Times are seconds after the switch to closed loop. ``trace`` holds the 10 Hz record
    (time, true back-pressure and valve demand per bank) when it was asked for.
    """

    feedback: str
    seed: int
    kp: float
    ki: float
    settling_time_s: float | None
    overshoot_pct: float
    iae: float
    valve_travel_pct: float
    tripped: bool
    trip_time_s: float | None
    fuel_l: float | None
    trace: dict[str, list[float]] | None = field(default=None, repr=False)

    def row(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("trace")
        return d


@dataclass
class Summary:
    """A feedback's results over seeds: medians, spread and trips (the ``--json`` object)."""

    feedback: str
    settling_time_s: float | None
    settling_spread_s: float | None
    overshoot_pct: float
    iae: float
    valve_travel_pct: float
    tripped: bool
    fuel_l: float | None
    seeds: int
    settled: int
    trips: int
    kp: float
    ki: float

    def as_json(self) -> dict[str, Any]:
        return asdict(self)


# -- record: one case in lockstep ---------------------------------------------------------------
def rated_hold(params: EngineParams, duration: float) -> DutyCycle:
    """A duty cycle holding rated speed and full load from t = 0 (the plant starts there)."""
    return DutyCycle("rated-hold", [(0.0, params.rated_speed, 1.0)], duration)


@dataclass
class Trace:
    """A closed-loop run at every MED tick after the switch: ``t`` in s after it, and the
    columns ``bp_<bank>`` (true back-pressure), ``demand_<bank>`` (valve demand) and
    ``fuel`` (L/h); ``dt`` is the tick period, ``trip_time_s`` when the engine tripped."""

    t: list[float]
    cols: dict[str, list[float]]
    dt: float
    trip_time_s: float | None


def case_cell(feedback: str, seed: int, kp: float, ki: float, duration: float, setpoint: float,
              engine: EngineParams, exhaust: ExhaustParams | None, db: CellDatabase,
              controller_settings: dict[str, Any] | None
              ) -> tuple[Simulator, Runtime, list[PIController]]:
    """The engine at rated with the valve fully open for ``duration`` s, and a runtime with
    every filter and both banks' PI controllers on ``feedback``, disabled (open loop)."""
    sim = Simulator(large_diesel(rated_hold(engine, duration), seed, initial_valve=100.0,
                                 engine=engine, exhaust=exhaust), db)
    ctrls = controllers(feedback, kp=kp, ki=ki, setpoint=setpoint, enable=False,
                        **(controller_settings or {}))
    rt = Runtime(db, [*native_filters(), *adaptive_filters(), *ctrls], history_s=1.0)
    return sim, rt, ctrls


def record_case(sim: Simulator, rt: Runtime, ctrls: Sequence[PIController], total: float,
                t_enable: float, stride: int | None = None) -> Trace:
    """Run ``total`` s in lockstep, switching the controllers on at ``t_enable``; record
    every MED tick from then on, until the end or an engine trip."""
    banks = sim.plant.plant("exhaust")
    med_steps = max(1, round(rt.rates.period("MED") / sim.dt))
    k_enable = round(t_enable / sim.dt)
    t: list[float] = []
    cols: dict[str, list[float]] = {f"bp_{b}": [] for b in BANKS}
    cols.update({f"demand_{b}": [] for b in BANKS})
    cols["fuel"] = []
    demand_ch = [rt.channels[c.output] for c in ctrls]
    fuel_ch = None

    def enable() -> None:
        for c in ctrls:
            rt.set_params(c.name, {"enable": True}, family="controller")

    if k_enable == 0:
        enable()
    for k, _ in Lockstep(sim, rt, stride=stride or med_steps).steps(round(total / sim.dt)):
        if banks.state == TRIPPED:
            break
        if k == k_enable - 1:
            enable()  # before the exchange of step k_enable: no tick runs in between
        if k >= k_enable and k % med_steps == 0:
            if fuel_ch is None:
                fuel_ch = rt.channels.get("FUEL_RATE")
            t.append(sim.t - t_enable)
            for b, ch in zip(BANKS, demand_ch, strict=True):
                cols[f"bp_{b}"].append(banks.truth[b])
                cols[f"demand_{b}"].append(ch.value if ch.value is not None else math.nan)
            cols["fuel"].append(fuel_ch.value if fuel_ch and fuel_ch.value is not None else 0.0)
    trip_time = None if banks.trip_time is None else banks.trip_time - t_enable
    return Trace(t, cols, med_steps * sim.dt, trip_time)


# -- score --------------------------------------------------------------------------------------
def _settling(t: np.ndarray, truth: np.ndarray, r: float, band: float, hold: float
              ) -> float | None:
    """First time in ``t`` from which ``truth`` stays within ``r`` ± band·r for ``hold`` s."""
    inside = np.abs(truth - r) <= band * abs(r)
    if not inside.any():
        return None
    # start of the current inside-run at each sample
    idx = np.arange(len(t))
    starts = np.where(inside & ~np.r_[False, inside[:-1]], idx, 0)
    run_start = np.maximum.accumulate(starts)
    ok = inside & (t - t[run_start] >= hold - 1e-9)
    hits = np.nonzero(ok)[0]
    return None if hits.size == 0 else float(t[run_start[hits[0]]])


def score_trace(tr: Trace, setpoint: float) -> dict[str, Any]:
    """The metrics of one run (module notes): the :class:`CaseResult` fields from
    ``settling_time_s`` to ``fuel_l``."""
    t = np.asarray(tr.t)
    bp = {b: np.asarray(tr.cols[f"bp_{b}"]) for b in BANKS}
    settle_each = [_settling(t, bp[b], setpoint, BAND, HOLD_S) for b in BANKS]
    settling = None if tr.trip_time_s is not None or None in settle_each else max(settle_each)
    over = max(float(np.max(bp[b], initial=-math.inf)) for b in BANKS)
    travel = [np.nansum(np.abs(np.diff(tr.cols[f"demand_{b}"]))) for b in BANKS]
    fuel = None
    if settling is not None:
        upto = t < settling
        fuel = float(np.sum(np.asarray(tr.cols["fuel"])[upto]) * tr.dt / 3600.0)
    return {"settling_time_s": settling,
            "overshoot_pct": max(0.0, (over - setpoint) / setpoint * 100.0),
            "iae": float(np.mean([np.sum(np.abs(bp[b] - setpoint)) * tr.dt for b in BANKS])),
            "valve_travel_pct": float(np.mean(travel)),
            "tripped": tr.trip_time_s is not None, "trip_time_s": tr.trip_time_s,
            "fuel_l": fuel}


def closed_loop(
    feedback: str = "kalman",
    seed: int = 0,
    kp: float | None = None,
    ki: float | None = None,
    *,
    duration: float = 300.0,
    t_enable: float = 20.0,
    setpoint: float = SETPOINT,
    engine: EngineParams | None = None,
    exhaust: ExhaustParams | None = None,
    db: CellDatabase | None = None,
    stride: int | None = None,
    trace: bool = False,
    controller_settings: dict[str, Any] | None = None,
) -> CaseResult:
    """Run one closed-loop case in lockstep and measure it.

    Parameters
    ----------
    feedback:
        ``raw``, ``maf``, ``kalman`` or ``adaptive`` (the bank's channel), or a channel
        pattern with ``{bank}``.
    seed:
        Noise seed of the plant.
    kp, ki:
        PI gains (default: the shipped :data:`cell.control.backpressure.DEFAULT_KP`/``DEFAULT_KI``).
    duration:
        Closed-loop time after the switch, s.
    t_enable:
        Open-loop time at rated, valve fully open, before the switch, s.
    engine, exhaust:
        Plant constants (default :class:`EngineParams`, :class:`ExhaustParams`).
    stride:
        Plant steps between the frames given to the runtime; default: one MED tick (exact,
        see the module notes). ``1`` feeds every frame.
    trace:
        Keep the 10 Hz record in :attr:`CaseResult.trace` (for the plot).
    controller_settings:
        Further :class:`~cell.control.backpressure.PIController` keywords.

    Returns
    -------
    CaseResult
    """
    if feedback not in FEEDBACK and "{bank}" not in feedback:
        raise ConfigError(f"--feedback {feedback!r} is not a feedback; choose from "
                          f"{', '.join(FEEDBACKS)}")
    kp = DEFAULT_KP if kp is None else kp
    ki = DEFAULT_KI if ki is None else ki
    total = t_enable + duration
    sim, rt, ctrls = case_cell(feedback, seed, kp, ki, total, setpoint, engine or EngineParams(),
                               exhaust, db or dbc_mod.load(), controller_settings)
    tr = record_case(sim, rt, ctrls, total, t_enable, stride)
    return CaseResult(feedback=feedback, seed=seed, kp=kp, ki=ki, **score_trace(tr, setpoint),
                      trace={"t": tr.t, **tr.cols} if trace else None)


def summarise(cases: Sequence[CaseResult]) -> Summary:
    """Medians over seeds; settling median over all seeds, a never-settled seed counting as
    infinitely slow (so the median is None when half or more never settle); spread is the
    max - min of the settled seeds' times."""
    times = [c.settling_time_s if c.settling_time_s is not None else math.inf for c in cases]
    med = statistics.median(times)
    settled = [x for x in times if math.isfinite(x)]
    fuels = [c.fuel_l if c.fuel_l is not None else math.inf for c in cases]
    fuel_med = statistics.median(fuels)
    return Summary(
        feedback=cases[0].feedback,
        settling_time_s=med if math.isfinite(med) else None,
        settling_spread_s=(max(settled) - min(settled)) if settled else None,
        overshoot_pct=statistics.median(c.overshoot_pct for c in cases),
        iae=statistics.median(c.iae for c in cases),
        valve_travel_pct=statistics.median(c.valve_travel_pct for c in cases),
        tripped=any(c.tripped for c in cases),
        fuel_l=fuel_med if math.isfinite(fuel_med) else None,
        seeds=len(cases),
        settled=len(settled),
        trips=sum(c.tripped for c in cases),
        kp=cases[0].kp,
        ki=cases[0].ki,
    )


def best_gains(grid: dict[tuple[float, float], Summary]) -> Summary:
    """The grid point with the shortest median settling (ties: the least valve travel)."""
    def key(s: Summary) -> tuple[float, float]:
        st = s.settling_time_s if s.settling_time_s is not None else math.inf
        return (st, s.valve_travel_pct)
    return min(grid.values(), key=key)


# -- many cases: over seeds, over gains -----------------------------------------------------------
def _run_case(job: tuple[str, int, float, float, float, bool]) -> CaseResult:
    feedback, seed, kp, ki, duration, trace = job
    return closed_loop(feedback, seed, kp, ki, duration=duration, trace=trace)


def run_cases(
    jobs: Sequence[tuple[str, int, float, float, float, bool]],
    workers: int = 1,
    progress: bool = True,
    desc: str = "closed-loop",
) -> list[CaseResult]:
    """Run ``(feedback, seed, kp, ki, duration, trace)`` jobs with a tqdm bar over cases,
    in ``workers`` processes (1: in this process). Results come back in job order."""
    from tqdm import tqdm

    with tqdm(total=len(jobs), unit="case", desc=desc, disable=not progress) as bar:
        if workers <= 1 or len(jobs) <= 1:
            out = []
            for job in jobs:
                out.append(_run_case(job))
                bar.update(1)
            return out
        with ProcessPoolExecutor(max_workers=workers) as pool:
            out = []
            for res in pool.map(_run_case, jobs, chunksize=1):
                out.append(res)
                bar.update(1)
            return out


def compare(
    feedbacks: Iterable[str] = FEEDBACKS,
    seeds: int = 5,
    kp: float | None = None,
    ki: float | None = None,
    duration: float = 300.0,
    workers: int = 1,
    progress: bool = True,
) -> tuple[list[Summary], list[CaseResult]]:
    """Every feedback over seeds ``0..seeds-1`` at one pair of gains; the summaries (one per
    feedback, in order) and every case (seed 0 of each feedback keeps its trace)."""
    kp = DEFAULT_KP if kp is None else kp
    ki = DEFAULT_KI if ki is None else ki
    feedbacks = list(feedbacks)
    jobs = [(fb, s, kp, ki, duration, s == 0) for fb in feedbacks for s in range(seeds)]
    cases = run_cases(jobs, workers, progress)
    summaries = [summarise([c for c in cases if c.feedback == fb]) for fb in feedbacks]
    return summaries, cases


#: Default gain-map grid: kp in %/mmH2O, ki in %/(mmH2O·s), around the shipped defaults.
GRID_KP = (0.0025, 0.005, 0.01, 0.02)
GRID_KI = (0.004, 0.008, 0.013, 0.02, 0.03)


def gain_map(
    feedbacks: Iterable[str] = ("maf", "kalman", "adaptive"),
    kps: Sequence[float] = GRID_KP,
    kis: Sequence[float] = GRID_KI,
    seeds: int = 5,
    duration: float = 300.0,
    workers: int = 1,
    progress: bool = True,
) -> dict[str, dict[tuple[float, float], Summary]]:
    """Median settling (and the rest) for every feedback over the kp × ki grid."""
    feedbacks = list(feedbacks)
    jobs = [(fb, s, kp, ki, duration, False)
            for fb in feedbacks for kp in kps for ki in kis for s in range(seeds)]
    cases = run_cases(jobs, workers, progress, desc="gain map")
    out: dict[str, dict[tuple[float, float], Summary]] = {fb: {} for fb in feedbacks}
    groups: dict[tuple[str, float, float], list[CaseResult]] = {}
    for c in cases:
        groups.setdefault((c.feedback, c.kp, c.ki), []).append(c)
    for (fb, kp, ki), cs in groups.items():
        out[fb][(kp, ki)] = summarise(cs)
    return out


# -- figures ------------------------------------------------------------------------------------
def plot_figure10(path: Path, cases: Sequence[CaseResult], summaries: Sequence[Summary],
                  setpoint: float = SETPOINT) -> Path:
    """Seed 004 Figure 10: back-pressure and valve demand over time, one panel per feedback
    (seed 0's run; truth of bank R, demand of bank R on the right axis)."""
    plt = pyplot()
    traced = {c.feedback: c for c in cases if c.trace is not None}
    order = [s.feedback for s in summaries if s.feedback in traced]
    fig, axes = plt.subplots(len(order), 1, figsize=(10, 2.6 * len(order)), sharex=True,
                             squeeze=False)
    for ax, fb in zip(axes[:, 0], order, strict=True):
        c = traced[fb]
        tr = c.trace
        t = np.asarray(tr["t"])
        ax.axhspan(setpoint * (1 - BAND), setpoint * (1 + BAND), color="tab:green", alpha=0.15,
                   label=f"settling band ±{BAND:.0%}")
        ax.axhline(setpoint, color="tab:green", lw=0.8, label=f"setpoint {setpoint:g} mmH2O")
        ax.plot(t, tr["bp_R"], color="tab:blue", lw=1.0, label="EXH_BP_R_TRUE")
        ax.set_ylabel("mmH2O")
        ax.set_ylim(0, 1300)
        ax2 = ax.twinx()
        ax2.plot(t, tr["demand_R"], color="tab:orange", lw=0.8, label="VALVE_DEMAND_R")
        ax2.set_ylabel("valve %")
        ax2.set_ylim(0, 105)
        settle = "never settles" if c.settling_time_s is None else \
            f"settled at {c.settling_time_s:.0f} s"
        trip = f", TRIPPED at {c.trip_time_s:.0f} s" if c.tripped else ""
        ax.set_title(f"{fb} feedback (seed {c.seed}, kp={c.kp:g}, ki={c.ki:g}): {settle}{trip}",
                     fontsize=9)
        if c.settling_time_s is not None:
            ax.axvline(c.settling_time_s, color="k", ls="--", lw=0.8, label="settled")
        ax.grid(alpha=0.3)
        handles, labels = ax.get_legend_handles_labels()
        h2, l2 = ax2.get_legend_handles_labels()
        ax2.legend(handles + h2, labels + l2, fontsize=7, loc="upper right", ncol=2)
    axes[-1, 0].set_xlabel("time after switching to closed loop [s]")
    return save(fig, path)


def plot_gain_map(path: Path, grids: dict[str, dict[tuple[float, float], Summary]]) -> Path:
    """Median settling time over kp × ki, one heat map per feedback; ✕ = never settles."""
    plt = pyplot()
    fbs = list(grids)
    fig, axes = plt.subplots(1, len(fbs), figsize=(4.8 * len(fbs), 4.6), squeeze=False,
                             layout="constrained")
    settled = [s.settling_time_s for g in grids.values() for s in g.values()
               if s.settling_time_s is not None]
    vmax = max(50.0, math.ceil(max(settled, default=0.0) / 50.0) * 50.0)  # no cell beyond the bar
    for ax, fb in zip(axes[0], fbs, strict=True):
        grid = grids[fb]
        kps = sorted({k for k, _ in grid})
        kis = sorted({i for _, i in grid})
        z = np.full((len(kps), len(kis)), np.nan)
        for (kp, ki), s in grid.items():
            if s.settling_time_s is not None:
                z[kps.index(kp), kis.index(ki)] = s.settling_time_s
        im = ax.imshow(z, origin="lower", cmap="viridis_r", aspect="auto", vmin=0, vmax=vmax)
        for i in range(len(kps)):
            for j in range(len(kis)):
                v = z[i, j]
                ax.text(j, i, "✕" if np.isnan(v) else f"{v:.0f}", ha="center", va="center",
                        fontsize=8, color="w" if np.isnan(v) or v > vmax / 2 else "k")
        best = best_gains(grid)
        ax.set_title(f"{fb}: best {format_value(best.settling_time_s, '.0f')} s\n"
                     f"at kp={best.kp:g}, ki={best.ki:g}", fontsize=9)
        ax.set_xticks(range(len(kis)), [f"{k:g}" for k in kis], rotation=45, ha="right")
        ax.set_yticks(range(len(kps)), [f"{k:g}" for k in kps])
        ax.set_xlabel("ki [%/(mmH2O·s)]")
        ax.set_ylabel("kp [%/mmH2O]")
    fig.colorbar(im, ax=axes[0].tolist(), label="median settling time [s]")
    return save(fig, path)


# -- report and files ---------------------------------------------------------------------------
def format_summaries(summaries: Sequence[Summary]) -> str:
    """The printed comparison: one row per feedback, medians over seeds."""
    head = ["feedback", "settle s", "spread s", "settled", "overshoot %", "IAE mmH2O·s",
            "travel %", "trips", "fuel L"]
    return format_table([[s.feedback, format_value(s.settling_time_s),
                          format_value(s.settling_spread_s), f"{s.settled}/{s.seeds}",
                          format_value(s.overshoot_pct), format_value(s.iae, ".0f"),
                          format_value(s.valve_travel_pct, ".0f"), f"{s.trips}/{s.seeds}",
                          format_value(s.fuel_l, ".2f")] for s in summaries], head)


def format_report(summaries: Sequence[Summary], seeds: int) -> str:
    """The set-up, the table and, with both, the Kalman against the moving average."""
    lines = [f"closed loop to {SETPOINT:g} mmH2O from 100 % open at rated; kp={summaries[0].kp:g}"
             f" %/mmH2O, ki={summaries[0].ki:g} %/(mmH2O·s); medians over {seeds} seeds",
             format_summaries(summaries)]
    by = {s.feedback: s for s in summaries}
    if {"kalman", "maf"} <= set(by) and by["kalman"].settling_time_s and \
            by["maf"].settling_time_s:
        ratio = by["kalman"].settling_time_s / by["maf"].settling_time_s
        saved = (by["maf"].fuel_l or 0.0) - (by["kalman"].fuel_l or 0.0)
        lines.append(f"Kalman/MA settling ratio {ratio:.2f}; fuel saved by Kalman feedback "
                     f"{saved:.2f} L per set-up (seed 004: 110/150 s = 0.73)")
    return "\n".join(lines)


def format_best_gains(grids: dict[str, dict[tuple[float, float], Summary]]) -> str:
    lines = ["gain map: best gains per filter (median settling over seeds)"]
    for fb, grid in grids.items():
        b = best_gains(grid)
        lines.append(f"  {fb:>9}: kp={b.kp:g} ki={b.ki:g} settling "
                     f"{format_value(b.settling_time_s)} s (spread "
                     f"{format_value(b.settling_spread_s)} s, travel {b.valve_travel_pct:.0f} %)")
    return "\n".join(lines)


def write_comparison(out: Path, summaries: Sequence[Summary], cases: Sequence[CaseResult]
                     ) -> list[str]:
    """The cases and the summaries as CSV, and Figure 10; the names written."""
    write_csv(out / "closed_loop_cases.csv", [c.row() for c in cases])
    write_csv(out / "closed_loop.csv", [s.as_json() for s in summaries])
    plot_figure10(out / "closed_loop.png", cases, summaries)
    return ["closed_loop.csv", "closed_loop_cases.csv", "closed_loop.png"]


def write_gain_map(out: Path, grids: dict[str, dict[tuple[float, float], Summary]]) -> list[str]:
    """The gain map as CSV and as heat maps; the names written."""
    write_csv(out / "gain_map.csv", [s.as_json() for g in grids.values() for s in g.values()])
    plot_gain_map(out / "gain_map.png", grids)
    return ["gain_map.csv", "gain_map.png"]


# -- command line -------------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``testcell experiment closed-loop`` options to ``parser``."""
    parser.add_argument("--feedback", default=",".join(FEEDBACKS),
                        help="comma-separated feedbacks from raw,maf,kalman,adaptive "
                             "(default: all four)")
    parser.add_argument("--out", default="experiment-closed-loop", metavar="DIR",
                        help="folder for the CSV files and PNGs (default ./experiment-closed-loop)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object per feedback on stdout (table on stderr)")
    parser.add_argument("--seeds", type=int, default=5, metavar="N",
                        help="noise seeds per case, 0..N-1 (default 5)")
    parser.add_argument("--kp", type=float, default=None,
                        help=f"proportional gain, %%/mmH2O (default {DEFAULT_KP})")
    parser.add_argument("--ki", type=float, default=None,
                        help=f"integral gain, %%/(mmH2O·s) (default {DEFAULT_KI})")
    parser.add_argument("--duration", type=float, default=300.0, metavar="S",
                        help="closed-loop seconds per case (default 300)")
    parser.add_argument("--gain-map", action="store_true",
                        help="also sweep kp x ki for each filter and plot the settling time")
    parser.add_argument("--grid-kp", default=",".join(f"{k:g}" for k in GRID_KP),
                        metavar="LIST", help="kp values of the gain map")
    parser.add_argument("--grid-ki", default=",".join(f"{k:g}" for k in GRID_KI),
                        metavar="LIST", help="ki values of the gain map")
    parser.add_argument("--jobs", type=int, default=None, metavar="N",
                        help="worker processes (default: CPU count)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _float_list(option: str, text: str) -> list[float]:
    out = []
    for part in str(text).split(","):
        part = part.strip()
        try:
            v = float(part)
        except ValueError:
            raise ConfigError(f"{option} {text!r}: {part!r} is not a number") from None
        if not math.isfinite(v) or v < 0:
            raise ConfigError(f"{option} {text!r}: gains must be finite and >= 0, got {part}")
        out.append(v)
    return out


def check_arguments(args: argparse.Namespace) -> dict[str, Any]:
    """Validate ``testcell experiment`` options; :class:`ConfigError` names the option."""
    feedbacks = [f.strip() for f in str(args.feedback).split(",") if f.strip()]
    if not feedbacks:
        raise ConfigError("--feedback names no feedback; choose from " + ",".join(FEEDBACKS))
    for fb in feedbacks:
        if fb not in FEEDBACKS:
            raise ConfigError(f"--feedback {fb!r} is not a feedback; choose from "
                              f"{','.join(FEEDBACKS)}")
    if len(set(feedbacks)) != len(feedbacks):
        raise ConfigError(f"--feedback {args.feedback!r} names a feedback twice")
    seeds = args.seeds
    if isinstance(seeds, bool) or not isinstance(seeds, int) or seeds < 1:
        raise ConfigError(f"--seeds must be a whole number >= 1, got {seeds!r}")
    for opt in ("kp", "ki"):
        v = getattr(args, opt, None)
        if v is not None and (not math.isfinite(v) or v < 0):
            raise ConfigError(f"--{opt} must be a finite number >= 0, got {v}")
    duration = getattr(args, "duration", 300.0)
    if not math.isfinite(duration) or duration < HOLD_S:
        raise ConfigError(f"--duration must be at least {HOLD_S:g} s, got {duration}")
    jobs = getattr(args, "jobs", None)
    if jobs is not None and jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {jobs}")
    return {
        "feedbacks": feedbacks, "seeds": seeds, "duration": duration,
        "kps": _float_list("--grid-kp", getattr(args, "grid_kp", "0.005")),
        "kis": _float_list("--grid-ki", getattr(args, "grid_ki", "0.013")),
        "workers": jobs or os.cpu_count() or 1,
    }


def main(args: argparse.Namespace) -> int:
    """Run ``testcell experiment closed-loop``; return the exit code (ConfigError on bad
    options, raised before any work)."""
    opts = check_arguments(args)
    out = output_folder(args.out)
    progress = not getattr(args, "quiet", False)
    report = sys.stderr if args.json else sys.stdout
    summaries, cases = compare(opts["feedbacks"], opts["seeds"], args.kp, args.ki,
                               opts["duration"], opts["workers"], progress)
    print(format_report(summaries, opts["seeds"]), file=report)
    files = write_comparison(out, summaries, cases)
    if args.gain_map:
        filters = [f for f in opts["feedbacks"] if f != "raw"] or ["maf", "kalman"]
        grids = gain_map(filters, opts["kps"], opts["kis"], opts["seeds"], opts["duration"],
                         opts["workers"], progress)
        files += write_gain_map(out, grids)
        print(format_best_gains(grids), file=report)
    print(f"wrote {', '.join(files)} to {out}", file=sys.stderr)
    if args.json:
        for s in summaries:
            print(json.dumps(s.as_json()))
    return 0


CLOSED_LOOP = registry.Experiment(
    name="closed-loop",
    help="PI back-pressure loop to 680 mmH2O with raw, moving-average, Kalman and adaptive "
         "feedback",
    add_arguments=add_arguments,
    run=main,
    seed="seed 004, Figure 10",
    description=__doc__.split("\n\n")[0],
)
