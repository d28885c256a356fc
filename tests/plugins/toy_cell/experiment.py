"""``testcell experiment toy-step``: the toy observer's velocity against simulator truth."""

from __future__ import annotations

import argparse
import json

import numpy as np

from cell.analysis.scores import truth_scores
from cell.bus.dbc import load
from cell.sim.lockstep import Lockstep
from cell.core import registry
from cell.core.registry import Experiment
from cell.runtime.scheduler import Runtime
from cell.sim.simulator import Simulator

from .observer import toy_observer
from .plant import Oscillator


def run(seconds: float, seed: int = 0) -> dict[str, float]:
    """RMSE of the observed velocity and of the raw position, scored after 5 s."""
    db = load(registry.DBC_FILES)  # the cell's own files and the plugin's toy.dbc
    sim = Simulator(Oscillator.composition(seed), db)
    rt = Runtime(db, [toy_observer()])
    rows = []

    def on_tick(t: float) -> None:
        ch = rt.channels
        rows.append([t, ch["TOY_EST_VEL"].value, ch["TOY_VEL_TRUE"].value,
                     ch["TOY_POS"].value, ch["TOY_POS_TRUE"].value])

    Lockstep(sim, rt, stride=10, on_tick=on_tick).run(seconds)
    a = np.array([r for r in rows if r[0] >= 5.0 and None not in r], dtype=float)
    vel = truth_scores(a[:, 1], a[:, 2], rt.rates.MED)
    pos_raw = float(np.sqrt(np.mean((a[:, 3] - a[:, 4]) ** 2)))
    return {"vel_rmse": float(vel["rmse"][0]), "pos_raw_rmse": pos_raw,
            "vel_std": float(np.std(a[:, 2])), "ticks": len(a)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=30.0, help="run length (default 30 s)")
    parser.add_argument("--seed", type=int, default=0)


def main(args: argparse.Namespace) -> int:
    print(json.dumps(run(args.seconds, args.seed)))
    return 0


TOY_STEP = Experiment("toy-step", "the toy observer's velocity against the plant's truth",
                      add_arguments, main, seed="test plugin")
