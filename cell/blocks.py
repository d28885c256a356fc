"""The one interface every runtime block shares.

Native filters, observers, controllers and compiled scripts all look alike to the
runtime: named input channels, named output channels, their own state, a rate
(``FAS``/``MED``/``SLO``) and ``step(t, inputs) -> outputs`` once per tick of that rate.
The base class validates tunable parameters; subclasses fill ``_step`` and ``_apply``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

from .errors import ParamError

RATE_NAMES = ("FAS", "MED", "SLO")


@dataclass(frozen=True)
class Param:
    """A tunable parameter: its type and the open or closed bounds it must respect."""

    name: str
    type: type  # float or int
    doc: str
    gt: float | None = None
    ge: float | None = None
    le: float | None = None

    def check(self, value: Any) -> float | int:
        """Return ``value`` converted to the parameter's type, or raise :class:`ParamError`."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParamError(self.name, f"must be a number, got {type(value).__name__} {value!r}")
        if self.type is int:
            if isinstance(value, float):
                if not math.isfinite(value) or value != int(value):
                    raise ParamError(self.name, f"must be a whole number, got {value!r}")
            value = int(value)
        else:
            value = float(value)
            if not math.isfinite(value):
                raise ParamError(self.name, f"must be finite, got {value!r}")
        if self.gt is not None and not value > self.gt:
            raise ParamError(self.name, f"must be > {self.gt:g}, got {value!r}")
        if self.ge is not None and not value >= self.ge:
            raise ParamError(self.name, f"must be >= {self.ge:g}, got {value!r}")
        if self.le is not None and not value <= self.le:
            raise ParamError(self.name, f"must be <= {self.le:g}, got {value!r}")
        return value


class Block:
    """Base class of everything the runtime steps.

    Parameters
    ----------
    name:
        Unique block name (for native filters, the name of its output channel).
    inputs, outputs:
        Channel names read and written.
    rate:
        ``"FAS"``, ``"MED"`` or ``"SLO"``.
    """

    kind: ClassVar[str] = "block"
    family: ClassVar[str] = "block"
    PARAMS: ClassVar[dict[str, Param]] = {}
    #: whether the block's DBC outputs go onto the bus (a disabled controller keeps off it)
    on_bus: bool = True
    #: an output without a DBC unit takes the unit of the block's single input (filters)
    keeps_input_unit: ClassVar[bool] = False
    #: parameters that are saved but not restored at start-up (a controller starts disabled)
    VOLATILE: ClassVar[tuple[str, ...]] = ()

    def __init__(
        self, name: str, inputs: list[str], outputs: list[str], rate: str | tuple[str, ...] = "MED"
    ) -> None:
        rates = (rate,) if isinstance(rate, str) else tuple(rate)
        for r in rates:
            if r not in RATE_NAMES:
                raise ParamError("rate", f"must be one of {', '.join(RATE_NAMES)}, got {r!r}")
        if not rates:
            raise ParamError("rate", "a block needs at least one rate")
        self.name = name
        self.inputs = list(inputs)
        self.outputs = list(outputs)
        #: the tasks whose ticks step this block; a multi-rate block (a script whose
        #: statements run at different intervals) is stepped once per tick of any of them
        self.rates = rates
        #: output -> reason, for outputs the last step could not compute (returned as NaN)
        self.errors: dict[str, str] = {}

    @property
    def rate(self) -> str:
        return self.rates[0]

    # -- parameters -----------------------------------------------------------------
    def params(self) -> dict[str, Any]:
        return {p: getattr(self, p) for p in self.PARAMS}

    def validate(self, changes: dict[str, Any]) -> dict[str, Any]:
        """Check a parameter change as a whole; raise :class:`ParamError` on the first bad field."""
        if not isinstance(changes, dict):
            raise ParamError("body", f"must be an object of parameters, got {type(changes).__name__}")
        if not changes:
            raise ParamError("body", f"names no parameter; {self.kind} {self.name} takes: {self._known()}")
        checked = {}
        for key, value in changes.items():
            spec = self.PARAMS.get(key)
            if spec is None:
                raise ParamError(
                    key, f"is not a parameter of {self.kind} {self.name}; it takes: {self._known()}"
                )
            checked[key] = spec.check(value)
        return checked

    def set_params(self, changes: dict[str, Any]) -> dict[str, Any]:
        """Validate then apply all changes at once; nothing changes if any field is bad."""
        checked = self.validate(changes)
        self._apply(checked)
        return self.params()

    def _apply(self, checked: dict[str, Any]) -> None:
        for key, value in checked.items():
            setattr(self, key, value)

    def _known(self) -> str:
        return ", ".join(self.PARAMS) or "nothing"

    # -- stepping --------------------------------------------------------------------
    def step(
        self, t: float, inputs: dict[str, float], ticking: frozenset[str] | None = None
    ) -> dict[str, float]:
        """Advance one tick at bus time ``t`` with the inputs' latest values.

        ``ticking`` names the tasks (``FAS``/``MED``/``SLO``) that tick at ``t``; a
        single-rate block can ignore it. Raise :class:`ArithmeticError` (or return a
        non-finite value) to mark the outputs invalid for this tick.
        """
        self.ticking = ticking if ticking is not None else frozenset(self.rates)
        return self._step(t, inputs)

    def _step(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        raise NotImplementedError

    def state(self) -> dict[str, Any]:
        return {}

    def describe(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "kind": self.kind,
            "family": self.family,
            "rate": self.rate,
            "rates": list(self.rates),
            "inputs": self.inputs,
            "outputs": self.outputs,
            "params": self.params(),
            "state": self.state(),
        }
