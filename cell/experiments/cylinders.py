"""``testcell experiment imbalance``: seed 001's cylinder-imbalance diagnosis on the cell.

Each case runs the ``si-turbo`` engine on a steady point (``--rpm``, default 1500, like the
paper's bench) with the crank-resolved plant, and the two seed-001 observers in the runtime
on the 6 deg sample frames, in lockstep on bus time. The engine starts balanced; at
``t_on`` a scenario frame (``FUEL_OFFSET_CMD``, what ``testcell scenario
fuel_offset_cyl_1=0.25`` sends) offsets the injectors. Results per case:

- the diagnosed cylinder (``IMBALANCE_CYL`` at the end) and the time from ``t_on`` to the
  first tick that names it, in engine cycles;
- the harmonic energies ``AFR_HARM_1..3`` before and after (mean over a second);
- the phase lag of the raw UEGO and of the reconstructed AFR behind the true manifold AFR
  (cross-correlation of the 6 deg samples);
- the torque balance ``TORQUE_BALANCE_1..4`` beside the true IMEP, and the stream counts.

Figures (PNG, as the paper's): 4 (measured vs reconstructed AFR), 5 and 7 (per-cylinder
diagnosis from the measured and from the reconstructed AFR, beside true IMEP), 6 and 8
(harmonic energies), 11 (measured vs reconstructed crank speed over two cycles) and 12
(balance energy beside IMEP).
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np

from cell.analysis.figures import pyplot, save
from cell.bus.dbc import CellDatabase, load
from cell.bus.scenario import scenario_frames
from cell.core.errors import ConfigError
from cell.core.registry import Experiment
from cell.estimators.cylinders import CYCLE, RodInversion, UegoInversion
from cell.plant.cylinders import N_CYL, CylinderParams
from cell.plant.si_engine import SICycle, steady_cycle
from cell.plant.si_turbo import si_turbo
from cell.runtime.samples import find_sample_streams
from cell.runtime.scheduler import Runtime
from cell.sim.lockstep import Lockstep
from cell.sim.simulator import Simulator


@dataclass(frozen=True)
class Case:
    """One run: the offsets applied at ``t_on``, the operating point and the bus's faults."""

    name: str
    offsets: tuple[float, ...]
    rpm: float = 1500.0
    load: float = 0.45
    t_on: float = 1.5
    duration: float = 4.0
    seed: int = 0
    drop: float = 0.0
    """Probability that a crank sensor frame is lost on the bus."""
    swap: float = 0.0
    """Probability that a crank sensor frame arrives after the next one of its stream."""

    @property
    def expected(self) -> tuple[int, ...]:
        """Cylinders a correct diagnosis may name (0: balanced): those whose fuel departs
        most from the mean (the λ control keeps the mean). Two opposite cylinders both rich
        make all four depart equally (two rich, two lean): any of them is right."""
        fuel = 1.0 + np.asarray(self.offsets, dtype=float)
        dev = np.abs(fuel - fuel.mean())
        if dev.max() < 1e-9:
            return (0,)
        return tuple(int(i) + 1 for i in np.nonzero(dev >= 0.99 * dev.max())[0])


# -- record: the engine and the observers in lockstep ----------------------------------------------
def lossy_wire(db: CellDatabase, drop: float, swap: float, seed: int
               ) -> Callable[[list[can.Message]], list[can.Message]]:
    """A bus that loses crank sensor frames with probability ``drop`` and delivers one after
    the next of its stream with probability ``swap``."""
    rng = np.random.default_rng([seed, 0x10])
    ids = {db.message(m).frame_id for m in ("CRANK_AFR_UEGO", "CRANK_N")}

    def wire(frames: list[can.Message]) -> list[can.Message]:
        out: list[can.Message] = []
        held: dict[int, can.Message] = {}
        for f in frames:
            if f.arbitration_id not in ids:
                out.append(f)
                continue
            if rng.random() < drop:
                continue
            prev = held.pop(f.arbitration_id, None)
            if prev is None and rng.random() < swap:
                held[f.arbitration_id] = f
                continue
            out.append(f)
            if prev is not None:
                out.append(prev)
        out.extend(held.values())
        return out

    return wire


