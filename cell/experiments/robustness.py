"""``testcell experiment robustness``: the observers on plants they were not written against.

Each **variant** is a set of the ``si-turbo`` plant options an observer cannot know (issue
18): the exhaust transport phase, the UEGO lags and the manifold mixing of the
crank-resolved plant (``--exhaust-phase``, ``--uego-lags``, ``--mixing``), and the λ sensor
model, kinetics and storage cells of the catalyst (its variant options). For every variant
the experiment designs from one log and evaluates on others, with another noise seed and
another drive:

- **imbalance** (``afr_inversion``): the design log runs the engine at two speeds with a
  known +15 % on cylinder 2 from part-way through (:data:`DESIGN_OFFSET`); ``testcell
  design imbalance``'s code identifies the exhaust phase per speed and the UEGO lags; the
  evaluations run at a third speed and another load with the design loaded: *balanced*
  (no cylinder may ever be named), *+15 % on cylinder 1* and *−20 % on cylinder 3* (the
  cylinder must be named within :data:`NAME_WITHIN` s of the offset, and no other cylinder
  at any time);
- **catalyst** (``twc``): *fresh*, *aged 0.6* and an *OSC step*, each scored by
  ``cell.experiments.catalyst.robustness_case(variant, case, seed, short)``; a cell shows
  "not available" where that function does not exist.

It prints the table (per cell: passed, and the main number), writes a heat map
(``robustness.png``: green passed, red failed, grey not available) and a JSON file of every
cell. ``--short`` runs the short cycles the tests use; ``--variants`` picks variants by
number.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cell.analysis.figures import format_table, pyplot, save
from cell.bus.dbc import CellDatabase, load
from cell.bus.scenario import scenario_frames
from cell.core.errors import ConfigError
from cell.core.registry import Experiment
from cell.design.cylinders import design_logs
from cell.experiments.cylinders import Case, CaseResult, run_case
from cell.plant.cylinders import N_CYL, variant_params
from cell.plant.si_engine import SICycle
from cell.plant.si_turbo import si_turbo
from cell.sim.lockstep import Lockstep
from cell.sim.simulator import Simulator


@dataclass(frozen=True)
class Variant:
    """A plant variant: its name and the ``si-turbo`` plant options (settings keys)."""

    name: str
    plant: Mapping[str, Any] = field(default_factory=dict)


#: The matrix: the cell's own plant, then one thing changed at a time, then several together.
VARIANTS: tuple[Variant, ...] = (
    Variant("cell's own plant"),
    Variant("exhaust phase +30 deg", {"exhaust_phase": 30.0}),
    Variant("exhaust phase +60 deg", {"exhaust_phase": 60.0}),
    Variant("exhaust phase -60 deg", {"exhaust_phase": -60.0}),
    Variant("UEGO lags x0.5", {"uego_lags": "0.0125,0.010"}),
    Variant("UEGO lags x2", {"uego_lags": "0.050,0.040"}),
    Variant("mixing x5", {"mixing": 0.015}),
    Variant("+50 deg, mixing x4, lags x1.5",
            {"exhaust_phase": 50.0, "mixing": 0.012, "uego_lags": "0.0375,0.030"}),
    Variant("λ lag on composition", {"lambda_sensor": "composition"}),
    Variant("λ dead time 50 ms, lags x2", {"lambda_dead_time": 0.05, "lambda_tau_scale": 2.0}),
    Variant("kinetics x0.3, 1 storage cell", {"kinetics_scale": 0.3, "storage_cells": 1}),
    Variant("kinetics x3, 12 storage cells", {"kinetics_scale": 3.0, "storage_cells": 12}),
    Variant("-40 deg, lags x0.6, composition, 8 cells",
            {"exhaust_phase": -40.0, "uego_lags": "0.015,0.012", "lambda_sensor": "composition",
             "storage_cells": 8}),
    Variant("+40 deg, mixing x3, kinetics x2, 12 thermal cells",
            {"exhaust_phase": 40.0, "mixing": 0.009, "kinetics_scale": 2.0, "thermal_cells": 12}),
)

#: imbalance cases: name -> fuel offsets evaluated (the design's is :data:`DESIGN_OFFSET`)
IMBALANCE_CASES: dict[str, tuple[float, ...]] = {
    "balanced": (0.0, 0.0, 0.0, 0.0),
    "cyl 1 +15 %": (0.15, 0.0, 0.0, 0.0),
    "cyl 3 -20 %": (0.0, 0.0, -0.20, 0.0),
}
CATALYST_CASES = ("fresh", "aged", "osc_step")
#: the design run's known offset (cylinder, fuel fraction) and its two speeds, rpm
DESIGN_OFFSET = (2, 0.15)
DESIGN_SPEEDS = (1500.0, 2500.0)
#: the evaluations' speed and load (a drive the design did not see)
EVAL_RPM, EVAL_LOAD = 2000.0, 0.3
#: the imbalanced cylinder must be named within this long after the offset, s
NAME_WITHIN = 2.0


@dataclass(frozen=True)
class Timing:
    """Run lengths, s: the design run's hold per speed and offset start, an evaluation's
    offset start and length."""

    hold: float
    design_on: float
    eval_on: float
    eval_duration: float


SHORT = Timing(hold=2.4, design_on=0.6, eval_on=1.0, eval_duration=3.2)
FULL = Timing(hold=4.0, design_on=1.0, eval_on=2.0, eval_duration=6.0)


# -- imbalance ------------------------------------------------------------------------------
def design_cycle(timing: Timing) -> SICycle:
    """The design run's drive: each of :data:`DESIGN_SPEEDS` held ``timing.hold`` s."""
    a, b = DESIGN_SPEEDS
    h = timing.hold
    return SICycle("design-two-speeds", np.array([0.0, h, h + 0.2]), np.array([a, a, b]),
                   np.array([0.45, 0.45, 0.45]), 2 * h + 0.2,
                   f"{a:g} rpm then {b:g} rpm at load 0.45")


