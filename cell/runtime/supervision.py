"""What ``/health`` says about a running cell: degraded states, the engine's trip, its reset.

A cell is ``waiting`` before its first frame, ``ok`` while frames flow and nothing is wrong,
``failed`` with the reason while its live loop has stopped, is restarting or is stalled (its
channels then all read ``stale``), and ``degraded`` with the reasons when the bus falls
silent, the bus connection is lost, the engine protection has tripped the engine, or one of
the run's validity counts passes its threshold (:data:`LIMITS`): frames lost over the last
minute (missed cycles of cyclic messages, datagrams the kernel dropped), the runtime's lag
behind the wall clock, tick overruns per minute, a block that is faulted now, a stall of the
loop or stale outputs dropped after one in the last minute. The trip is read
from the bus like everything else (``ENGINE_STATE`` = TRIPPED and ``TRIP_REASON``, decoded
with the DBC's value names); it is reset by a new value of ``ENGINE_RESET`` (DBC
``cell_commands.dbc``), which ``POST /engine/reset`` sends and ``testcell scenario`` can send.
"""

from __future__ import annotations

import time
from typing import Any

from cell.runtime.channels import OK
from cell.core.errors import ConfigError
from cell.runtime.scheduler import Runtime

WAITING, HEALTHY, DEGRADED, FAILED = "waiting", "ok", "degraded", "failed"

#: Thresholds past which ``/health`` is degraded. ``lost_per_min``: frames lost over the
#: last minute (more than this many); ``lag_s``: seconds the runtime's bus time is behind the
#: wall clock's estimate; ``overruns_per_min``: tick overruns over the last minute of bus time.
LIMITS = {"lost_per_min": 0, "lag_s": 0.5, "overruns_per_min": 6}

#: The window of "recent" stalls and dropped stale outputs, wall seconds.
RECENT_S = 60.0

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
    failure = None
    if live is not None:
        problem = getattr(live, "problem", None)
        failure = problem() if callable(problem) else (
            None if live.running else "the runtime loop has stopped")
        if failure:
            reasons.append(failure)
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
        reasons.extend(validity(h, live))
        status = DEGRADED if reasons else HEALTHY
    if failure:
        status = FAILED
    return {"status": status, "reasons": reasons, "trip": tripped}


def validity(h: dict[str, Any], live: Any = None) -> list[str]:
    """The reasons a run's validity counts give for ``degraded`` (see :data:`LIMITS`)."""
    reasons = []
    lost = h["frames_lost"]
    missed = lost["missed_cycles_last_min"]
    if missed > LIMITS["lost_per_min"]:
        worst = sorted(lost["by_message"].items(), key=lambda kv: -kv[1])[:3]
        reasons.append(f"frames lost: {missed} missed cycles in the last minute "
                       f"({', '.join(f'{m} {n}' for m, n in worst)} in all)")
    overruns = h["tick_overruns_per_min"]
    if overruns > LIMITS["overruns_per_min"]:
        reasons.append(f"tick overruns: {overruns} in the last minute "
                       f"(limit {LIMITS['overruns_per_min']})")
    for name, f in h["block_faults"].items():
        if f["backing_off"]:
            reasons.append(f"block {name} faulted: {f['last_reason']} "
                           f"(retry at bus time {f['retry_at']:.1f} s)")
    if live is not None and hasattr(live, "status"):
        lag = live.lag_s()
        if lag is not None and lag > LIMITS["lag_s"]:
            reasons.append(f"runtime lag: {lag:.2f} s behind the wall clock "
                           f"(limit {LIMITS['lag_s']:g} s)")
        drops = live.kernel_drops()
        recent = live.recent_kernel_drops(RECENT_S)
        if recent > LIMITS["lost_per_min"]:
            reasons.append(f"frames lost: the kernel dropped {recent} datagrams in the last "
                           f"minute ({drops} in all)")
        stall = live.last_stall
        if stall is not None and time.time() - stall[1] < RECENT_S:
            reasons.append(f"runtime loop stalled for {stall[0]:.1f} s "
                           f"{time.time() - stall[1]:.0f} s ago ({live.stalls} stalls in all)")
        dropped = live.dropped_stale_since(RECENT_S)
        if dropped:
            reasons.append(f"stale outputs dropped: {dropped} output frames older than one cycle "
                           f"in the last minute ({live.dropped_stale} in all)")
    return reasons


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


__all__ = ["DEGRADED", "FAILED", "HEALTHY", "LIMITS", "WAITING", "assess", "reset_trip", "trip",
           "validity"]