class SampleTruth:
    """The truth streams of the 6 deg sample frames (``AFR_MANIFOLD_TRUE``, ``N_CYL_TRUE``),
    read on the frames' way to the runtime: each value by (frame time in µs, angle index)."""

    def __init__(self, db: CellDatabase, names: Sequence[str] = ("AFR_MANIFOLD_TRUE", "N_CYL_TRUE")
                 ) -> None:
        self.db = db
        self.layouts = {db.message(la.message).frame_id: la
                        for la in find_sample_streams(db.messages).values()}
        self.values: dict[str, dict[tuple[int, int], float]] = {n: {} for n in names}

    def read(self, frames: list[can.Message]) -> None:
        for f in frames:
            la = self.layouts.get(f.arbitration_id)
            if la is not None and la.name in self.values:
                idx, vals = la.unpack(self.db.decode(f)[1])
                key_t = round(f.timestamp * 1e6)
                for k, v in enumerate(vals):
                    self.values[la.name][(key_t, (idx + k) % CYCLE)] = v

    def beside(self, block: UegoInversion | RodInversion, stream: str) -> np.ndarray:
        """The block's trace (t, angle index, measured, reconstructed) with the truth of
        ``stream`` at each sample as a fifth column."""
        tr = np.concatenate(block.trace) if block.trace else np.zeros((0, 4))
        tv = self.values[stream]
        true = np.array([tv.get((round(r[0] * 1e6), int(r[1])), math.nan) for r in tr])
        return np.column_stack([tr, true]) if len(tr) else np.zeros((0, 5))


#: Channels of the observers recorded at every tick.
TICK_CHANNELS = (["IMBALANCE_CYL"] + [f"AFR_HARM_{k}" for k in (1, 2, 3)]
                 + [f"TORQUE_BALANCE_{i}" for i in range(1, N_CYL + 1)])


class TickRecorder:
    """At every MED tick: :data:`TICK_CHANNELS`, the UEGO observer's per-cylinder AFR
    (estimated and measured) and the true IMEP and AFR of each cylinder."""

    def __init__(self, rt: Runtime, comp, uego: UegoInversion) -> None:
        self.rt, self.comp, self.uego = rt, comp, uego
        self.rows: list[list[float]] = []
        self.afr_true: list[list[float]] = []

    def __call__(self, t: float) -> None:
        ch, sig = self.rt.channels, self.comp.signals
        self.afr_true.append([sig[f"AFR_CYL_{i}_TRUE"] for i in range(1, N_CYL + 1)])
        vals = [ch[n].value if ch[n].status == "ok" else math.nan for n in TICK_CHANNELS]
        vals = [math.nan if v is None else v for v in vals]
        u = self.uego
        self.rows.append([t, *vals, *u.cyl_est.tolist(), *u.cyl_meas.tolist(),
                          *(sig[f"IMEP_CYL_{i}_TRUE"] for i in range(1, N_CYL + 1))])

    def columns(self) -> dict[str, np.ndarray]:
        a = np.array(self.rows)
        n = len(TICK_CHANNELS)
        return {"t": a[:, 0], "diagnosis": a[:, 1], "harmonics": a[:, 2:5],
                "balance": a[:, 5:1 + n], "cyl_est": a[:, 1 + n:1 + n + 4],
                "cyl_meas": a[:, 5 + n:9 + n], "imep": a[:, 9 + n:13 + n]}


