r"""``testcell design airpath LOG``: the air-path observer's gain table from stationary data.

Seed 003, section 3: linearise the default model at the operating points of an engine map,
take the measurement noise from the stationary variance of each measured signal with a
floor (§3.3.1), the state noise from the stationary model error (§3.3.2), and solve the
Riccati equation at every point (§3.4).

1. The log is read at the plant's rate (every frame of the measured channels). Stationary
   segments are runs of constant ``ENGINE_SPEED`` and ``SI_LOAD_DEMAND`` (the duty
   cycle's set points) of at least ``--min-hold`` s; the first ``--settle`` s of each are
   dropped.
2. For each segment: the mean input (THROTTLE, WASTEGATE, ENGINE_SPEED; λ = 1), the mean
   and variance of every measurement (:math:`R_i = \frac1T\int (y - \bar y)^2 dt`, floored
   at :data:`R_FLOOR`).
3. The default model's stationary point :math:`x_{stat}` at that input (simulated to rest,
   §3.1; the measured actuator positions replace the paper's throttle and wastegate
   controllers), and :math:`Q_i = (x_{meas} - x_{stat})^2` for the measured states, floored
   at :data:`Q_FLOOR` (the exhaust manifold pressure, which has no sensor, gets its floor).
   :math:`Q` is read as an intensity per second; the discrete design uses :math:`Q\Delta t`.
4. The Jacobian :math:`A_i` by central differences, and the gains by
   :func:`~cell.estimators.si_airpath.discrete_gain` at the table's ``--dt``.

A log that lacks what the design needs is refused with what is missing and nothing is
written.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from cell.core.errors import ConfigError
from cell.estimators.si_airpath import DEFAULT_FEEDBACK, MEASUREMENTS, GainTable, TablePoint
from cell.estimators.core import numerical_jacobian
from cell.plant.si_airpath import MODEL_PARAMS, SIAirPathParams, airpath_rhs, steady_state
from cell.core.registry import Experiment

#: Channels the design reads.
REQUIRED = ("ENGINE_SPEED", "SI_LOAD_DEMAND", "THROTTLE", "WASTEGATE", *MEASUREMENTS)
#: Floor of each measurement's noise variance, SI units² (§3.3.1: "a minimum value ... to
#: make sure that R_i is not close to zero").
R_FLOOR = {"P_IC": 150.0**2, "P_IM": 300.0**2, "T_IM": 0.1**2, "N_TC": (100.0 * math.pi / 30.0) ** 2}
#: Floor of each state's noise intensity, SI units² per second; ``dc_eta_vol`` is the random
#: walk of ΔC_ηvol (seed 003 §4.2 models it as a "slowly varying constant").
Q_FLOOR = (300.0**2, 300.0**2, 0.5**2, 3000.0**2, 200.0**2, 0.02**2)


@dataclass
class Segment:
    """A stationary stretch of the log."""

    speed: float
    load: float
    t0: float
    t1: float
    mean: dict[str, float]
    var: dict[str, float]


def read_channels(path: str | Path, names: tuple[str, ...] = REQUIRED, progress: bool = True,
                  db=None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every value of ``names`` in a CAN log, as (times, values) per channel."""
    from cell.bus.dbc import FrameDecodeError, load
    from cell.runtime.replay import read_log

    db = db or load()
    want = set(names)
    out: dict[str, tuple[list[float], list[float]]] = {}
    for msg in read_log(path, progress=None if progress else False):
        try:
            message, values = db.decode(msg)
        except FrameDecodeError:
            continue
        for k, v in values.items():
            if k in want:
                ts, vs = out.setdefault(k, ([], []))
                ts.append(msg.timestamp)
                vs.append(v)
    return {k: (np.asarray(t), np.asarray(v, dtype=float)) for k, (t, v) in out.items()}