def record_design_frames(variant: Variant, seed: int, timing: Timing,
                         db: CellDatabase | None = None) -> list:
    """The frames of the design run (what ``testcell sim --out`` writes, with ``testcell
    scenario fuel_offset_cyl_2=0.15`` sent at ``timing.design_on``)."""
    db = db or load()
    cycle = design_cycle(timing)
    sim = Simulator(si_turbo(cycle, seed, imbalance=(0.0,) * N_CYL,
                             cylinders=variant_params(variant.plant)), db)
    cyl, off = DESIGN_OFFSET
    frames, on = [], False
    for _k, got in Lockstep(sim).steps(round(cycle.duration / sim.dt), frames=True):
        frames.extend(got)
        if not on and sim.t >= timing.design_on - 1e-9:
            # stamped at send time: the simulator discards a command older than its cycle
            for f in scenario_frames(db, {f"fuel_offset_cyl_{cyl}": off}, sim.t0 + sim.t):
                sim.receive(f)
            on = True
    return frames


def score_imbalance(r: CaseResult, t_on: float) -> dict[str, Any]:
    """A cell of the matrix: passed, metrics and the reason (module docstring)."""
    exp = {c for c in r.case.expected if c}
    d = r.diagnosis
    named = d[np.isfinite(d) & (d > 0)]
    wrong = sorted({int(v) for v in named if int(v) not in exp})
    metrics: dict[str, Any] = {"wrong_names": wrong, "final": r.diagnosed}
    if not exp:
        metrics["time_to_name_s"] = None
        ok = len(named) == 0
        reason = "no cylinder named" if ok else f"named cylinder(s) {wrong} on a balanced engine"
        return {"passed": ok, "metrics": metrics, "reason": reason}
    hit = (r.t >= t_on) & np.isin(d, sorted(exp))
    t_name = float(r.t[np.argmax(hit)] - t_on) if hit.any() else None
    metrics["time_to_name_s"] = None if t_name is None else round(t_name, 3)
    if wrong:
        return {"passed": False, "metrics": metrics, "reason": f"named wrong cylinder(s) {wrong}"}
    if t_name is None:
        return {"passed": False, "metrics": metrics, "reason": "never named the cylinder"}
    if t_name > NAME_WITHIN:
        return {"passed": False, "metrics": metrics,
                "reason": f"named after {t_name:.2f} s (goal {NAME_WITHIN:g} s)"}
    return {"passed": True, "metrics": metrics, "reason": f"named after {t_name:.2f} s"}