def run_case(case: Case, db: CellDatabase | None = None,
             wire: Callable[[list[can.Message]], list[can.Message]] | None = None, *,
             cylinders: CylinderParams | None = None, design: dict[str, Any] | None = None,
             cycle: SICycle | None = None) -> CaseResult:
    """Run one case offline (module docstring); ``wire`` may further impair the frames the
    runtime receives (after the case's own ``drop``/``swap``). ``cylinders`` is a plant
    variant, ``design`` an imbalance design the UEGO observer loads, ``cycle`` a drive in
    place of the case's steady point."""
    db = db or load()
    comp = si_turbo(cycle or steady_cycle(case.rpm, case.load, case.duration), case.seed,
                    imbalance=(0.0,) * N_CYL, cylinders=cylinders)
    sim = Simulator(comp, db)
    uego, rod = UegoInversion(record=True, design=design), RodInversion(record=True)
    rt = Runtime(db, [uego, rod])
    truth = SampleTruth(db)
    ticks = TickRecorder(rt, comp, uego)
    impair = lossy_wire(db, case.drop, case.swap, case.seed) if case.drop or case.swap else None

    def bus(frames: list[can.Message]) -> list[can.Message]:
        truth.read(frames)
        frames = frames if impair is None else impair(frames)
        return frames if wire is None else wire(frames)

    offsets = {f"fuel_offset_cyl_{i + 1}": v for i, v in enumerate(case.offsets)}
    on = False
    for _k, _ in Lockstep(sim, rt, on_tick=ticks, wire=bus).steps(round(case.duration / sim.dt)):
        if not on and sim.t >= case.t_on - 1e-9:
            # stamped now: the simulator discards a command older than one cycle (E2E)
            for f in scenario_frames(db, offsets, sim.t0 + sim.t):
                sim.receive(f)  # what `testcell scenario` puts on the bus
            on = True
    c = ticks.columns()
    return CaseResult(case, c["t"], c["diagnosis"], c["harmonics"], c["cyl_est"], c["cyl_meas"],
                      c["balance"], c["imep"], truth.beside(uego, "AFR_MANIFOLD_TRUE"),
                      truth.beside(rod, "N_CYL_TRUE"), np.array(ticks.afr_true),
                      rt.health()["streams"], {"afr": uego.state(), "rod": rod.state()})


# -- score ----------------------------------------------------------------------------------
@dataclass
class CaseResult:
    case: Case
    t: np.ndarray
    diagnosis: np.ndarray
    harmonics: np.ndarray
    cyl_est: np.ndarray
    cyl_meas: np.ndarray
    balance: np.ndarray
    imep: np.ndarray
    afr_trace: np.ndarray
    """Per sample: t, angle index, measured AFR, reconstructed AFR, true manifold AFR."""
    crank_trace: np.ndarray
    """Per sample: t, angle index, measured speed, reconstructed N_CYL, true N_CYL."""
    afr_true: np.ndarray
    """Per tick: the true AFR of each cylinder's charge."""
    streams: dict[str, Any] = field(default_factory=dict)
    observer_state: dict[str, Any] = field(default_factory=dict)

    @property
    def diagnosed(self) -> int | None:
        d = self.diagnosis[-1]
        return None if not np.isfinite(d) else int(d)

    def diagnosis_cycles(self) -> float | None:
        """Engine cycles from the imbalance until ``IMBALANCE_CYL`` first names an expected
        cylinder (``None``: never, or a balanced case)."""
        exp = [c for c in self.case.expected if c]
        if not exp:
            return None
        hit = (self.t >= self.case.t_on) & np.isin(self.diagnosis, exp)
        if not hit.any():
            return None
        return float((self.t[np.argmax(hit)] - self.case.t_on) * self.case.rpm / 120.0)

    def mean_harmonics(self, before: bool) -> np.ndarray:
        c = self.case
        sel = ((self.t > c.t_on - 1.0) & (self.t <= c.t_on) if before
               else self.t > c.duration - 1.0)
        return np.nanmean(self.harmonics[sel], axis=0)

    def phase_lags(self, after: float | None = None) -> dict[str, float]:
        """Cross-correlation lag (deg CA) of the UEGO and of the reconstruction behind the
        true manifold AFR, over the samples after ``after`` (default ``t_on`` + 1 s)."""
        a = self.afr_trace
        a = a[a[:, 0] > (self.case.t_on + 1.0 if after is None else after)]
        a = a[np.isfinite(a).all(axis=1)]
        return {"sensor_deg": 6.0 * xcorr_lag(a[:, 4], a[:, 2]),
                "estimate_deg": 6.0 * xcorr_lag(a[:, 4], a[:, 3])}

    def mean_balance(self) -> np.ndarray:
        return np.nanmean(self.balance[self.t > self.case.duration - 1.0], axis=0)

    def as_json(self) -> dict[str, Any]:
        c = self.case
        h0, h1 = self.mean_harmonics(True), self.mean_harmonics(False)
        # a lag is defined modulo the signal's period: one cylinder off repeats every cycle
        single = sum(1 for o in c.offsets if o) == 1
        lags = self.phase_lags() if single else {"sensor_deg": None, "estimate_deg": None}
        return {
            "case": c.name, "offsets": list(c.offsets), "rpm": c.rpm,
            "diagnosed_cylinder": self.diagnosed, "expected": list(c.expected),
            "diagnosis_cycles": _r(self.diagnosis_cycles()),
            "harmonics_before": [_r(v) for v in h0], "harmonics_after": [_r(v) for v in h1],
            "phase_lag_sensor_deg": _r(lags["sensor_deg"]),
            "phase_lag_estimate_deg": _r(lags["estimate_deg"]),
            "torque_balance": [_r(v) for v in self.mean_balance()],
            "imep_true": [_r(v) for v in self.imep[-1]],
            "streams": {k: {q: v for q, v in s.items() if q != "last_gap"}
                        for k, s in self.streams.items()},
        }


