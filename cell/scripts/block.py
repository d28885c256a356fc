"""The runtime block every compiled script becomes.

A :class:`ScriptBlock` looks to the runtime like any native block (:class:`cell.runtime.blocks.Block`):
named inputs, named outputs, its own state and ``step(t, inputs, ticking)``. Its state is
a flat list of float slots that the compiled code of its dialect reads and writes.

Runtime errors are contained per statement (seed 004 scripts keep running in the cell
when one formula misbehaves): a statement that divides by zero, leaves a function's
domain or yields NaN/inf keeps its previous value, and every statement using it later in
the same tick is skipped too. Outputs so affected are returned as NaN with the reason in
``errors``; ``errors`` is rebuilt at every step, so the next good tick clears it.
"""

from __future__ import annotations

import collections
import math
from typing import Any, ClassVar

from cell.runtime.blocks import Block
from cell.core.errors import ParamError
from cell.scripts.codegen import reason

#: Default FAS/MED/SLO rates in Hz (seed 004: 50, 10 and 1 Hz).
DEFAULT_RATES_HZ = {"FAS": 50.0, "MED": 10.0, "SLO": 1.0}

_NAN = math.nan


def rates_hz(rates: Any = None) -> dict[str, float]:
    """FAS/MED/SLO rates in Hz from ``None``, a mapping or an object with those attributes."""
    out = dict(DEFAULT_RATES_HZ)
    if rates is None:
        return out
    for name, default in out.items():
        if isinstance(rates, dict):
            value = rates.get(name, default)
        else:
            value = getattr(rates, name, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
            math.isfinite(value) and value > 0
        ):
            raise ParamError(f"rates.{name}", f"must be a positive number of Hz, got {value!r}")
        out[name] = float(value)
    return out