def imbalance_cells(variant: Variant, seed: int, short: bool, db: CellDatabase | None = None,
                    design: bool = True) -> tuple[dict[str, dict[str, Any]], dict[str, Any] | None]:
    """The variant's imbalance cells, and the design used (None without ``design``)."""
    db = db or load()
    timing = SHORT if short else FULL
    d = None
    if design:
        try:
            d = design_logs([record_design_frames(variant, seed, timing, db)], DESIGN_OFFSET, db=db)
        except ConfigError as exc:
            bad = {"passed": False, "metrics": {}, "reason": f"design refused: {exc}"}
            return {c: dict(bad) for c in IMBALANCE_CASES}, None
    params = variant_params(variant.plant)
    cells = {}
    for i, (name, offsets) in enumerate(IMBALANCE_CASES.items()):
        case = Case(name, offsets, rpm=EVAL_RPM, load=EVAL_LOAD, t_on=timing.eval_on,
                    duration=timing.eval_duration, seed=seed + 1 + i)
        r = run_case(case, db, cylinders=params, design=d)
        cells[name] = score_imbalance(r, timing.eval_on)
    return cells, d


# -- catalyst -------------------------------------------------------------------------------
def catalyst_case() -> Callable[..., dict[str, Any]] | None:
    """``cell.experiments.catalyst.robustness_case`` where it exists."""
    from cell.experiments import catalyst

    return getattr(catalyst, "robustness_case", None)


NOT_AVAILABLE = {"passed": None, "metrics": {}, "reason": "not available"}


def catalyst_cells(variant: Variant, seed: int, short: bool) -> dict[str, dict[str, Any]]:
    fn = catalyst_case()
    if fn is None:
        return {c: dict(NOT_AVAILABLE) for c in CATALYST_CASES}
    out = {}
    for case in CATALYST_CASES:
        try:
            out[case] = fn(dict(variant.plant), case, seed, short)
        except ConfigError as exc:
            out[case] = {"passed": False, "metrics": {}, "reason": str(exc)}
    return out


# -- the matrix -----------------------------------------------------------------------------
def run(variants: Sequence[Variant], *, seed: int = 11, short: bool = False,
        catalyst: bool = True, progress: bool = True) -> list[dict[str, Any]]:
    """One row per variant: its name, options, design and cells by case."""
    from tqdm import tqdm

    db = load()
    rows = []
    for v in tqdm(variants, unit="variant", desc="robustness", disable=not progress):
        cells, d = imbalance_cells(v, seed, short, db)
        if catalyst:
            cells.update(catalyst_cells(v, seed, short))
        else:
            cells.update({c: dict(NOT_AVAILABLE) for c in CATALYST_CASES})
        ident = None if d is None else d["identified"]
        rows.append({"variant": v.name, "plant": dict(v.plant), "cells": cells,
                     "design": None if ident is None else {
                         "phase_deg": {str(p["rpm"]): p["phase_deg"] for p in ident["points"]},
                         "tau1": ident["tau1"], "tau2": ident["tau2"],
                         "explained_held_out": d["fit"]["explained_held_out"]}})
    return rows


def cases() -> list[str]:
    return [*IMBALANCE_CASES, *CATALYST_CASES]