def _r(v: float | None, nd: int = 4) -> float | None:
    return None if v is None or not math.isfinite(v) else round(float(v), nd)


def xcorr_lag(ref: np.ndarray, sig: np.ndarray, max_lag: int = CYCLE // 2 - 1) -> int:
    """The lag (samples, >= 0 when ``sig`` is behind ``ref``) maximising their
    cross-correlation, mean removed; within half an engine cycle (a lag of a signal that
    repeats every cycle is defined modulo the cycle)."""
    r, s = ref - ref.mean(), sig - sig.mean()
    n = len(r)
    best, arg = -np.inf, 0
    for lag in range(-max_lag, max_lag + 1):
        if lag >= 0:
            v = float(np.dot(r[:n - lag], s[lag:])) / (n - lag)
        else:
            v = float(np.dot(r[-lag:], s[:n + lag])) / (n + lag)
        if v > best:
            best, arg = v, lag
    return arg


# -- figures --------------------------------------------------------------------------------
CYL_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red")


def _reconstruction(x: np.ndarray, trace: np.ndarray, labels: Sequence[str]):
    """A figure of a trace's truth, measurement and reconstruction (columns 4, 2 and 3) over
    ``x``; the figure and its axes."""
    fig, ax = pyplot().subplots(figsize=(8, 3.6))
    for col, color, lw, label in zip((4, 2, 3), ("0.6", "tab:blue", "tab:red"), (0.8, 1.0, 1.0),
                                     labels, strict=True):
        ax.plot(x, trace[:, col], color=color, lw=lw, label=label)
    return fig, ax


def plot_afr(path: Path, r: CaseResult) -> Path:
    """Figure 4: the UEGO against the reconstructed manifold AFR (and the truth)."""
    a = r.afr_trace
    c = r.case
    a = a[(a[:, 0] > c.t_on - 0.3) & (a[:, 0] < c.t_on + 0.6)]
    fig, ax = _reconstruction(a[:, 0], a, ("true manifold AFR (simulator)", "measured AFR (UEGO)",
                                           "reconstructed AFR (observer)"))
    ax.axvline(c.t_on, color="k", ls=":", lw=0.8)
    ax.set(xlabel="time [s]", ylabel="AFR [-]",
           title=f"Figure 4: AFR reconstruction, {c.name} at t = {c.t_on:g} s, {c.rpm:g} rpm")
    ax.legend(fontsize=8, loc="lower left")
    return save(fig, path)


def plot_diagnosis(path: Path, r: CaseResult, number: int) -> Path:
    """Figures 5 and 7: true IMEP, then the exhaust-phase mean of the measured and of the
    reconstructed AFR, per cylinder."""
    plt = pyplot()
    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    for i in range(N_CYL):
        kw = {"color": CYL_COLORS[i], "lw": 1.0, "label": f"cylinder {i + 1}"}
        axes[0].plot(r.t, r.imep[:, i], **kw)
        axes[1].plot(r.t, r.cyl_meas[:, i], **kw)
        axes[2].plot(r.t, r.cyl_est[:, i], **kw)
    for ax in axes:
        ax.axvline(r.case.t_on, color="k", ls=":", lw=0.8)
    axes[0].set(ylabel="IMEP [bar]", title=f"Figure {number}: diagnosis of cylinder imbalance, "
                                           f"{r.case.name}")
    axes[1].set(ylabel="AFR, measured")
    axes[2].set(ylabel="AFR, estimated", xlabel="time [s]")
    axes[0].legend(fontsize=8, ncol=4)
    return save(fig, path)


def plot_harmonics(path: Path, r: CaseResult, number: int) -> Path:
    """Figures 6 and 8: the harmonic energies E(k) of the reconstructed AFR."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 3.4))
    for k in range(3):
        ax.plot(r.t, r.harmonics[:, k], lw=1.2, label=f"E({k + 1})")
    ax.axvline(r.case.t_on, color="k", ls=":", lw=0.8)
    ax.set(xlabel="time [s]", ylabel="energy [AFR]",
           title=f"Figure {number}: harmonic energies, {r.case.name}")
    ax.legend(fontsize=8)
    return save(fig, path)


def plot_crank(path: Path, r: CaseResult) -> Path:
    """Figure 11: measured and reconstructed crank speed over two engine cycles."""
    a = r.crank_trace
    a = a[a[:, 0] > r.case.duration - 0.5]
    start = int(np.argmax(a[:, 1] == 0))
    a = a[start:start + 2 * CYCLE]
    fig, ax = _reconstruction(np.arange(len(a)) * 6.0, a, (
        "true speed next to the cylinders", "measured N_e,meas (end of the rod)",
        "reconstructed N_e,est (observer)"))
    ax.set(xlabel="crank angle [deg]", ylabel="engine speed [rpm]",
           title=f"Figure 11: engine speed reconstruction over 2 cycles, {r.case.rpm:g} rpm")
    ax.legend(fontsize=8)
    return save(fig, path)


def plot_balance(path: Path, r: CaseResult) -> Path:
    """Figure 12: true IMEP per cylinder above the balance energy V_i - mean(V)."""
    plt = pyplot()
    fig, axes = plt.subplots(2, 1, figsize=(6, 5.5))
    x = np.arange(1, N_CYL + 1)
    axes[0].bar(x, r.imep[-1], color=CYL_COLORS)
    axes[0].set(ylabel="IMEP [bar]", title=f"Figure 12: torque imbalance, {r.case.name}")
    lo = float(np.min(r.imep[-1]))
    axes[0].set_ylim(lo - 1.0, float(np.max(r.imep[-1])) + 0.5)
    axes[1].bar(x, r.mean_balance(), color=CYL_COLORS)
    axes[1].axhline(0.0, color="k", lw=0.6)
    axes[1].set(ylabel="balance energy [rpm²]", xlabel="cylinder")
    for ax in axes:
        ax.set_xticks(x)
    return save(fig, path)


def figures(out: Path, r: CaseResult) -> list[Path]:
    """The paper's figures of one case: 7 and 8 for two cylinders offset, else 4-6, 11, 12."""
    if sum(1 for o in r.case.offsets if o) == 2:
        return [plot_diagnosis(out / "fig7_diagnosis_opposite.png", r, 7),
                plot_harmonics(out / "fig8_harmonics_opposite.png", r, 8)]
    return [plot_afr(out / "fig4_afr_reconstruction.png", r),
            plot_diagnosis(out / "fig5_diagnosis.png", r, 5),
            plot_harmonics(out / "fig6_harmonics.png", r, 6),
            plot_crank(out / "fig11_crank_speed.png", r),
            plot_balance(out / "fig12_torque_balance.png", r)]


# -- the experiment -------------------------------------------------------------------------
def run(cases: Sequence[Case], out: Path | None, progress: bool = True) -> list[CaseResult]:
    """Run the cases with a progress bar; write the figures to ``out``."""
    from tqdm import tqdm

    db = load()
    results = [run_case(case, db)
               for case in tqdm(cases, unit="case", desc="imbalance", disable=not progress)]
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        for r in results:
            figures(out, r)
    return results


def format_result(j: dict[str, Any]) -> str:
    """One case's numbers (:meth:`CaseResult.as_json`) as a sentence."""
    return (f"{j['case']}: diagnosed cylinder {j['diagnosed_cylinder']} after "
            f"{j['diagnosis_cycles']} engine cycles; E(k) before "
            f"{j['harmonics_before']} after {j['harmonics_after']}; phase lag behind "
            f"the true AFR: UEGO {j['phase_lag_sensor_deg']} deg, reconstruction "
            f"{j['phase_lag_estimate_deg']} deg; torque balance {j['torque_balance']} "
            f"(IMEP {j['imep_true']} bar)")


# -- command line ---------------------------------------------------------------------------
def cases_from_args(args: argparse.Namespace) -> list[Case]:
    """The cases the options ask for; refuses bad ones before any work."""
    if not math.isfinite(args.rpm) or not 800.0 <= args.rpm <= 6000.0:
        raise ConfigError(f"--rpm must be 800..6000, got {args.rpm:g}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration >= 2.5):
        raise ConfigError(f"--duration must be at least 2.5 s, got {args.duration:g}")
    # the observers settle over engine cycles: scale the run with the cycle time
    t_on = max(1.5, 18 * 120.0 / args.rpm)
    duration = args.duration if args.duration is not None else t_on + max(2.5, 30 * 120.0 / args.rpm)
    t_on = min(t_on, duration - 1.0)
    kw = {"rpm": args.rpm, "t_on": t_on, "duration": duration, "seed": args.seed}
    if args.opposite and args.cylinder is not None:
        raise ConfigError("--opposite and --cylinder exclude each other")
    if args.cylinder is not None:
        if args.cylinder not in range(1, N_CYL + 1):
            raise ConfigError(f"--cylinder must be 1..{N_CYL}, got {args.cylinder}")
        if not math.isfinite(args.offset) or not 0 < abs(args.offset) <= 0.5:
            raise ConfigError(f"--offset must be a fuel fraction in -0.5..+0.5 other than 0, "
                              f"got {args.offset:g}")
        off = [0.0] * N_CYL
        off[args.cylinder - 1] = args.offset
        return [Case(f"cylinder {args.cylinder} {args.offset:+.0%} fuel", tuple(off), **kw)]
    opposite = Case("opposite cylinders 1 and 4 +25 % fuel", (0.25, 0.0, 0.0, 0.25), **kw)
    if args.opposite:
        return [opposite]
    return [Case("cylinder 1 +25% fuel", (0.25, 0.0, 0.0, 0.0), **kw), opposite]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cylinder", type=int, default=None, metavar="N",
                        help="offset one cylinder (1..4) instead of the default two cases")
    parser.add_argument("--offset", type=float, default=0.25, metavar="X",
                        help="its fuel offset, a fraction (default +0.25)")
    parser.add_argument("--opposite", action="store_true",
                        help="only the case of cylinders 1 and 4 offset against each other")
    parser.add_argument("--rpm", type=float, default=1500.0, help="engine speed (default 1500)")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="run length per case (default: about 50 engine cycles)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="experiment-imbalance", metavar="DIR",
                        help="folder for the PNG figures (default experiment-imbalance)")
    parser.add_argument("--json", action="store_true", help="print one JSON line per case")


def main(args: argparse.Namespace) -> int:
    cases = cases_from_args(args)
    out = Path(args.out) if args.out else None
    for r in run(cases, out, progress=not args.json):
        j = r.as_json()
        print(json.dumps(j) if args.json else format_result(j))
    if out is not None and not args.json:
        print(f"figures in {out}/")
    return 0


IMBALANCE = Experiment(
    "imbalance", "cylinder imbalance from the UEGO and the crank speed (periodic-input observers)",
    add_arguments, main, seed="seed 001, Figures 4-8, 11-12",
    description=__doc__.split("\n\n")[0])
