"""Plants wired together by signal name, each stepped at its own rate."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

from cell.core.errors import ConfigError
from cell.plant.base import Plant

_EPS = 1e-9


class Composition:
    """An engine: plants whose inputs are other plants' outputs, or frames from the bus.

    The composition steps at the fastest plant's period ``dt``; a plant whose period is
    ``n`` times that steps at every ``n``-th step. Within a step, plants step in the order
    given, so a plant listed after another sees that plant's outputs of the same step. An
    input that no plant produces is *external*: it comes from the bus (a demand or a
    scenario command, see :meth:`set_input`) and is absent until it first arrives.

    Parameters
    ----------
    name:
        The engine profile's name.
    plants:
        The plants, in stepping order. Two plants producing one signal are refused.
    duration:
        Nominal length of a run, s (the duty cycle's), for runs given no duration.
    about:
        What the profile wants said about this run when it starts (duty, seed, options).
    """

    def __init__(self, name: str, plants: Sequence[Plant], duration: float | None = None,
                 about: dict[str, object] | None = None) -> None:
        if not plants:
            raise ConfigError(f"engine {name}: a composition needs at least one plant")
        self.name = name
        self.plants = list(plants)
        self.duration = duration
        self.about = dict(about or {})
        self.producer: dict[str, Plant] = {}
        names = set()
        for plant in self.plants:
            if plant.name in names:
                raise ConfigError(f"engine {name}: two plants are named {plant.name!r}")
            names.add(plant.name)
            for out in plant.outputs:
                other = self.producer.get(out)
                if other is not None:
                    raise ConfigError(f"engine {name}: {out} is produced by both plant "
                                      f"{other.name} and plant {plant.name}")
                self.producer[out] = plant
        self.consumers: dict[str, list[Plant]] = {}
        for plant in self.plants:
            for inp in plant.inputs:
                self.consumers.setdefault(inp, []).append(plant)
        self.commander: dict[str, Plant] = {}
        for plant in self.plants:
            for name_ in plant.commands:
                self.commander[name_] = plant
        self.external = {s for s in self.consumers if s not in self.producer} | set(self.commander)
        #: whether the plants are in their safe state (:meth:`set_safe`)
        self.safe = False
        self.dt = min(p.period for p in self.plants)
        self._every: list[int] = []
        for plant in self.plants:
            n = plant.period / self.dt
            if abs(n - round(n)) > 1e-6:
                raise ConfigError(f"engine {name}: plant {plant.name}'s period {plant.period:g} s "
                                  f"is not a whole multiple of {self.dt:g} s")
            self._every.append(round(n))
        self.k = 0
        #: the current value of every plant output and of every external input received
        self.signals: dict[str, float] = {}
        for plant in self.plants:
            plant.start(self._inputs(plant))
            self.signals.update(plant.output())

    @property
    def t(self) -> float:
        """Simulation time, s (``k x dt``)."""
        return self.k * self.dt

    def describe(self) -> dict[str, object]:
        return {"engine": self.name, **self.about}

    def plant(self, name: str) -> Plant:
        for p in self.plants:
            if p.name == name:
                return p
        raise ConfigError(f"engine {self.name} has no plant {name!r}; it has: "
                          f"{', '.join(p.name for p in self.plants)}")

    def _inputs(self, plant: Plant) -> dict[str, float]:
        s = self.signals
        return {name: s[name] for name in plant.inputs if name in s}

    def set_input(self, name: str, value: float) -> None:
        """Set an external input (from a received frame); it holds until set again."""
        if name not in self.external:
            raise ConfigError(f"engine {self.name}: {name} is not an input of any plant "
                              f"(inputs from the bus: {', '.join(sorted(self.external)) or 'none'})")
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"engine {self.name}: {name} must be finite, got {value}")
        self.signals[name] = value

    def command(self, values: dict[str, float]) -> None:
        """Hand one received frame's command signals to the plants that take them (once)."""
        by_plant: dict[str, tuple[Plant, dict[str, float]]] = {}
        for name, v in values.items():
            plant = self.commander.get(name)
            if plant is not None:
                by_plant.setdefault(plant.name, (plant, {}))[1][name] = float(v)
        for plant, given in by_plant.values():
            plant.command(given, self.t)

    def set_safe(self, safe: bool) -> None:
        """Put every plant in its safe state, or take it out (:meth:`Plant.set_safe`)."""
        if safe != self.safe:
            self.safe = safe
            for plant in self.plants:
                plant.set_safe(safe)

    def step(self) -> None:
        """Advance every plant that is due by one step of ``dt``."""
        self.k += 1
        t = self.k * self.dt
        for plant, every in zip(self.plants, self._every):
            if self.k % every == 0:
                plant.step(t, self._inputs(plant))
                self.signals.update(plant.output())

    def run(self, seconds: float) -> None:
        """Step for ``seconds`` of simulation time."""
        for _ in range(round(seconds / self.dt)):
            self.step()

    def missing(self, names: Iterable[str]) -> list[str]:
        """The names among ``names`` that no plant produces."""
        return [n for n in names if n not in self.producer]

    def __getitem__(self, signal: str) -> float:
        return self.signals[signal]
