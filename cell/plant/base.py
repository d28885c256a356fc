"""What every plant is: a small stateful object with named inputs and outputs.

A plant's inputs and outputs are named by DBC signal (its truth included, as
``<SIGNAL>_TRUE``), so plants wire to each other, and to the bus, by name alone. Its
equations are plain functions over numbers or numpy arrays, in python-control's
``f(t, x, u, params)`` style, written beside it with the paper and equation they come from;
an observer's *model* calls the same functions with its own, deliberately different,
parameters.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import ClassVar

import numpy as np

from cell.core.errors import ConfigError


class Plant:
    """Base class of the simulator's plants.

    Subclasses set :attr:`inputs` and :attr:`outputs` (DBC signal names), hold their
    parameters in a dataclass at :attr:`params`, and fill :meth:`start`, :meth:`step` and
    :meth:`output`. A :class:`~cell.plant.composition.Composition` calls them in that order.

    Parameters
    ----------
    name:
        The plant's name in its composition (``engine``, ``exhaust``, ...).
    period:
        Step period, s. In a composition it is a whole multiple of the fastest plant's.
    """

    inputs: ClassVar[tuple[str, ...]] = ()
    outputs: ClassVar[tuple[str, ...]] = ()
    #: crank-angle sample streams (:mod:`cell.runtime.samples`) the plant produces: samples that
    #: it hands out with :meth:`take_samples` rather than as held outputs
    streams: ClassVar[tuple[str, ...]] = ()
    #: command signals (events, not held values): each received frame carrying one is handed
    #: to :meth:`command` once, with the frame's other command signals of this plant
    commands: ClassVar[tuple[str, ...]] = ()

    def __init__(self, name: str, period: float) -> None:
        if not period > 0 or not math.isfinite(period):
            raise ConfigError(f"plant {name}: step period must be > 0 s, got {period}")
        self.name = name
        self.period = float(period)

    def start(self, u: Mapping[str, float]) -> None:
        """Set the initial state from the inputs' initial values (those produced so far).

        An input that no plant produces and no frame has set yet is absent from ``u``.
        """

    def step(self, t: float, u: Mapping[str, float]) -> None:
        """Advance from ``t - period`` to ``t`` with the inputs ``u``."""
        raise NotImplementedError

    def output(self) -> dict[str, float]:
        """The current value of every output."""
        raise NotImplementedError

    def command(self, values: Mapping[str, float], t: float) -> None:
        """Act on one received command frame's signals of :attr:`commands` at time ``t``."""

    def set_safe(self, safe: bool) -> None:
        """Enter (``True``) or leave the safe state: what an actuator or an engine controller
        does when its commands stop (back-pressure valves open, the engine idles)."""

    def take_samples(self) -> dict[str, tuple[int, np.ndarray, np.ndarray]]:
        """The stream samples produced since the last call, per stream in :attr:`streams`.

        Each is ``(index, values, times)``: the global index of the first sample (its angle
        is ``index x step``), the consecutive samples, and each sample's simulation time.
        """
        return {}

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, period={self.period:g})"


def lag_factor(dt: float, tau: float) -> float:
    """Discrete first-order lag factor ``1 - exp(-dt / tau)`` (exact for a held input)."""
    return 1.0 - math.exp(-dt / tau)