class ScriptBlock(Block):
    """Base of the compiled script blocks (family ``script``).

    Attributes
    ----------
    source:
        The script text as loaded.
    dialect:
        ``"fdv"`` or ``"cyflex"``.
    errors:
        Output -> reason for the outputs the last step could not compute.
    error_counts:
        Runtime errors counted per variable (outputs and locals) since load.
    units:
        Output -> unit text (CyFlex labels declare units; ``.fdv`` outputs have none).
    """

    family: ClassVar[str] = "script"
    dialect: ClassVar[str] = "script"

    def dependencies(self) -> dict[str, set[str]]:
        """Variable -> the names its value is computed from (the script's statements)."""
        return {}

    def sources_of(self, out: str) -> set[str] | None:
        """The input channels ``out`` depends on, through the script's locals and labels."""
        graph = self.dependencies()
        inputs, seen, todo, found = set(self.inputs), set(), [out], set()
        while todo:
            name = todo.pop()
            if name in seen:
                continue
            seen.add(name)
            if name in inputs:
                found.add(name)
            todo.extend(graph.get(name, ()))
        return found

    def __init__(self, name: str, inputs: list[str], outputs: list[str], rate: Any) -> None:
        super().__init__(name, inputs, outputs, rate)
        self.source = ""
        self.error_counts: collections.Counter[str] = collections.Counter()
        #: every variable (not only outputs) that failed at the last step, with its reason
        self.last_errors: dict[str, str] = {}
        self.units: dict[str, str] = {}
        self.steps = 0
        self._S: list[float] = []
        #: name -> slot of each state variable (locals, labels, statistics)
        self._slot: dict[str, int] = {}
        #: constant name -> slot of its value
        self._const_slot: dict[str, int] = {}
        #: variable name -> text of its definition, compared by :meth:`adopt_state`
        self._keys: dict[str, Any] = {}
        self._outputs_set = frozenset()

    # -- runtime errors ---------------------------------------------------------------
    def _finish(self, out: dict[str, float], bad: dict[str, str]) -> dict[str, float]:
        """Count the step; mark the outputs that failed, or clear last tick's marks."""
        self.steps += 1
        if bad:
            self._mark(out, bad)
        elif self.errors:
            self.errors = {}
        return out

    def _mark(self, out: dict[str, float], bad: dict[str, str]) -> None:
        errors: dict[str, str] = {}
        outputs = self._outputs_set
        for name, why in bad.items():
            self.error_counts[name] += 1
            if name in outputs:
                out[name] = _NAN
                errors[name] = why
        self.errors = errors
        self.last_errors = dict(bad)

    # -- constants -------------------------------------------------------------------
    def constants(self) -> dict[str, float]:
        """The script's constants and their current values."""
        S = self._S
        return {name: S[k] for name, k in self._const_slot.items()}

    def validate_constants(self, changes: Any) -> dict[str, float]:
        """Check a constant change as a whole; raise :class:`ParamError` naming the bad field."""
        known = ", ".join(self._const_slot) or "none"
        if not isinstance(changes, dict):
            raise ParamError("constants", f"must be an object of name: value, got "
                             f"{type(changes).__name__}")
        if not changes:
            raise ParamError("constants", f"names no constant; {self.name} has: {known}")
        checked: dict[str, float] = {}
        for key, value in changes.items():
            if key not in self._const_slot:
                raise ParamError(str(key), f"is not a constant of script {self.name}; "
                                 f"its constants are: {known}")
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ParamError(key, f"must be a number, got {type(value).__name__} {value!r}")
            value = float(value)
            if not math.isfinite(value):
                raise ParamError(key, f"must be finite, got {value!r}")
            checked[key] = value
        return checked

    def set_constants(self, changes: dict[str, float]) -> dict[str, float]:
        """Validate then apply all changes; they take effect at the next step.

        Nothing changes if any name or value is refused (:class:`ParamError`).
        """
        checked = self.validate_constants(changes)
        for key, value in checked.items():
            self._S[self._const_slot[key]] = value
        self._constants_changed(checked)
        return self.constants()

    def _constants_changed(self, checked: dict[str, float]) -> None:
        """Hook for dialects that mirror a constant elsewhere."""

    # Block's parameter API routes to the constants, so scripts tune like native filters.
    def params(self) -> dict[str, Any]:
        return self.constants()

    def validate(self, changes: dict[str, Any]) -> dict[str, Any]:
        return self.validate_constants(changes)

    def set_params(self, changes: dict[str, Any]) -> dict[str, Any]:
        return self.set_constants(changes)

    # -- hot swap --------------------------------------------------------------------
    def adopt_state(self, old: Block) -> list[str]:
        """Take over the state of ``old`` for every variable whose definition is unchanged.

        A variable (output, local, label, constant) keeps its value when ``old`` is a
        script of the same dialect defining it with the same formula text (compared
        after parsing, so spacing and comments do not matter). Returns the adopted names.
        """
        if not isinstance(old, ScriptBlock) or old.dialect != self.dialect:
            return []
        adopted: list[str] = []
        for name, key in self._keys.items():
            if old._keys.get(name) == key and name in old._slot and name in self._slot:
                self._S[self._slot[name]] = old._S[old._slot[name]]
                adopted.append(name)
        for name, k in self._const_slot.items():
            if name in adopted and name in old._const_slot:
                self._S[k] = old._S[old._const_slot[name]]
        adopted.extend(self._adopt_more(old))
        return adopted

    def _adopt_more(self, old: ScriptBlock) -> list[str]:
        return []

    # -- views -----------------------------------------------------------------------
    def values(self) -> dict[str, float]:
        """Current value of every state variable."""
        S = self._S
        return {name: S[k] for name, k in self._slot.items()}

    def state(self) -> dict[str, Any]:
        return {"steps": self.steps, "values": self.values()}

    def describe(self) -> dict[str, Any]:
        out = super().describe()
        out.update({
            "dialect": self.dialect,
            "source": self.source,
            "constants": self.constants(),
            "units": dict(self.units),
            "errors": dict(self.errors),
            "error_counts": dict(self.error_counts),
        })
        return out

    def _error_helpers(self, table: list[tuple[str, int, int]]) -> dict[str, Any]:
        """``_why``/``_dep`` for generated code: the reason a statement failed, by its index
        in ``table`` (target, line, column), and the reason a statement reading a failed
        value is skipped."""

        def why(k: int, exc: BaseException) -> str:
            target, line, col = table[k]
            return self.why(target, line, col, exc)

        def dep(bad: dict[str, str], reads: tuple[str, ...]) -> str:
            for r in reads:
                if r in bad:
                    return bad[r]
            return "depends on an invalid value"  # pragma: no cover

        return {"_why": why, "_dep": dep}

    @staticmethod
    def why(target: str, line: int, column: int, exc: BaseException) -> str:
        return f"{target} (line {line}:{column}): {reason(exc)}"