def _cell_text(c: dict[str, Any]) -> str:
    if c["passed"] is None:
        return "n/a"
    t = c["metrics"].get("time_to_name_s")
    mark = "ok" if c["passed"] else "FAIL"
    return f"{mark} {t:.2f}s" if isinstance(t, float) else mark


def table(rows: Sequence[dict[str, Any]]) -> str:
    cols = cases()
    body = [[r["variant"], *(_cell_text(r["cells"][c]) for c in cols)] for r in rows]
    return format_table(body, ["variant", *cols], align="<" + ">" * len(cols))


def heat_map(path: Path, rows: Sequence[dict[str, Any]]) -> Path:
    """Variants x cases: green passed, red failed, grey not available."""
    plt = pyplot()
    from matplotlib.colors import ListedColormap

    cols = cases()
    grid = np.array([[math.nan if r["cells"][c]["passed"] is None else float(r["cells"][c]["passed"])
                      for c in cols] for r in rows])
    fig, ax = plt.subplots(figsize=(1.4 * len(cols) + 3.5, 0.42 * len(rows) + 1.6))
    cmap = ListedColormap(["tab:red", "tab:green"])
    cmap.set_bad("0.85")
    ax.imshow(np.ma.masked_invalid(grid), cmap=cmap, vmin=0, vmax=1, aspect="auto")
    for i, r in enumerate(rows):
        for j, c in enumerate(cols):
            ax.text(j, i, _cell_text(r["cells"][c]), ha="center", va="center", fontsize=7)
    ax.set_xticks(range(len(cols)), cols, fontsize=8)
    ax.set_yticks(range(len(rows)), [r["variant"] for r in rows], fontsize=8)
    ax.set_title("observers after design, on plant variants (green: passed, grey: not available)",
                 fontsize=9)
    return save(fig, path)


# -- command line ---------------------------------------------------------------------------
def _variants(text: str) -> list[int]:
    try:
        out = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--variants {text!r}: numbers 1..{len(VARIANTS)}, "
                                         "comma-separated") from None
    bad = [i for i in out if not 1 <= i <= len(VARIANTS)]
    if not out or bad:
        raise argparse.ArgumentTypeError(f"--variants {text!r}: each must be 1..{len(VARIANTS)}")
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--variants", type=_variants, default=None, metavar="N,N,..",
                        help=f"variants to run, numbered 1..{len(VARIANTS)} as --list-variants "
                             "shows (default: all)")
    parser.add_argument("--list-variants", action="store_true", help="list the variants and exit")
    parser.add_argument("--short", action="store_true", help="short cycles (as the tests run)")
    parser.add_argument("--no-catalyst", action="store_true", help="only the imbalance cases")
    parser.add_argument("--seed", type=int, default=11,
                        help="noise seed of the design runs (evaluations use the next ones)")
    parser.add_argument("--out", default="experiment-robustness", metavar="DIR",
                        help="folder for robustness.png and robustness.json")
    parser.add_argument("--json", action="store_true", help="print one JSON line per variant")


def main(args: argparse.Namespace) -> int:
    if args.list_variants:
        for i, v in enumerate(VARIANTS, 1):
            opts = " ".join(f"--{k.replace('_', '-')} {val}" for k, val in v.plant.items())
            print(f"{i:2d}  {v.name:<50} {opts}")
        return 0
    picked = [VARIANTS[i - 1] for i in (args.variants or range(1, len(VARIANTS) + 1))]
    rows = run(picked, seed=args.seed, short=args.short, catalyst=not args.no_catalyst,
               progress=not args.json)
    if args.json:
        for r in rows:
            print(json.dumps(r))
    else:
        print(table(rows))
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        heat_map(out / "robustness.png", rows)
        (out / "robustness.json").write_text(json.dumps(rows, indent=1) + "\n")
        if not args.json:
            print(f"heat map and cells in {out}/")
    return 0


ROBUSTNESS = Experiment(
    "robustness", "observers after design on a matrix of plant variants (imbalance, catalyst)",
    add_arguments, main, seed="issue 18",
    description=__doc__.split("\n\n")[0])
