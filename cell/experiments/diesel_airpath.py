"""Seed 002 on the cell: ``testcell experiment bias``.

1. The simulation study of §6.1 (:func:`simulation_study`): a third-order linear system
   with true :math:`A_q = [[1,-2],[2,1],[0,0]]`, two slowly varying biases and an extra
   sensor on :math:`x_2`; prints :math:`S_r`, :math:`\\hat A_q` and the largest principal
   angle between their spans, and draws Figures 1-2.
2. The diesel on ``etc`` (:func:`diesel_study`): a design run with the ``P_EM`` sensor
   (the design tool of :mod:`cell.design.diesel_airpath`, ``testcell design bias``), then
   an evaluation run without it (``--no-pem-sensor``), both observers side by side, errors
   scored against simulator truth (the paper had to use non-causal low-pass filtered
   measurements); Figures 3-4 and a table like Table 1.

Each study is its steps: record (the system, or the engine and the runtime in lockstep),
estimate (the design of :math:`\\hat A_q`), score (against the truth), figures.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cell.analysis.figures import format_table, output_folder, pyplot, save
from cell.bus import dbc as dbc_mod
from cell.core import registry
from cell.core.errors import ConfigError
from cell.design.diesel_airpath import (
    UNIT,
    Record,
    Recorder,
    design_from_frames,
    format_matrix,
    read_frames,
    seconds_bar,
    write_design,
)
from cell.estimators import augmentation as bias
from cell.estimators.core import KalmanCore, steady_state_gain
from cell.estimators.diesel_airpath import augmented_observer, default_observer
from cell.plant.diesel_airpath import SIGNAL, STATES
from cell.plant.large_diesel import large_diesel
from cell.runtime.scheduler import Rates, Runtime
from cell.sim.lockstep import Lockstep
from cell.sim.simulator import Simulator

#: Scoring starts after the observers' initial transient, s.
SCORE_FROM = 20.0


# -- §6.1: the simulation study --------------------------------------------------------------
#: The §6.1 system: continuous A (stable, invertible), B, and the true augmentation.
STUDY_A = np.array([[-3.0, 1.0, 0.5], [2.0, -6.0, 1.0], [0.5, 1.5, -1.0]])
STUDY_B = np.array([[3.0, 0.0], [0.0, 4.0], [1.0, 1.0]])
STUDY_AQ = np.array([[1.0, -2.0], [2.0, 1.0], [0.0, 0.0]])
STUDY_LEVELS = ((40, 30), (60, 20), (30, 60), (70, 50), (50, 40), (80, 70), (35, 45), (65, 35))
#: The study's process and measurement noise (standard deviations).
STUDY_W, STUDY_V = 0.02, 0.5


@dataclass
class StudyRun:
    """The study system's run: times, inputs, true states, measurements, and its
    discrete matrices (F, B) and sensors (C)."""

    t: np.ndarray
    u: np.ndarray
    x: np.ndarray
    y: np.ndarray
    F: np.ndarray
    B: np.ndarray
    C: np.ndarray


def study_record(seed: int, duration: float, ts: float, sensors: Sequence[int]) -> StudyRun:
    """The true system: the Euler-discretised eq. 4 with :data:`STUDY_AQ` and two slowly
    varying biases (:math:`A_q q` 0-10 % of the states), white process and measurement noise,
    and piecewise-constant inputs (eight holds: the stationary operating points)."""
    rng = np.random.default_rng([seed, 61])
    n_steps = int(round(duration / ts))
    t = np.arange(n_steps) * ts
    F = np.eye(3) + ts * STUDY_A
    Bd = ts * STUDY_B
    hold = duration / len(STUDY_LEVELS)
    u = np.array([STUDY_LEVELS[min(int(tt // hold), len(STUDY_LEVELS) - 1)] for tt in t], float)
    q = np.column_stack([4.0 + 3.0 * np.sin(2 * np.pi * t / 400.0),
                         2.0 + 2.0 * np.sin(2 * np.pi * t / 250.0 + 1.0)])
    C = np.eye(3)[list(sensors)]
    x = np.linalg.solve(-STUDY_A, STUDY_B @ u[0])
    X, Y = np.zeros((n_steps, 3)), np.zeros((n_steps, len(sensors)))
    for k in range(n_steps):
        X[k] = x
        Y[k] = C @ x + rng.normal(0.0, STUDY_V, len(sensors))
        x = F @ x + (np.eye(3) - F) @ STUDY_AQ @ q[k] + Bd @ u[k] + rng.normal(0.0, STUDY_W, 3)
    return StudyRun(t, u, X, Y, F, Bd, C)


def kalman_run(run: StudyRun, F, B, C, Q, R, x0) -> np.ndarray:
    """A Kalman filter on (F, B, C) over the run's measurements: its state at every step."""
    kf = KalmanCore(x0, np.eye(len(x0)), Q, R, F=F, B=B, H=C)
    out = np.zeros((len(run.t), len(x0)))
    for k in range(len(run.t)):
        if k:
            kf.predict(run.u[k - 1])
        kf.update(run.y[k])
        out[k] = kf.x
    return out