def stationary_segments(data: dict[str, tuple[np.ndarray, np.ndarray]], settle: float = 6.0,
                        min_hold: float = 8.0) -> list[Segment]:
    """Runs of constant speed and load demand at least ``min_hold`` s long, from ``settle``
    s after they begin; means and variances of every channel over each."""
    missing = [n for n in REQUIRED if n not in data or data[n][0].size == 0]
    if missing:
        raise ConfigError(f"the log has no {', '.join(missing)}: the air-path design needs "
                          f"{', '.join(REQUIRED)} (a log of the si-turbo engine, e.g. testcell "
                          f"sim --engine si-turbo --duty operating-points --out ops.log)")
    ts, speed = data["ENGINE_SPEED"]
    tl, load = data["SI_LOAD_DEMAND"]
    load_at = np.interp(ts, tl, load)
    change = np.flatnonzero((np.abs(np.diff(speed)) > 1.0) | (np.abs(np.diff(load_at)) > 1e-3))
    bounds = np.concatenate([[0], change + 1, [ts.size]])
    segments = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b - a < 2:
            continue
        t0, t1 = ts[a] + settle, ts[b - 1]
        if t1 - ts[a] < min_hold:
            continue
        mean, var = {}, {}
        for name in REQUIRED:
            t, v = data[name]
            sel = (t >= t0) & (t <= t1)
            if sel.sum() < 10:
                break
            mean[name], var[name] = float(v[sel].mean()), float(v[sel].var())
        else:
            segments.append(Segment(float(np.median(speed[a:b])), float(np.median(load_at[a:b])),
                                    float(t0), float(t1), mean, var))
    return segments


def check_coverage(segments: list[Segment], speeds: tuple[float, ...] | None, min_loads: int = 2
                   ) -> None:
    """Refuse a set of segments that does not cover the grid: every speed of ``speeds``
    needs ``min_loads`` stationary load levels."""
    if not segments:
        raise ConfigError("the log has no stationary segment (constant speed and load demand for "
                          "at least the minimum hold); record one with --duty operating-points")
    if speeds is None:
        return
    for s in speeds:
        loads = {round(seg.load, 3) for seg in segments if abs(seg.speed - s) <= 25.0}
        if not loads:
            have = sorted({round(seg.speed) for seg in segments})
            raise ConfigError(f"no stationary segment at {s:g} rpm (the log has stationary "
                              f"segments at {', '.join(f'{h:g}' for h in have)} rpm)")
        if len(loads) < min_loads:
            raise ConfigError(f"only {len(loads)} stationary load level at {s:g} rpm; the gain "
                              f"table needs at least {min_loads} per speed")


def design_point(seg: Segment, params: SIAirPathParams = MODEL_PARAMS) -> TablePoint:
    """Linearisation, R_i and Q_i at one stationary segment (seed 003, §3.1-3.3)."""
    m = seg.mean
    u = [m["THROTTLE"], min(max(m["WASTEGATE"] / 100.0, 0.0), 1.0), m["ENGINE_SPEED"], 1.0]
    meas_si = {name: m[name] * scale + offset for name, (_, scale, offset) in MEASUREMENTS.items()}
    guess = [meas_si["P_IC"], meas_si["P_IM"], meas_si["T_IM"],
             max(meas_si["P_IC"], params.p_amb) * 1.05, meas_si["N_TC"]]
    try:
        x = steady_state(params, u, guess)
    except ArithmeticError as exc:
        raise ConfigError(f"segment at {seg.speed:g} rpm, load {seg.load:.2f} "
                          f"({seg.t0:.1f}-{seg.t1:.1f} s): {exc}") from None
    xa = np.concatenate([x[:5], [0.0]])
    A = numerical_jacobian(lambda v: airpath_rhs(0.0, v, u, params), xa)
    Q = list(Q_FLOOR)
    for name, (row, _, _) in MEASUREMENTS.items():
        Q[row] = max((meas_si[name] - x[row]) ** 2, Q_FLOOR[row])
    R = {name: max(seg.var[name] * scale * scale, R_FLOOR[name])
         for name, (_, scale, _) in MEASUREMENTS.items()}
    return TablePoint(speed=seg.speed, load=seg.load, u=u, x=xa.tolist(),
                      x_meas={k: m[k] for k in MEASUREMENTS}, A=A.tolist(), Q=Q, R=R,
                      window=[seg.t0, seg.t1])


