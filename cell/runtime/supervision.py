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
with the DBC's value names). It is reset in two steps (DBC ``ENGINE_CMD``, in
``cell_commands.dbc``): :func:`request_reset` sends a request carrying a fresh random
challenge, :func:`confirm_reset` a confirm carrying that challenge; the simulator clears the
trip only on a confirm matching a request of the last 2 s, and only when the trip's cause has
cleared (``RESET_STATE`` tells what it did). ``POST /engine/reset`` and
``POST /engine/reset/confirm`` are the two steps; ``testcell scenario engine_reset_req=N``
then ``engine_reset_confirm=N`` too.
"""

from __future__ import annotations

import time
import secrets
from typing import Any

from cell.runtime.channels import OK
from cell.core.errors import ConfigError, ParamError
from cell.runtime.scheduler import Runtime

WAITING, HEALTHY, DEGRADED, FAILED = "waiting", "ok", "degraded", "failed"

#: Thresholds past which ``/health`` is degraded. ``lost_per_min``: frames lost over the
#: last minute (more than this many); ``lag_s``: seconds the runtime's bus time is behind the
#: wall clock's estimate; ``overruns_per_min``: tick overruns over the last minute of bus time.
LIMITS = {"lost_per_min": 0, "lag_s": 0.5, "overruns_per_min": 6}

#: The window of "recent" stalls and dropped stale outputs, wall seconds.
RECENT_S = 60.0

#: The signals the trip is read from and the reset is written to.
STATE_SIGNAL, REASON_SIGNAL = "ENGINE_STATE", "TRIP_REASON"
#: The two steps of a reset (DBC ``ENGINE_CMD``).
REQUEST_SIGNAL, CONFIRM_SIGNAL = "ENGINE_RESET_REQ", "ENGINE_RESET_CONFIRM"
#: The simulator's window from request to confirm, s (``ExhaustParams.reset_window``).
RESET_WINDOW_S = 2.0


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


def _send_reset_step(runtime: Runtime, request: int, confirm: int, at: float) -> None:
    db = runtime.db
    if REQUEST_SIGNAL not in db.signals or CONFIRM_SIGNAL not in db.signals:
        raise ConfigError(f"no DBC file defines {REQUEST_SIGNAL} and {CONFIRM_SIGNAL}: this "
                          "cell cannot reset a trip")
    message = db.signals[REQUEST_SIGNAL].message
    runtime.outbox.append(db.encode(message, {REQUEST_SIGNAL: request, CONFIRM_SIGNAL: confirm},
                                    at))


def request_reset(runtime: Runtime, at: float | None = None) -> int:
    """Step one: queue a reset request with a fresh random challenge; returns the challenge.

    ``at`` is the bus time stamped on the frame (default: the runtime's). A newer request
    replaces an older one that was not confirmed.
    """
    challenge = secrets.randbelow(65535) + 1  # 1..65535: 0 means "no request"
    with runtime.lock:
        now = (runtime.now or 0.0) if at is None else at
        _send_reset_step(runtime, challenge, 0, now)
        runtime.extra_state["reset_challenge"] = (challenge, now)
    return challenge


def confirm_reset(runtime: Runtime, challenge: Any, at: float | None = None) -> int:
    """Step two: queue the confirm of the pending request; returns the challenge sent.

    Raises
    ------
    ParamError
        ``challenge`` is not the pending request's (none pending, another value, or not a
        whole number); nothing is sent and the pending request stays.
    """
    if isinstance(challenge, bool) or not isinstance(challenge, int):
        raise ParamError("challenge", f"must be the whole number POST /engine/reset returned, "
                                      f"got {challenge!r}")
    with runtime.lock:
        pending = runtime.extra_state.get("reset_challenge")
        if pending is None:
            raise ParamError("challenge", "no reset request is pending: POST /engine/reset first")
        if challenge != pending[0]:
            raise ParamError("challenge", f"{challenge} is not the pending request's challenge")
        now = (runtime.now or 0.0) if at is None else at
        _send_reset_step(runtime, 0, challenge, now)
        del runtime.extra_state["reset_challenge"]
    return challenge


__all__ = ["DEGRADED", "FAILED", "HEALTHY", "LIMITS", "WAITING", "assess", "confirm_reset",
           "request_reset", "trip", "validity"]
