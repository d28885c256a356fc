r"""``testcell design bias LOG``: the bias augmentation :math:`\hat A_q` of the large diesel's
air-path observer from a recorded log (seed 002, §4.2, Approach 2 by default).

``testcell design bias LOG [--states P_IM,P_EM,N_T] [--approach 2] [--out FILE]``:

1. Replay the log through the *design observer* (:func:`design_observer`): Approach 2 the
   *default observer* of :mod:`cell.estimators.diesel_airpath`, Approach 3 the maximally
   augmented one, Approach 1 none (it uses the measurements themselves), measuring
   ``--states`` (state names; by default every air-path state with a sensor in the log: with
   ``DSL_P_EM`` on the bus, all three, as seed 002, §6.2 does).
2. Find the stationary segments automatically from engine speed and fuel
   (:func:`cell.estimators.augmentation.stationary_segments`).
3. Take the SVD of the stationary residuals (or bias states), choose dim q by
   :data:`~cell.estimators.augmentation.DIM_RATIO` (at most the run-time sensors, P_IM and
   N_T) and estimate :math:`\hat A_q` by eq. 9.
4. The augmentation must pass the PBH test (Theorem 2) with the *run-time* sensors; then the
   file is written (JSON: ``Aq``, ``singular_values``, the segments...), for the runtime to
   load (setting ``bias_design``).

A log without stationary segments, or without the air path's signals, is refused and
nothing is written.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cell.bus import dbc as dbc_mod
from cell.core import registry
from cell.core.errors import ConfigError, LogFormatError
from cell.core.files import write_text_atomic
from cell.estimators import augmentation as bias
from cell.estimators.contract import DESIGN_FORMAT
from cell.estimators.diesel_airpath import (
    AUGMENTED_NAME,
    OUTPUTS,
    RUNTIME_SENSORS,
    augmented_observer,
    default_model,
    default_observer,
    runtime_C,
)
from cell.plant.diesel_airpath import INPUTS, SIGNAL, STATES
from cell.runtime.scheduler import Rates, Runtime
from cell.sim.lockstep import feed

#: Stationarity of the operating point: range over the window of engine speed (rpm) and
#: fuel (L/h), the window and the settling time dropped from each segment, s.
SPEED_TOL, FUEL_TOL, WINDOW, SETTLE, MIN_LENGTH = 10.0, 4.0, 4.0, 14.0, 8.0
#: Scale of each measurement against its model state (N_T in rpm, the state in krpm).
UNIT = {"P_IM": 1.0, "P_EM": 1.0, "N_T": 1000.0}


# -- records of a run -------------------------------------------------------------------------
@dataclass
class Record:
    """Per-tick values of a run (MED ticks): time, and named columns."""

    t: np.ndarray
    cols: dict[str, np.ndarray]

    def __getitem__(self, name: str) -> np.ndarray:
        return self.cols[name]

    def stack(self, names: Sequence[str]) -> np.ndarray:
        """The columns ``names`` side by side, one row per tick."""
        return np.column_stack([self[n] for n in names]) if names else np.zeros((len(self.t), 0))


class Recorder:
    """A tick listener keeping the runtime's channels ``names`` (NaN unless ``ok``) and,
    with ``extra``, what it returns at every tick."""

    def __init__(self, rt: Runtime, names: Sequence[str], extra: Callable[[], dict] | None = None
                 ) -> None:
        self.rt, self.names, self.extra = rt, list(names), extra
        self.rows: list[list[float]] = []
        self.t: list[float] = []
        self.more: list[dict] = []

    def __call__(self, t: float) -> None:
        ch = self.rt.channels
        row = []
        for n in self.names:
            c = ch.get(n)
            v = c.value if c is not None and c.status == "ok" else None
            row.append(np.nan if v is None else float(v))
        self.t.append(t)
        self.rows.append(row)
        if self.extra is not None:
            self.more.append(self.extra())

    def record(self) -> Record:
        a = np.array(self.rows, dtype=float).reshape(len(self.t), len(self.names))
        return Record(np.array(self.t), {n: a[:, i] for i, n in enumerate(self.names)})


def seconds_bar(total: float, desc: str, progress: bool):
    """A tqdm bar over ``total`` seconds of bus time."""
    from tqdm import tqdm

    return tqdm(total=round(total), unit="s", desc=desc, disable=not progress)


# -- 1. the design observer over the log ------------------------------------------------------
def present_signals(db, frames) -> set[str]:
    """Signals of the messages that occur in ``frames``."""
    out: set[str] = set()
    ids = {(m.arbitration_id, bool(m.is_extended_id)) for m in frames}
    for m in db.messages:
        if (m.frame_id, m.is_extended_frame) in ids:
            out.update(s.name for s in m.signals)
    return out


def check_log(present: set[str], states: Sequence[str] | None, approach: int, source: str
              ) -> list[str]:
    """The states the design measures (default: those with a sensor in the log); refuses a
    log without the air path's inputs, states without sensors and a bad approach."""
    missing = [s for s in INPUTS if s not in present]
    if missing:
        raise ConfigError(f"{source}: no values of {', '.join(missing)}: the design needs the "
                          "large-diesel air path's inputs (a log of `testcell sim --engine "
                          "large-diesel`)")
    if states is None:
        states = [s for s in OUTPUTS if SIGNAL[s] in present]
    states = list(states)
    bad = [s for s in states if s not in OUTPUTS]
    if bad:
        raise ConfigError(f"--states: {', '.join(bad)} is not an air-path state; choose from "
                          f"{', '.join(OUTPUTS)}")
    absent = [SIGNAL[s] for s in states if SIGNAL[s] not in present]
    if absent or not states:
        raise ConfigError(f"{source}: no values of {', '.join(absent) or 'any air-path sensor'} "
                          f"(the sensors of --states {','.join(states) or '(none)'})")
    if approach not in (1, 2, 3):
        raise ConfigError(f"--approach must be 1, 2 or 3, got {approach}")
    if approach == 1 and len(states) < 3:
        raise ConfigError("--approach 1 needs every state measured (C of full column rank): "
                          "use a log with P_EM and --states P_IM,P_EM,N_T")
    return states