def design(segments: list[Segment], dt: float = 0.01, params: SIAirPathParams = MODEL_PARAMS,
           feedback: tuple[str, ...] = DEFAULT_FEEDBACK, source: str = "",
           progress: bool = True) -> GainTable:
    """The gain table of a set of stationary segments."""
    points = [design_point(seg, params) for seg in tqdm(segments, desc="design airpath",
                                                        unit="point", disable=not progress)]
    table = GainTable(dt, points, tuple(feedback), source,
                      {"model": "cell.plant.si_airpath.MODEL_PARAMS",
                       "R_floor": R_FLOOR, "Q_floor": list(Q_FLOOR)})
    table.fill_gains()
    return table


def design_log(log: str | Path, out: str | Path | None = None, *, speeds: tuple[float, ...] | None = None,
               dt: float = 0.01, settle: float = 6.0, min_hold: float = 8.0, progress: bool = True,
               db=None) -> GainTable:
    """Read ``log``, check it covers ``speeds``, design, and write ``out`` (JSON) when given.
    Nothing is written unless the whole design succeeds."""
    if not (math.isfinite(dt) and 0.0 < dt <= 1.0):
        raise ConfigError(f"--dt must be in (0, 1] s, got {dt}")
    data = read_channels(log, progress=progress, db=db)
    segments = stationary_segments(data, settle, min_hold)
    check_coverage(segments, speeds)
    table = design(segments, dt, source=str(log), progress=progress)
    if out is not None:
        table.save(out)
    return table


def _speeds(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(s) for s in text.split(",") if s.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"--speeds {text!r}: a comma-separated list of rpm") from None
    if not vals or any(not math.isfinite(v) or v <= 0 for v in vals):
        raise argparse.ArgumentTypeError(f"--speeds {text!r}: speeds must be positive rpm")
    return vals


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", help="CAN log of stationary operating points (testcell sim --engine "
                                    "si-turbo --duty operating-points --out ops.log)")
    parser.add_argument("--out", default="airpath_gains.json", metavar="FILE",
                        help="gain table to write, JSON (default airpath_gains.json)")
    parser.add_argument("--speeds", type=_speeds, default=None, metavar="RPM,RPM,..",
                        help="speeds the log must cover with stationary segments (default: any)")
    parser.add_argument("--dt", type=float, default=0.01, help="observer tick period, s (default 0.01)")
    parser.add_argument("--settle", type=float, default=6.0,
                        help="seconds dropped at the start of each stationary segment (default 6)")
    parser.add_argument("--min-hold", type=float, default=8.0,
                        help="shortest stationary segment used, s (default 8)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def main(args: argparse.Namespace) -> int:
    table = design_log(args.log, args.out, speeds=args.speeds, dt=args.dt, settle=args.settle,
                       min_hold=args.min_hold, progress=not args.quiet)
    speeds = sorted({round(p.speed) for p in table.points})
    print(f"wrote {args.out}: {len(table.points)} operating points at {', '.join(map(str, speeds))} "
          f"rpm, feedback {', '.join(table.feedback)}, dt {table.dt:g} s")
    return 0


AIRPATH_DESIGN = Experiment(
    "airpath", "gain table of the SI air-path observer from a log of stationary points",
    add_arguments, main, seed="seed 003, §3",
    description="Linearise the default air-path model at each stationary segment of LOG, take "
                "R from the stationary measurement variance (with a floor) and Q from the "
                "stationary model error, solve the discrete Riccati equation per point and write "
                "the gain table (JSON) that the runtime's airpath observer loads.")
