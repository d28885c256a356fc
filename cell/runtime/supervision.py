"""What ``/health`` says about a running cell: degraded states, the engine's trip, its reset.

A cell is ``waiting`` before its first frame, ``ok`` while frames flow and nothing is wrong,
and ``degraded`` with the reasons when the bus falls silent, the bus connection is lost,
the live loop has stopped, or the engine protection has tripped the engine. The trip is read
from the bus like everything else (``ENGINE_STATE`` = TRIPPED and ``TRIP_REASON``, decoded
with the DBC's value names); it is reset by a new value of ``ENGINE_RESET`` (DBC
``cell_commands.dbc``), which ``POST /engine/reset`` sends and ``testcell scenario`` can send.
"""

from __future__ import annotations

from typing import Any

from cell.runtime.channels import OK
from cell.core.errors import ConfigError
from cell.runtime.scheduler import Runtime

WAITING, HEALTHY, DEGRADED = "waiting", "ok", "degraded"

#: The signals the trip is read from and the reset is written to.
STATE_SIGNAL, REASON_SIGNAL, RESET_SIGNAL = "ENGINE_STATE", "TRIP_REASON", "ENGINE_RESET"


def _label(runtime: Runtime, signal: str, value: float) -> str:
    """A signal value's DBC name (``VAL_``), else the number."""
    info = runtime.db.signals.get(signal)
    if info is not None:
        sig = runtime.db.message(info.message).get_signal_by_name(signal)
        choices = sig.choices or {}
        name = choices.get(int(value))
        if name is not None:
            return str(name)
    return f"{value:g}"


def trip(runtime: Runtime) -> dict[str, Any] | None:
    """The engine's trip as the bus shows it: ``None`` when running (or unknown), else
    ``{"state", "reason", "since"}`` with ``since`` the bus time of the first frame saying so."""
    with runtime.lock:
        chans = runtime.channels
        state = chans.get(STATE_SIGNAL)
        if state is None or state.value is None or state.status != OK:
            return None
        label = _label(runtime, STATE_SIGNAL, state.value)
        if label != "TRIPPED":
            runtime.extra_state.pop("trip_since", None)
            return None
        since = runtime.extra_state.setdefault("trip_since", state.t)
        reason = chans.get(REASON_SIGNAL)
        why = _label(runtime, REASON_SIGNAL, reason.value) if reason and reason.value is not None \
            else "unknown"
        return {"state": label, "reason": why, "since": since}


def assess(runtime: Runtime, live: Any = None) -> dict[str, Any]:
    """Status and reasons of the cell (see the module notes) with the trip, if any."""
    h = runtime.health()
    reasons: list[str] = []
    if live is not None:
        if not live.running:
            reasons.append("the runtime loop has stopped")
        bus_problem = getattr(live, "bus_problem", None)
        if bus_problem:
            reasons.append(bus_problem)
    tripped = trip(runtime)
    if h["frames"] == 0:
        status = WAITING
        reasons.insert(0, "no frame received yet")
    else:
        if h["frames_per_s"] == 0.0:
            last, now = h["last_frame_time"], h["bus_time"]
            silent = f" for {now - last:.1f} s" if last is not None and now is not None else ""
            reasons.append(f"bus silent: 0 frames/s{silent} (last frame at bus time {last:.3f} s)"
                           if last is not None else "bus silent: 0 frames/s")
        reasons += runtime.senders.reasons(h["bus_time"])  # a forger on the bus
        if tripped is not None:
            reasons.append(f"engine tripped: {tripped['reason']} (since bus time "
                           f"{tripped['since']:.1f} s); reset with POST /engine/reset")
        status = DEGRADED if reasons else HEALTHY
    return {"status": status, "reasons": reasons, "trip": tripped}


def reset_trip(runtime: Runtime) -> int:
    """Queue an ``ENGINE_RESET`` frame with a new counter value; returns the value sent.

    The value is one more than the newest seen on the bus (a ``testcell scenario`` command
    is seen there too) or sent by this runtime, so the simulator always sees a change.
    """
    db = runtime.db
    if RESET_SIGNAL not in db.signals:
        raise ConfigError(f"no DBC file defines {RESET_SIGNAL}: this cell cannot reset a trip")
    with runtime.lock:
        seen = runtime.channels.get(RESET_SIGNAL)
        last, at = runtime.extra_state.get("reset_sent", (0, -float("inf")))
        if seen is not None and seen.value is not None and seen.t is not None and seen.t >= at:
            last = int(seen.value)  # someone else's command is newer than ours
        value = last % 255 + 1  # 1..255: never the initial 0
        runtime.extra_state["reset_sent"] = (value, runtime.now or 0.0)
        msg = db.encode(db.signals[RESET_SIGNAL].message, {RESET_SIGNAL: value}, runtime.now or 0.0)
        runtime.outbox.append(msg)
        return value


__all__ = ["DEGRADED", "HEALTHY", "WAITING", "assess", "reset_trip", "trip"]
