"""Scoring filters on the ``transient`` duty cycle against simulator truth (shared by tests)."""

import numpy as np

from cell.sim import simulate
from cell.sim.lockstep import feed
from cell.runtime.scheduler import Runtime


def run_cycle(db, blocks, names, seed):
    """Run the transient cycle's frames through ``blocks``; rows of (t, *names) per MED tick."""
    rt = Runtime(db, blocks)
    rows = []
    feed(rt, simulate(db, "transient", seed),
         lambda t: rows.append([t, *(rt.channels[n].value for n in names)]))
    return np.array(rows, dtype=float).T


def time_to_63(t, x, truth, step):
    """Seconds from a step until ``x`` covers 63 % of the truth's change across it."""
    before = truth[(t >= step - 5) & (t < step)].mean()
    after = truth[(t >= step + 20) & (t < step + 34)].mean()
    crossed = np.nonzero((t >= step) & ((x - before) / (after - before) >= 0.63))[0]
    return t[crossed[0]] - step