def measured(states: Sequence[str]) -> np.ndarray:
    """Rows of C for the measured ``states`` (model units)."""
    return np.eye(3)[[OUTPUTS.index(s) for s in states]]


def design_observer(approach: int, states: Sequence[str]):
    """The observer replayed over the log: the default one (Approach 2), the maximally
    augmented one (Approach 3), or none (Approach 1 uses the measurements, §4.1)."""
    if approach == 3:
        return augmented_observer(bias.max_augmentation(measured(states)), "bias-design",
                                  sensors=states, channels={})
    if approach == 2:
        return default_observer("bias-design", sensors=states, channels={}, rate="FAS")
    return None


@dataclass
class Replay:
    """The design observer over a log: per MED tick, its inputs, the measurements of
    ``states``, the observer's states (``x_names``) and its gain."""

    record: Record
    states: list[str]
    x_names: list[str]
    gains: list[np.ndarray]

    @property
    def names(self) -> list[str]:
        return [*INPUTS, *(SIGNAL[s] for s in self.states), *self.x_names]


def replay(db, frames: list, obs, states: list[str], source: str, progress: bool) -> Replay:
    """Feed ``frames`` to a runtime running ``obs``; record every MED tick."""
    rt = Runtime(db, [obs] if obs is not None else [], Rates())
    x_names = list(obs.outputs[:len(obs.model.states)]) if obs is not None else []
    names = [*INPUTS, *(SIGNAL[s] for s in states), *x_names]
    rec = Recorder(rt, names, extra=(lambda: {"K": obs.core.K.copy()}) if obs is not None else None)
    span = (frames[-1].timestamp - frames[0].timestamp) if frames else 0.0
    with seconds_bar(span, "design bias", progress) as bar:
        def on_tick(t: float) -> None:
            rec(t)
            if t - frames[0].timestamp >= bar.n + 1.0:
                bar.update(1)

        fed = feed(rt, frames, on_tick)
    if fed.error is not None:
        raise ConfigError(f"{source}: {fed.error}")
    r = rec.record()
    if len(r.t) < 10:
        raise ConfigError(f"{source}: too short ({len(r.t)} ticks) for a design")
    return Replay(r, list(states), x_names, [m["K"] for m in rec.more])


# -- 2. the stationary segments ---------------------------------------------------------------
@dataclass
class Stationary:
    """The stationary segments of a replay: ``mask`` marks their ticks with every value
    present, ``seg_of`` each tick's segment (-1: none)."""

    segments: list[tuple[float, float]]
    mask: np.ndarray
    seg_of: np.ndarray


def stationary(run: Replay, source: str) -> Stationary:
    """Runs of constant engine speed and fuel (:data:`SPEED_TOL`, :data:`FUEL_TOL`)."""
    r = run.record
    drive = np.column_stack([r["ENGINE_SPEED"], r["FUEL_RATE"]])
    ok = np.isfinite(drive).all(axis=1) & np.isfinite(r.stack(run.names)).all(axis=1)
    segments = bias.stationary_segments(r.t[ok], drive[ok], [SPEED_TOL, FUEL_TOL], WINDOW,
                                        SETTLE, MIN_LENGTH)
    if not segments:
        raise ConfigError(f"{source}: no stationary segment (engine speed within {SPEED_TOL:g} rpm "
                          f"and fuel within {FUEL_TOL:g} L/h for {SETTLE + MIN_LENGTH:g} s); the "
                          "design needs stationary operating points (e.g. --duty etc); nothing "
                          "written")
    mask = ok & bias.segment_mask(r.t, segments)
    seg_of = np.full(len(r.t), -1)
    for k, (a, b) in enumerate(segments):
        seg_of[(r.t >= a) & (r.t <= b)] = k
    return Stationary(segments, mask, seg_of)


