"""What the observer benchmarks share: their command line, CPU-time timing and the load line.

Every observer benchmark takes the seconds of its drive as its one positional argument and
``--repeat N`` (best of N, on CPU time), and prints its ratio against the real-time budget on
one core both on the wall clock and on this process's CPU time (``time.process_time``): on a
loaded machine the second is what the code costs, the first what the machine gave it. The
load average is printed beside the numbers, as the machine's load moves them.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable


def parse(description: str, seconds: float, drive: str,
          argv: list[str] | None = None) -> argparse.Namespace:
    """``SECONDS`` (default ``seconds``, of ``drive``) and ``--repeat``."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("seconds", nargs="?", type=float, default=seconds,
                        help=f"seconds of {drive} to record and step (default {seconds:g})")
    parser.add_argument("--repeat", type=int, default=3,
                        help="timed runs over the same inputs; the best is reported (default 3)")
    args = parser.parse_args(argv)
    if args.seconds <= 0 or args.repeat < 1:
        parser.error("SECONDS must be positive and --repeat at least 1")
    return args


def best_of(repeat: int, run: Callable[[], object]) -> tuple[float, float]:
    """``(wall, cpu)`` seconds of the fastest of ``repeat`` calls of ``run`` (by CPU time)."""
    best: tuple[float, float] | None = None
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        run()
        got = (time.perf_counter() - t0, time.process_time() - c0)
        if best is None or got[1] < best[1]:
            best = got
    assert best is not None
    return best


def load_line() -> str:
    """The 1/5/15-minute load average, for beside the numbers."""
    try:
        one, five, fifteen = os.getloadavg()
    except OSError:
        return "load average: unknown"
    return f"load average {one:.2f} {five:.2f} {fifteen:.2f} on {os.cpu_count()} cores"


def verdict(ratio: float, goal: float) -> str:
    return "met" if ratio >= goal else "NOT met"


__all__ = ["best_of", "load_line", "parse", "verdict"]