def simulation_study(seed: int = 0, duration: float = 600.0, ts: float = 0.01,
                     sensors: Sequence[int] = (0, 1, 2)) -> dict[str, Any]:
    """Seed 002, §6.1, on a linear third-order system; returns numbers and traces.

    The default Kalman filter (the model without bias) runs on ``sensors`` (default all
    three: ``y_1 = x_1``, ``y_2 = x_3`` and the extra sensor on ``x_2``); Approach 2 gives
    :math:`\\hat A_q`; the augmented filter (eq. 4 with :math:`\\hat A_q`) is compared.
    """
    run = study_record(seed, duration, ts, sensors)
    F, Bd, C = run.F, run.B, run.C
    Qf, Rf = np.eye(3) * 1e-3, np.eye(len(sensors)) * STUDY_V ** 2
    x0 = np.linalg.pinv(C) @ run.y[0]
    # estimate: the default filter's stationary residuals (eq. 8), Approach 2
    Xd = kalman_run(run, F, Bd, C, Qf, Rf, x0)
    r = run.y - Xd @ C.T
    segments = bias.stationary_segments(run.t, run.u, [1e-9, 1e-9], window=1.0, settle=20.0,
                                        min_length=10.0)
    mask = bias.segment_mask(run.t, segments)
    K, _ = steady_state_gain(F, C, Qf, Rf)
    design = bias.approach2(r[mask], bias.stationary_map(F, K, C), segments=segments,
                            max_dim=len(sensors))
    bias.pbh_check(C, design.Aq)
    Fa, Ba, Ca = bias.augmented_linear(F, Bd, C, design.Aq)
    Qa = np.diag([*np.diag(Qf), *[1e-4] * design.n_q])
    Xa = kalman_run(run, Fa, Ba, Ca, Qa, Rf, np.concatenate([x0, np.zeros(design.n_q)]))[:, :3]
    # score against the true states
    score = run.t >= 20.0
    e_def, e_aug = (Xd - run.x)[score], (Xa - run.x)[score]
    return {
        "S_r": design.singular_values.tolist(),
        "n_q": design.n_q,
        "Aq_hat": design.Aq.tolist(),
        "Aq_true": STUDY_AQ.tolist(),
        "largest_angle_deg": bias.largest_angle_deg(design.Aq, STUDY_AQ),
        "segments": [list(s) for s in segments],
        "mean_abs_error_default": np.abs(e_def).mean(axis=0).tolist(),
        "mean_abs_error_augmented": np.abs(e_aug).mean(axis=0).tolist(),
        "_traces": {"t": run.t, "x": run.x, "default": Xd, "augmented": Xa},
    }


# -- the diesel: record -----------------------------------------------------------------------
EVAL_NAMES = (*(f"{SIGNAL[s]}{k}" for k in ("_TRUE", "_EST_DEFAULT", "_EST") for s in STATES),
              "DSL_P_IM", "N_T",
              "ENGINE_SPEED", "FUEL_RATE", "EXH_BP_L_TRUE")


def evaluate(Aq: np.ndarray, duration: float, seed: int = 1, duty: str = "etc",
             valve_steps: Sequence[tuple[float, float]] = (), progress: bool = False,
             initial_valve: float | None = None) -> Record:
    """Run the engine without the P_EM sensor and both observers in lockstep; record.

    ``valve_steps``: ``(t, opening %)`` demands sent to both back-pressure valves.
    """
    db = dbc_mod.load()
    plant = large_diesel(duty, seed, initial_valve=initial_valve, pem_sensor=False)
    sim = Simulator(plant, db)
    obs = [default_observer(), augmented_observer(Aq)]
    rt = Runtime(db, obs, Rates())
    nq = np.asarray(Aq).reshape(3, -1).shape[1]
    rec = Recorder(rt, [*EVAL_NAMES, *[f"Q_BIAS_{i + 1}" for i in range(nq)]])
    steps = sorted(valve_steps)
    per_s = round(1.0 / sim.dt)
    with seconds_bar(duration, f"bias {duty}", progress) as bar:
        for k, _ in Lockstep(sim, rt, stride=2, on_tick=rec).steps(round(duration / sim.dt)):
            while steps and sim.t >= steps[0][0] - 1e-9:
                _, v = steps.pop(0)
                plant.set_input("VALVE_DEMAND_L", v)
                plant.set_input("VALVE_DEMAND_R", v)
            if (k + 1) % per_s == 0:
                bar.update(1)
    return rec.record()


