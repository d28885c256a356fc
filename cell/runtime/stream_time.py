"""The blocks' work on sample streams, counted as their work at ticks is (issue 18 point 6).

A crank-angle observer does most of its work per frame of samples, between ticks. That time
is added to the block's ``step_time`` (the seconds, not the number of steps, so ``/health``,
``/metrics`` and the benchmarks see the block's whole cost), and to the work of the next
tick that has work, so that a tick period whose stream work and tick work together overrun
it is counted in ``tick_overruns``.
"""

from __future__ import annotations

import weakref
from typing import Any

_pending: weakref.WeakKeyDictionary[Any, list[float]] = weakref.WeakKeyDictionary()


def count(runtime: Any, block: str, seconds: float) -> None:
    """Count ``seconds`` of ``block``'s work on samples in ``runtime``."""
    spent = runtime.counters.step_time.get(block)
    if spent is None:
        spent = runtime.counters.step_time[block] = [0.0, 0]
    spent[0] += seconds
    acc = _pending.get(runtime)
    if acc is None:
        _pending[runtime] = [seconds]
    else:
        acc[0] += seconds


def take(runtime: Any) -> float:
    """The stream work counted since the last call (it goes to the tick that asks)."""
    acc = _pending.get(runtime)
    if acc is None:
        return 0.0
    seconds, acc[0] = acc[0], 0.0
    return seconds


__all__ = ["count", "take"]
