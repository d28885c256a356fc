"""Back-pressure frames for tests that drive a runtime by hand, without a simulator."""

from __future__ import annotations

import math
from collections.abc import Callable

Signal = Callable[[float], float]


def wavy(level: float) -> Signal:
    """``level`` plus a 10 mmH2O sine: a bank that is not flat, so a filter has work to do."""
    return lambda t: level + 10.0 * math.sin(t)


def steady(level: float) -> Signal:
    return lambda t: level


def feed(rt, db, t0: float, t1: float, left: Signal = steady(680.0), right: Signal | None = None,
         advance: bool = True) -> None:
    """One ``EXH_BP`` frame every 10 ms of bus time over ``[t0, t1)``, the banks' values from
    ``left(t)`` and ``right(t)`` (default: the left's); then, unless ``advance`` is false, the
    runtime's ticks up to ``t1 - 10 ms``."""
    right = right or left
    t = t0
    while t < t1 - 1e-9:
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": left(t), "EXH_BP_R": right(t)}, t))
        t = round(t + 0.01, 6)
    if advance:
        rt.advance(round(t1 - 0.01, 6))
