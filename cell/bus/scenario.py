"""Scenario commands: frames that change a running simulator's plant (``testcell scenario``).

A *scenario message* is a DBC message whose sender is node ``SCENARIO`` and whose signals
are received by ``SIM``. Every such signal is a scenario *key*: its name in lower case
(``OSC`` -> ``osc``). ``testcell scenario osc=0.5`` and ``POST /scenario {"osc": 0.5}``
both encode the message that carries ``OSC`` and send it on the bus; the simulator hands
the value to the plant that consumes it (:meth:`cell.sim.simulator.Simulator.receive`),
which holds it until the next command. A signal of the message that is not given takes
its initial value (``GenSigStartValue``, else 0).

Nothing here is specific to one plant: a DBC file that adds a ``SCENARIO`` message adds
its keys. A value outside its signal's DBC range ``[minimum|maximum]`` is refused, never
clamped: a command that cannot be carried out as given is not sent.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import can
from cantools.database.can import Message, Signal

from cell.bus.dbc import CellDatabase
from cell.core.errors import ConfigError, ParamError

#: The DBC node that sends scenario commands.
SENDER = "SCENARIO"
#: The node that receives them.
RECEIVER = "SIM"


@dataclass(frozen=True)
class ScenarioKey:
    """One scenario key: the DBC signal it sets and the message that carries it."""

    key: str
    message: Message
    signal: Signal

    @property
    def initial(self) -> float:
        """The value sent when the key is not given: GenSigStartValue, else 0."""
        v = self.signal.initial
        return float(v) if v is not None else 0.0

    def describe(self) -> dict[str, Any]:
        s = self.signal
        return {"key": self.key, "signal": s.name, "message": self.message.name,
                "frame_id": self.message.frame_id, "minimum": s.minimum, "maximum": s.maximum,
                "unit": s.unit or "", "initial": self.initial,
                "comment": s.comment or ""}


def scenario_keys(db: CellDatabase) -> dict[str, ScenarioKey]:
    """Every scenario key of the DBC files, sorted by name."""
    keys: dict[str, ScenarioKey] = {}
    for m in db.messages:
        if SENDER not in (m.senders or []):
            continue
        given = set(db.payload_signals(m))  # not the E2E counter and CRC: encode fills them
        for s in m.signals:
            if RECEIVER in (s.receivers or []) and s.name in given:
                keys[s.name.lower()] = ScenarioKey(s.name.lower(), m, s)
    return dict(sorted(keys.items()))


def parse_assignments(items: Sequence[str]) -> dict[str, str]:
    """``["osc=0.5", ...]`` -> ``{"osc": "0.5"}``; a malformed item is named."""
    out: dict[str, str] = {}
    for i, item in enumerate(items, 1):
        key, sep, value = item.partition("=")
        key, value = key.strip(), value.strip()
        if not sep or not key or not value:
            raise ConfigError(f"argument {i} {item!r}: expected KEY=VALUE (e.g. osc=0.5)")
        if key.lower() in out:
            raise ConfigError(f"argument {i} {item!r}: {key} is given twice")
        out[key.lower()] = value
    return out


def _value(k: ScenarioKey, raw: Any) -> float:
    """The physical value of one key, checked against its DBC range."""
    s = k.signal
    if isinstance(raw, str):
        text = raw.strip()
        choices = {str(name).lower(): num for num, name in (s.choices or {}).items()}
        if text.lower() in choices:
            return float(choices[text.lower()])
        try:
            v = float(text)
        except ValueError:
            named = f" or one of {', '.join(map(str, s.choices.values()))}" if s.choices else ""
            raise ParamError(k.key, f"must be a number{named}, got {raw!r}") from None
    elif isinstance(raw, bool) or not isinstance(raw, (int, float)):
        raise ParamError(k.key, f"must be a number, got {type(raw).__name__} {raw!r}")
    else:
        v = float(raw)
    if not math.isfinite(v):
        raise ParamError(k.key, f"must be finite, got {v}")
    lo, hi = s.minimum, s.maximum
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        unit = f" {s.unit}" if s.unit else ""
        raise ParamError(k.key, f"must be within [{lo:g}, {hi:g}]{unit} (the DBC range of "
                                f"{s.name} in {k.message.name}), got {v:g}")
    return v


def scenario_frames(db: CellDatabase, values: Mapping[str, Any], timestamp: float = 0.0
                    ) -> list[can.Message]:
    """The frames that carry a scenario command, one per scenario message touched.

    Parameters
    ----------
    db:
        The DBC files.
    values:
        Key (case-insensitive) -> value: a number, or a text holding one (or a value name
        of the signal's ``VAL_`` table).
    timestamp:
        Bus time stamped on the frames.

    Raises
    ------
    ParamError
        No key given, an unknown key (the message lists the known ones), or a value that
        is not a number or lies outside its signal's DBC range. Nothing is encoded then.
    """
    keys = scenario_keys(db)
    known = ", ".join(keys) or "none (no DBC message is sent by SCENARIO to SIM)"
    if not isinstance(values, Mapping) or not values:
        raise ParamError("body", f"names no scenario key; known: {known}")
    grouped: dict[str, dict[str, float]] = {}
    for key, raw in values.items():
        k = keys.get(str(key).strip().lower())
        if k is None:
            raise ParamError(str(key), f"is not a scenario key; known: {known}")
        grouped.setdefault(k.message.name, {})[k.signal.name] = _value(k, raw)
    frames = []
    for name, given in grouped.items():
        message = db.message(name)
        full = {}
        for s in (message.get_signal_by_name(n) for n in db.payload_signals(message)):
            if s.name in given:
                full[s.name] = given[s.name]
            else:
                full[s.name] = float(s.initial) if s.initial is not None else 0.0
        frames.append(db.encode(name, full, timestamp))
    return frames


def describe_frames(db: CellDatabase, frames: Sequence[can.Message]) -> list[dict[str, Any]]:
    """What each frame carries, decoded back (for the command's answer)."""
    out = []
    for msg in frames:
        message, values = db.decode(msg)
        given = db.payload_signals(message)  # not the E2E counter and CRC
        out.append({"message": message.name, "frame_id": message.frame_id,
                    "signals": {k: values[k] for k in given}})
    return out


__all__ = ["RECEIVER", "SENDER", "ScenarioKey", "describe_frames", "parse_assignments",
           "scenario_frames", "scenario_keys"]
