r"""Observer designs on a grid of engine speeds, made off the hot path and interpolated.

An angle-domain observer of a time-domain sensor (seed 001's UEGO inversion) has gains that
depend on the engine speed: a lag of time constant :math:`\tau` is :math:`1/(\tau\omega_e)`
per radian of crank angle. Designing at every speed change costs tens of milliseconds, which
stalls the runtime's loop. Instead a :class:`SpeedGrid` holds the designs at geometrically
spaced speeds (``ratio`` apart), made once per process and per set of parameters:

- a background thread designs every node as soon as the grid is first asked for one,
  nearest the speed asked first; a node asked for before the thread reached it is designed
  at once (only in the first moments of a process);
- :meth:`SpeedGrid.system` gives a :class:`InterpolatedSystem` at a speed: the per-frame
  transition of the two neighbouring designs, interpolated linearly in log-speed, entry by
  entry. The designs are smooth in the speed, so this is closer to the exact design than a
  design held over a band;
- the caller keeps one system while the speed stays within a hysteresis band
  (:meth:`SpeedGrid.moved`), so a speed that dithers does not rebuild anything.

The node designs are a pure function of the speed and the parameters, so the results do
not depend on when the thread got to a node.
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


class InterpolatedSystem:
    """The :meth:`LinearPeriodic.run` of a design between two grid nodes.

    ``weight`` is the share of the upper node (0: the lower node's design exactly).
    """

    def __init__(self, lower: LinearPeriodic, upper: LinearPeriodic, weight: float) -> None:
        self.lower, self.upper, self.weight = lower, upper, float(weight)
        self.d, self.p, self.q = lower.d, lower.p, lower.q
        self.period = lower.period
        self._stacked: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    @staticmethod
    def _block(lp: LinearPeriodic, j: int, n: int) -> np.ndarray:
        got = lp._stacked.get((j, n))
        if got is None:
            F, G, H, J = lp.frame(j, n)
            got = lp._stacked[(j, n)] = (np.block([[F, G], [H, J]]),
                                         np.empty(lp.d + n * lp.p))
        return got[0]

    def run(self, z: np.ndarray, j: int, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """State after the samples ``y`` from angle index ``j`` and the outputs at each."""
        n = len(y)
        key = (j % self.period, n)
        got = self._stacked.get(key)
        if got is None:
            S = self._block(self.lower, *key)
            if self.weight:
                S = S + self.weight * (self._block(self.upper, *key) - S)
            got = self._stacked[key] = (S, np.empty(self.d + n * self.p))
        S, buf = got
        buf[:self.d] = z
        buf[self.d:] = np.ravel(y)
        v = S @ buf
        return v[:self.d], v[self.d:].reshape(n, self.q)


class SpeedGrid:
    """Designs ``design(rpm)`` at ``lo * ratio**i`` rpm up to ``hi`` (module docstring).

    ``design`` returns ``(system, extra)``: the :class:`LinearPeriodic` whose frames are
    interpolated, and whatever else the observer needs of a design (its stages), taken
    from the lower node.
    """

    def __init__(self, design: Callable[[float], tuple[LinearPeriodic, Any]], lo: float = 300.0,
                 hi: float = 9000.0, ratio: float = 1.05, hysteresis: float = 0.0025) -> None:
        if not (0.0 < lo < hi and ratio > 1.0 and hysteresis >= 0.0):
            raise ValueError(f"a speed grid needs 0 < lo < hi, ratio > 1 and hysteresis >= 0; "
                             f"got lo={lo}, hi={hi}, ratio={ratio}, hysteresis={hysteresis}")
        self._design = design
        count = int(math.ceil(math.log(hi / lo) / math.log(ratio))) + 1
        self.speeds = lo * ratio ** np.arange(count)
        self._log_lo, self._log_ratio = math.log(lo), math.log(ratio)
        self.hysteresis = float(hysteresis)
        self._nodes: list[tuple[LinearPeriodic, Any] | None] = [None] * count
        self._locks = [threading.Lock() for _ in range(count)]
        self._thread: threading.Thread | None = None
        self._start_lock = threading.Lock()
        #: designs made by the caller's thread because the background one had not got there
        self.designed_inline = 0
        self.designed = 0

    # -- nodes ------------------------------------------------------------------------------
    def node(self, i: int, inline: bool = True) -> tuple[LinearPeriodic, Any]:
        got = self._nodes[i]
        if got is not None:
            return got
        with self._locks[i]:
            got = self._nodes[i]
            if got is None:
                got = self._design(float(self.speeds[i]))
                lp = got[0]
                for j in range(0, lp.period, 4):  # the frames the simulator sends: 4 samples
                    InterpolatedSystem._block(lp, j, 4)
                lp._cache.clear()  # the stacked products are what runs
                self._nodes[i] = got
                self.designed += 1
                if inline:
                    self.designed_inline += 1
        return got

    def _fill(self, first: int) -> None:
        order = sorted(range(len(self.speeds)), key=lambda i: abs(i - first))
        for i in order:
            self.node(i, inline=False)

    def _start(self, near: int) -> None:
        with self._start_lock:
            if self._thread is None:
                self._thread = threading.Thread(target=self._fill, args=(near,), daemon=True,
                                                name="speed-grid-designs")
                self._thread.start()

    @property
    def complete(self) -> bool:
        return all(n is not None for n in self._nodes)

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the background designs (tests and benchmarks); True when all are made."""
        if self._thread is not None:
            self._thread.join(timeout)
        return self.complete

    # -- the system at a speed ----------------------------------------------------------------
    def position(self, rpm: float) -> tuple[int, float]:
        """``(lower node, weight of the upper one)`` at ``rpm``, clamped to the grid."""
        f = (math.log(rpm) - self._log_lo) / self._log_ratio
        last = len(self.speeds) - 1
        if f <= 0.0:
            return 0, 0.0
        if f >= last:
            return last, 0.0
        i = int(f)
        return i, f - i

    def system(self, rpm: float) -> tuple[InterpolatedSystem, Any]:
        """The interpolated design at ``rpm`` and the lower node's extras."""
        i, w = self.position(rpm)
        self._start(i)
        lower = self.node(i)
        upper = self.node(i + 1) if w else lower
        return InterpolatedSystem(lower[0], upper[0], w), lower[1]

    def moved(self, rpm: float, designed_at: float | None) -> bool:
        """Whether ``rpm`` has left the hysteresis band around the speed of the design in use."""
        return designed_at is None or abs(math.log(rpm / designed_at)) > self.hysteresis


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


__all__ = ["InterpolatedSystem", "SpeedGrid", "shared_grid"]