# -- 3. the estimate of A_q (§4.1-4.3) --------------------------------------------------------
def segment_maps(run: Replay, st: Stationary) -> tuple[list[np.ndarray], list[int]]:
    """Eq. 9's map at each stationary operating point, and its weight (ticks): F of one
    filter step at the segment's mean state and input, K the filter's gain at its end."""
    model = default_model()
    C = measured(run.states)
    xs, us = run.record.stack(run.x_names), run.record.stack(INPUTS)
    dt = 1.0 / Rates().FAS
    scale = np.array([UNIT[s] for s in run.states])
    maps, weights = [], []
    for k in range(len(st.segments)):
        idx = np.flatnonzero(st.mask & (st.seg_of == k))
        if len(idx) == 0:
            continue
        x_m, u_m = xs[idx].mean(axis=0), us[idx].mean(axis=0)
        _, F = model.step(0.0, x_m[:3], u_m, dt, jacobian=True)
        K = run.gains[idx[-1]][:3]
        Cs = C * np.array([1.0, 1.0, 1000.0])[None, :]  # h's Jacobian (N_T in rpm)
        maps.append(bias.stationary_map(F, K, Cs) / scale[:, None])
        weights.append(len(idx))
    return maps, weights


def approach2(run: Replay, st: Stationary, n_q: int | None, max_dim: int) -> bias.BiasDesign:
    """§4.2: the default observer's stationary residuals through eq. 9's maps."""
    maps, weights = segment_maps(run, st)
    r, mask = run.record, st.mask
    scale = np.array([UNIT[s] for s in run.states])
    ys = r.stack([SIGNAL[s] for s in run.states])
    xs = r.stack(run.x_names)
    resid = ys[mask] / scale - (xs[mask][:, :3] @ measured(run.states).T)
    return bias.approach2(resid, maps, weights, n_q=n_q, max_dim=max_dim, segments=st.segments)


def approach1(run: Replay, st: Stationary, n_q: int | None, max_dim: int) -> bias.BiasDesign:
    """§4.1: every state measured; the model's one-step predictions against the next
    measurement."""
    model = default_model()
    r, mask = run.record, st.mask
    ys = r.stack([SIGNAL[s] for s in run.states])
    us = r.stack(INPUTS)
    scale = np.array([1.0, 1.0, 1000.0])
    idx = np.flatnonzero(mask)
    idx = idx[idx + 1 < len(r.t)]
    idx = idx[mask[idx + 1]]
    X1 = ys[idx + 1] / scale
    P, Fs = [], []
    for i in idx:
        xn, Fk = model.step(0.0, ys[i] / scale, us[i], r.t[i + 1] - r.t[i], jacobian=True)
        P.append(xn)
        Fs.append(Fk)
    return bias.approach1(X1, np.array(P), Fs, st.seg_of[idx], n_q=n_q, max_dim=max_dim,
                          segments=st.segments)


def approach3(run: Replay, st: Stationary, n_q: int | None, max_dim: int) -> bias.BiasDesign:
    """§4.3: the bias states of the maximally augmented observer."""
    qs = run.record.stack(run.x_names)[st.mask][:, 3:]
    return bias.approach3(qs, bias.max_augmentation(measured(run.states)), n_q=n_q,
                          max_dim=max_dim, segments=st.segments)


APPROACHES = {1: approach1, 2: approach2, 3: approach3}


# -- 4. fit for the run-time sensors ----------------------------------------------------------
def fit_runtime(design: bias.BiasDesign, runtime_sensors: Sequence[str], n_q: int | None,
                source: str) -> None:
    """Reduce dim q (unless given) to what the run-time sensors observe, and refuse an
    :math:`\\hat A_q` failing the PBH test with them."""
    C_rt = runtime_C(runtime_sensors)
    if n_q is None:
        keep = max(1, bias.observable_dim(C_rt, design.Aq))
        if keep < design.n_q:
            design.Aq, design.n_q = design.Aq[:, :keep], keep
    try:
        bias.pbh_check(C_rt, design.Aq, STATES, runtime_sensors)
    except bias.AugmentationError as exc:
        raise ConfigError(f"{source}: the estimated A_q cannot be used with the run-time sensors "
                          f"{', '.join(runtime_sensors)}: {exc}") from None


