r"""Observer designs on a grid of engine speeds, made off the hot path.

An angle-domain observer of a time-domain sensor (seed 001's UEGO inversion) has gains that
depend on the engine speed: a lag of time constant :math:`\tau` is :math:`1/(\tau\omega_e)`
per radian of crank angle. The observer uses the design of the 1 % speed band it runs in
(node ``i`` at :math:`1.01^i` rpm). Designing a band costs tens of milliseconds (the
per-angle tables and the per-frame products), which would stall the runtime's loop at
every band the engine speed crosses. A :class:`SpeedGrid` makes them elsewhere:

- a background thread designs the bands next to the one in use (``ahead`` on each side)
  as soon as the speed settles in a band, so a speed that moves finds its next band made;
  only a band asked for before the thread got there (the first one of a process, or a jump
  of more than ``ahead`` bands within one frame) is designed in the caller's thread, and
  counted (:attr:`SpeedGrid.designed_inline`);
- :meth:`SpeedGrid.select` holds the band in use until the speed has left it by
  ``hysteresis`` of a band width, so a speed that dithers at a band edge does not flip
  between two designs;
- at most ``keep`` designs are held (the ones farthest from the speed go first), shared by
  every observer of the process with the same parameters (:func:`shared_grid`).

A node's design is a pure function of its speed and the parameters, so the results do not
depend on which thread made it, or when.
"""

from __future__ import annotations

import collections
import math
import threading
from collections.abc import Callable, Hashable
from typing import Any

import numpy as np

from cell.estimators.periodic import LinearPeriodic

#: grids kept per process (a retuned observer makes a new one; the oldest goes)
MAX_GRIDS = 4
#: the band width: node ``i`` is designed at ``BAND ** i`` rpm
BAND = 1.01


class SpeedGrid:
    """Designs ``design(rpm)`` per 1 % speed band, made ahead by a background thread.

    ``design`` returns ``(system, extra)``: the :class:`LinearPeriodic` that runs the
    samples (its frames of ``frame_len`` samples are multiplied out with the design) and
    whatever else the observer needs of a design.
    """

    def __init__(self, design: Callable[[float], tuple[LinearPeriodic, Any]], *,
                 ahead: int = 3, keep: int = 12, hysteresis: float = 0.25,
                 frame_len: int = 4) -> None:
        if ahead < 0 or keep < 2 * ahead + 1 or not 0.0 <= hysteresis < 0.5:
            raise ValueError(f"a speed grid needs ahead >= 0, keep >= 2 ahead + 1 and "
                             f"0 <= hysteresis < 0.5; got ahead={ahead}, keep={keep}, "
                             f"hysteresis={hysteresis}")
        self._design = design
        self.ahead, self.keep, self.hysteresis = int(ahead), int(keep), float(hysteresis)
        self.frame_len = int(frame_len)
        self._nodes: dict[int, tuple[LinearPeriodic, Any]] = {}
        self._lock = threading.Lock()  # the node table
        self._making: dict[int, threading.Lock] = {}
        self._wanted: collections.deque[int] = collections.deque()
        self._wake = threading.Condition(self._lock)
        self._thread: threading.Thread | None = None
        self._centre = 0
        #: designs made in the caller's thread because the background one had not got there
        self.designed_inline = 0
        #: designs made in all
        self.designed = 0

    # -- nodes ------------------------------------------------------------------------------
    @staticmethod
    def speed(i: int) -> float:
        return BAND ** i

    def _make(self, i: int, inline: bool) -> tuple[LinearPeriodic, Any]:
        with self._lock:
            got = self._nodes.get(i)
            if got is not None:
                return got
            making = self._making.setdefault(i, threading.Lock())
        with making:
            got = self._nodes.get(i)
            if got is not None:
                return got
            try:
                got = self._design(self.speed(i))
            except Exception:
                with self._lock:
                    self._making.pop(i, None)
                raise
            lp = got[0]
            n = self.frame_len
            for j in range(0, lp.period, n):  # the frames of the stream, multiplied out
                lp.run(np.zeros(lp.d), j, np.zeros((n, lp.p)))
            lp._cache.clear()  # the stacked products are what runs
            with self._lock:
                self._nodes[i] = got
                self._making.pop(i, None)
                self.designed += 1
                if inline:
                    self.designed_inline += 1
                self._trim()
        return got

    def _trim(self) -> None:
        while len(self._nodes) > self.keep:
            far = max(self._nodes, key=lambda k: abs(k - self._centre))
            del self._nodes[far]

    def _work(self) -> None:
        while True:
            with self._wake:
                while not self._wanted:
                    self._wake.wait()
                i = self._wanted.popleft()
                if i in self._nodes or abs(i - self._centre) > self.ahead:
                    continue
            try:
                self._make(i, inline=False)
            except Exception:  # a band that cannot be designed is designed (and fails) inline
                pass

    def _prefetch(self, centre: int) -> None:
        with self._wake:
            self._centre = centre
            want = [centre + d * s for d in range(1, self.ahead + 1) for s in (1, -1)]
            self._wanted = collections.deque(i for i in want if i not in self._nodes)
            if self._wanted:
                if self._thread is None:
                    self._thread = threading.Thread(target=self._work, daemon=True,
                                                    name="speed-grid-designs")
                    self._thread.start()
                self._wake.notify()

    def idle(self) -> bool:
        """No band near the one in use is waiting for its design (tests and benchmarks)."""
        with self._lock:
            return not self._wanted and not self._making

    # -- the design at a speed ----------------------------------------------------------------
    def select(self, rpm: float, current: int | None) -> int:
        """The band to run at ``rpm``: ``current`` while the speed is within it or within
        ``hysteresis`` of a band width of its edges, else the band the speed is in."""
        f = math.log(rpm) / math.log(BAND)
        if current is not None and abs(f - current) <= 0.5 + self.hysteresis:
            return current
        return int(round(f))

    def design(self, i: int) -> tuple[LinearPeriodic, Any]:
        """Band ``i``'s design (made now if the background thread has not made it), and the
        bands around it queued for the background thread."""
        got = self._nodes.get(i)
        if got is None:
            got = self._make(i, inline=True)
        self._prefetch(i)
        return got


_GRIDS: collections.OrderedDict[Hashable, SpeedGrid] = collections.OrderedDict()
_GRIDS_LOCK = threading.Lock()


def shared_grid(key: Hashable, design: Callable[[float], tuple[LinearPeriodic, Any]],
                **kwargs: Any) -> SpeedGrid:
    """The process's grid for ``key`` (the design's parameters), made on first use."""
    with _GRIDS_LOCK:
        grid = _GRIDS.get(key)
        if grid is None:
            grid = _GRIDS[key] = SpeedGrid(design, **kwargs)
            while len(_GRIDS) > MAX_GRIDS:
                _GRIDS.popitem(last=False)
        else:
            _GRIDS.move_to_end(key)
        return grid


__all__ = ["BAND", "SpeedGrid", "shared_grid"]