# -- the diesel: score ------------------------------------------------------------------------
def error_table(r: Record, start: float = SCORE_FROM) -> dict[str, dict[str, float]]:
    """Table 1 of seed 002: max-abs and mean error per state, default and augmented,
    against simulator truth (N_T in rpm)."""
    sel = r.t >= start
    out = {}
    for s in ("P_IM", "P_EM", "N_T"):
        truth = r[f"{SIGNAL[s]}_TRUE"][sel]
        row = {}
        for label, ch in (("default", f"{SIGNAL[s]}_EST_DEFAULT"), ("augmented", f"{SIGNAL[s]}_EST")):
            e = r[ch][sel] * UNIT[s] - truth
            e = e[np.isfinite(e)]
            row[f"max_abs_{label}"] = float(np.max(np.abs(e)))
            row[f"mean_{label}"] = float(np.mean(e))
        out[s] = row
    return out


def mean_error_reduction(table: dict[str, dict[str, float]], state: str = "P_EM") -> float:
    """1 - |mean error augmented| / |mean error default| (seed 002, §6.2: about 0.5)."""
    row = table[state]
    return 1.0 - abs(row["mean_augmented"]) / abs(row["mean_default"])


def diesel_study(design_seconds: float = 1800.0, eval_seconds: float = 1800.0,
                 design_seed: int = 0, eval_seed: int = 1, progress: bool = True,
                 log_dir: Path | None = None) -> dict[str, Any]:
    """Design on an ``etc`` run with the P_EM sensor, evaluate on one without it."""
    from cell.sim import write_log

    with tempfile.TemporaryDirectory() as tmp:
        log = Path(log_dir or tmp) / "etc_design.log"
        write_log(log, "etc", seed=design_seed, duration=design_seconds, progress=progress)
        design = design_from_frames(read_frames(log), source=str(log))
    rec = evaluate(np.array(design["Aq"]), eval_seconds, eval_seed, progress=progress)
    table = error_table(rec)
    return {"design": design, "table": table,
            "mean_error_reduction": mean_error_reduction(table), "_record": rec}


# -- figures ----------------------------------------------------------------------------------
def _compare(path: Path, t: np.ndarray, panels, title: str, figsize: tuple[float, float],
             truth_label: str = "truth") -> Path:
    """One panel per ``(label, truth, default, augmented)``: the truth and both observers'
    estimates; with ``truth_label=None``, both estimates' errors."""
    plt = pyplot()
    fig, axes = plt.subplots(len(panels), 1, figsize=figsize, sharex=True)
    for ax, (label, truth, default, augmented) in zip(axes, panels):
        if truth_label is None:
            ax.plot(t, default - truth, "C0", lw=0.8, label="default")
            ax.plot(t, augmented - truth, "C3", lw=0.8, label="augmented")
            ax.axhline(0.0, color="k", lw=0.5)
            label = "error " + label
        else:
            ax.plot(t, truth, "k", lw=1.0, label=truth_label)
            ax.plot(t, default, "C0", lw=0.8, label="default observer")
            ax.plot(t, augmented, "C3", lw=0.8, label="augmented observer")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    axes[0].set_title(title)
    axes[-1].set_xlabel("time [s]")
    return save(fig, path)