def design_from_frames(frames, states: Sequence[str] | None = None, approach: int = 2,
                       runtime_sensors: Sequence[str] = RUNTIME_SENSORS, source: str = "log",
                       n_q: int | None = None, progress: bool = False) -> dict[str, Any]:
    """Estimate :math:`\\hat A_q` from the frames of a large-diesel run (seed 002, §4).

    ``states``: the sensors the design observer uses (default: those present). Raises
    :class:`ConfigError` naming what is missing, or when there is no stationary segment.
    """
    db = dbc_mod.load()
    frames = list(frames)
    states = check_log(present_signals(db, frames), states, approach, source)
    run = replay(db, frames, design_observer(approach, states), states, source, progress)
    st = stationary(run, source)
    max_dim = len(runtime_sensors)
    design = APPROACHES[approach](run, st, n_q, max_dim)
    fit_runtime(design, runtime_sensors, n_q, source)
    out = {"format": DESIGN_FORMAT, "observer": AUGMENTED_NAME, **design.as_dict(STATES)}
    out.update({"design_sensors": states, "runtime_sensors": list(runtime_sensors),
                "source": str(source),
                "rule": f"n_q = number of singular values >= {bias.DIM_RATIO:g} x the largest, "
                        f"at most {max_dim} (the run-time sensors), and reduced until C·A_q "
                        f"(run-time C) has condition number <= {bias.MAX_COND:g}"})
    return out


# -- files --------------------------------------------------------------------------------------
def read_frames(log: Path) -> list:
    """Every frame of a CAN log; a malformed line is a :class:`ConfigError` naming it."""
    from cell.runtime.replay import read_log

    try:
        return list(read_log(log))
    except LogFormatError as exc:
        raise ConfigError(f"LOG {exc}") from None


def write_design(path: Path, design: dict[str, Any]) -> Path:
    """Write a design file atomically (nothing is left behind on failure)."""
    path = Path(path)
    write_text_atomic(path, json.dumps(design, indent=1))
    return path


def format_matrix(a) -> str:
    """A matrix, one bracketed row per line."""
    return "\n".join("  [" + "  ".join(f"{v:8.3f}" for v in row) + "]" for row in np.atleast_2d(a))


# -- command line -------------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="LOG", help="a large-diesel CAN log (candump .log, .asc, "
                        ".blf, .csv) with the air path's frames")
    parser.add_argument("--states", default=None, metavar="LIST",
                        help="sensors the design observer uses, comma-separated from P_IM,P_EM,N_T "
                             "(default: those in the log)")
    parser.add_argument("--approach", type=int, default=2, choices=(1, 2, 3),
                        help="seed 002's approach (§4.1-4.3; default 2)")
    parser.add_argument("--out", default="bias_design.json", metavar="FILE",
                        help="design file to write (default bias_design.json)")
    parser.add_argument("--dim", type=int, default=None, metavar="N",
                        help="dim q (default: from the singular values)")


def main(args: argparse.Namespace) -> int:
    states = None
    if args.states is not None:
        states = [s.strip().upper() for s in args.states.split(",") if s.strip()]
        if not states:
            raise ConfigError("--states: give one or more of P_IM,P_EM,N_T")
    if args.dim is not None and not 1 <= args.dim <= len(RUNTIME_SENSORS):
        raise ConfigError(f"--dim must be 1..{len(RUNTIME_SENSORS)} (the run-time sensors), "
                          f"got {args.dim}")
    log = Path(args.log)
    if not log.exists():
        raise ConfigError(f"LOG {log}: no such file")
    design = design_from_frames(read_frames(log), states, args.approach, source=str(log),
                                n_q=args.dim, progress=True)
    write_design(Path(args.out), design)
    print("S_r = diag(" + ", ".join(f"{s:.4g}" for s in design["singular_values"]) + ")")
    print(f"dim q = {design['n_q']} ({design['rule']})")
    print("A_q estimate (rows P_IM, P_EM, N_T):\n" + format_matrix(design["Aq"]))
    print("stationary segments: " + ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in design["segments"]))
    unseen = [s for s in OUTPUTS if s not in design["design_sensors"]]
    if unseen:
        print(f"note: no sensor of {', '.join(unseen)} in the design, so its row of A_q is zero "
              "(seed 002, §4.4): the augmentation cannot correct it")
    print(f"wrote {args.out}")
    return 0


BIAS_DESIGN = registry.Experiment(
    "bias", "estimate the bias augmentation A_q from a large-diesel log (seed 002, §4)",
    add_arguments, main, seed="seed 002, eq. 9")