def plot_study(out: Path, study: dict[str, Any]) -> list[Path]:
    """Seed 002, Figures 1-2: states and estimates of x_1, x_2; estimation errors."""
    tr = study["_traces"]
    sl = slice(None, None, max(1, len(tr["t"]) // 4000))
    panels = [(f"x_{i + 1}", tr["x"][sl, i], tr["default"][sl, i], tr["augmented"][sl, i])
              for i in range(3)]
    return [_compare(out / "fig1_study_states.png", tr["t"][sl], panels[:2],
                     "Seed 002 Fig. 1: true and estimated states (simulation study)", (8, 5.5),
                     truth_label="true"),
            _compare(out / "fig2_study_errors.png", tr["t"][sl], panels,
                     "Seed 002 Fig. 2: estimation errors (simulation study)", (8, 7),
                     truth_label=None)]


def plot_diesel(out: Path, rec: Record) -> list[Path]:
    """Seed 002, Figures 3-4 on the cell: estimates and errors against simulator truth."""
    labels = {"P_IM": "p_im [kPa]", "P_EM": "p_em [kPa] (not measured)", "N_T": "n_t [rpm]"}
    panels = [(label, rec[f"{SIGNAL[s]}_TRUE"], rec[f"{SIGNAL[s]}_EST_DEFAULT"] * UNIT[s],
               rec[f"{SIGNAL[s]}_EST"] * UNIT[s]) for s, label in labels.items()]
    return [_compare(out / "fig3_diesel_states.png", rec.t, panels,
                     "Seed 002 Fig. 3: air-path state estimates on the etc cycle (no P_EM sensor)",
                     (9, 7.5)),
            _compare(out / "fig4_diesel_errors.png", rec.t, panels,
                     "Seed 002 Fig. 4: estimation errors against simulator truth", (9, 7.5),
                     truth_label=None)]


# -- report -----------------------------------------------------------------------------------
def format_error_table(table: dict[str, dict[str, float]]) -> str:
    """Seed 002, Table 1's layout."""
    units = {"P_IM": "kPa", "P_EM": "kPa", "N_T": "rpm"}
    rows = [[f"{s} [{units[s]}]", *(f"{row[k]:.2f}" for k in
                                    ("max_abs_default", "max_abs_augmented", "mean_default",
                                     "mean_augmented"))] for s, row in table.items()]
    return (f"{'':<12}{'max abs error':>24}{'mean error':>24}\n"
            + format_table(rows, ["", "default", "augmented", "default", "augmented"],
                           widths=(12,) * 5, align="<>>>>", sep=""))


def results(study: dict[str, Any], diesel: dict[str, Any], seconds: float, figs: list[Path]
            ) -> dict[str, Any]:
    """The ``--json`` object."""
    table = diesel["table"]
    return {"study": {k: v for k, v in study.items() if not k.startswith("_")},
            "diesel": {"design": {k: diesel["design"][k] for k in
                                  ("Aq", "singular_values", "n_q", "segments", "samples")},
                       "table": table,
                       "mean_error_reduction": diesel["mean_error_reduction"],
                       "max_abs_change": table["P_EM"]["max_abs_augmented"]
                       / table["P_EM"]["max_abs_default"] - 1.0,
                       "seconds": seconds},
            "mean_error_reduction": diesel["mean_error_reduction"],
            "figures": [str(p) for p in figs]}


def format_report(study: dict[str, Any], diesel: dict[str, Any], seconds: float,
                  figs: list[Path]) -> str:
    """The printed numbers of both studies."""
    d = diesel["design"]
    return "\n".join([
        "Seed 002, §6.1 simulation study",
        "S_r = diag(" + ", ".join(f"{s:.3g}" for s in study["S_r"]) + f"), dim q = {study['n_q']}",
        "A_q estimate:\n" + format_matrix(study["Aq_hat"]),
        f"largest principal angle between span(A_q estimate) and span(A_q): "
        f"{study['largest_angle_deg']:.2f} deg",
        f"\nSeed 002, §6.2 on the cell: large-diesel, etc, {seconds:g} s",
        f"stationary segments: {', '.join(f'{a:.0f}-{b:.0f} s' for a, b in d['segments'])}",
        "S_r = diag(" + ", ".join(f"{s:.3g}" for s in d["singular_values"]) + f"), dim q = {d['n_q']}",
        "A_q estimate (P_IM, P_EM, N_T):\n" + format_matrix(d["Aq"]),
        "\n" + format_error_table(diesel["table"]),
        f"\nP_EM mean error reduction: {100 * diesel['mean_error_reduction']:.0f} %",
        "figures: " + ", ".join(str(p) for p in figs),
    ])


# -- command line -------------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="bias_results", metavar="DIR",
                        help="folder for the figures and the design file (default bias_results)")
    parser.add_argument("--json", action="store_true", help="print the numbers as JSON")
    parser.add_argument("--seconds", type=float, default=1800.0, metavar="S",
                        help="length of the design and evaluation etc runs (default 1800 s)")
    parser.add_argument("--seed", type=int, default=0, help="noise seed of the design run "
                        "(the evaluation uses seed + 1)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def main(args: argparse.Namespace) -> int:
    if not args.seconds >= 100.0:
        raise ConfigError(f"--seconds must be >= 100 (the etc cycle's first stationary holds "
                          f"end near 90 s), got {args.seconds}")
    out = output_folder(args.out)
    study = simulation_study(args.seed)
    figs = plot_study(out, study)
    diesel = diesel_study(args.seconds, args.seconds, args.seed, args.seed + 1,
                          progress=not args.no_progress)
    write_design(out / "bias_design.json", diesel["design"])
    figs += plot_diesel(out, diesel["_record"])
    if args.json:
        print(json.dumps(results(study, diesel, args.seconds, figs), indent=1))
    else:
        print(format_report(study, diesel, args.seconds, figs))
    return 0


BIAS = registry.Experiment(
    "bias", "bias compensation: the §6.1 study and the diesel's augmented observer on etc",
    add_arguments, main, seed="seed 002, Figs. 1-4, Table 1")
