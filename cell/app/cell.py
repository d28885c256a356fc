"""What one running cell is made of, and what the HTTP service may ask of it.

:class:`Cell` is the service's façade: its runtime, the bus it runs on, the settings it was
started with, its scripts, its tuning store and its live loop. Every question the service
asks (channels, their history, blocks, the health counts) and every command it gives
(tuning, frames for the bus, a scenario, an engine reset) goes through a method that takes
the runtime's lock itself, so the service never holds the lock nor reads the runtime's parts.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import can

from cell.app.live import LiveCell
from cell.app.tuning import TuningStore
from cell.bus.scenario import describe_frames, scenario_frames, scenario_keys
from cell.core import registry
from cell.core.errors import ConfigError, UnknownBlockError
from cell.core.settings import Settings
from cell.runtime import supervision
from cell.runtime.blocks import Block
from cell.runtime.channels import STALE
from cell.runtime.scheduler import Runtime
from cell.runtime.store import Reading
from cell.scripts.manager import ScriptManager

log = logging.getLogger(__name__)


@dataclass
class Cell:
    """Everything the HTTP service needs to show, tune and command a cell.

    ``bus`` names the bus (``virtual:x``, ``socketcan:vcan0``, ``none``); ``settings`` are
    those the cell was started with (``None`` when ``testcell up`` did not start it);
    ``scripts`` is its script manager (``None``: the cell runs no scripts).
    """

    runtime: Runtime
    bus: str = "none"
    settings: Settings | None = None
    scripts: ScriptManager | None = None
    tuning: TuningStore | None = None
    live: LiveCell | None = None
    #: block -> what was applied but could not be saved (a safety action on a full or
    #: read-only disk), shown in :meth:`health` until the next save succeeds
    unsaved: dict[str, str] = field(default_factory=dict)
    #: the last snapshot, readings and health answered, for readers while a step hangs
    _seen: dict[str, Any] = field(default_factory=lambda: {"snapshot": [], "readings": {},
                                                           "health": None},
                                  init=False, repr=False)

    # -- bus time ---------------------------------------------------------------------
    @property
    def now(self) -> float | None:
        """The runtime's bus time (``None`` before the first frame)."""
        with self.runtime.lock:
            return self.runtime.now

    def bus_time(self) -> float | None:
        """The bus time now: the live loop's estimate while it runs, else the runtime's."""
        with self.runtime.lock:
            now = self.runtime.now
            if self.live is not None:
                est = self.live.estimated_bus_time()
                now = est if est is not None else now
            return now

    def period(self, task: str) -> float:
        """Seconds between two ticks of a task (``FAS``, ``MED`` or ``SLO``)."""
        return self.runtime.rates.period(task)

    # -- channels ---------------------------------------------------------------------
    def loop_problem(self) -> str | None:
        """Why the live loop's values cannot be trusted now (stopped, restarting, stalled),
        else ``None``; while there is one, every channel reads ``stale`` with it."""
        return self.live.problem() if self.live is not None else None

    @contextlib.contextmanager
    def _held(self) -> Iterator[bool]:
        """Hold the runtime's lock; yields ``False`` (not held) when a live loop has held it
        longer than its stall limit (a step that hangs), so readers answer from what they
        saw last, all ``stale``, instead of hanging with the loop."""
        lock = self.runtime.lock
        if self.live is None:
            got = lock.acquire()
        else:  # once the loop is known to be stalled, no reader waits for it
            got = lock.acquire(timeout=0.0 if self.live.problem() else max(0.05, self.live.stall_s))
        try:
            yield got
        finally:
            if got:
                lock.release()

    def _stuck(self) -> str:
        return self.loop_problem() or "the runtime loop is stuck in a step (its lock is held)"

    def snapshot(self) -> list[dict[str, Any]]:
        """Every channel as seen now, by name: value, unit, bus time, status and source."""
        with self._held() as held:
            if not held:
                problem = self._stuck()
                return [{**s, "status": STALE, "reason": problem} for s in self._seen["snapshot"]]
            snaps = self.runtime.snapshot()
            self._seen["snapshot"] = snaps
        problem = self.loop_problem()
        if problem:
            for snap in snaps:
                snap["status"], snap["reason"] = STALE, problem
        return snaps

    def channel(self, name: str) -> dict[str, Any]:
        """One channel as seen now; :class:`~cell.core.errors.UnknownBlockError` if none."""
        rt = self.runtime
        with self._held() as held:
            if not held:
                for seen in self._seen["snapshot"]:
                    if seen["name"] == name:
                        return {**seen, "status": STALE, "reason": self._stuck()}
                raise UnknownBlockError("channel", name, [s["name"] for s in self._seen["snapshot"]])
            snap = rt.channel(name).snapshot(rt.now)
        problem = self.loop_problem()
        if problem:
            snap["status"], snap["reason"] = STALE, problem
        return snap

    def channel_names(self) -> list[str]:
        """The name of every channel, sorted."""
        with self.runtime.lock:
            return sorted(self.runtime.channels)

    def describe_channels(self, names: Iterable[str]) -> list[dict[str, Any]]:
        """Name, unit and source of each of ``names`` that is a channel, in that order."""
        with self.runtime.lock:
            chans = self.runtime.channels
            return [{"name": n, "unit": chans[n].unit, "source": chans[n].source}
                    for n in names if n in chans]

    def history(self, name: str, seconds: float) -> list[tuple[float, float | None, str]]:
        """``(time, value or None, status)`` of a channel at each MED tick of the last
        ``seconds`` of bus time."""
        with self._held() as held:
            if not held:  # a step hangs: the channel is stale now, its history waits
                now = self.live.estimated_bus_time() if self.live is not None else None
                return [] if now is None else [(now, None, STALE)]
            points = self.runtime.history(name, seconds)
        problem = self.loop_problem()
        now = self.bus_time()
        if problem and now is not None and (not points or now > points[-1][0]):
            points.append((now, None, STALE))  # the loop stopped: the channel is stale now
        return points

    def readings(self, names: Iterable[str] | None = None,
                 at: float | None = None) -> tuple[float | None, dict[str, Reading]]:
        """The bus time ``at`` (default: now) and, as seen then, the value, status and bus
        time of the value of every channel, or of those of ``names`` that exist."""
        rt = self.runtime
        with self._held() as held:
            if not held:
                seen = self._seen["readings"]
                wanted = seen if names is None else {n: seen[n] for n in names if n in seen}
                now = self.live.estimated_bus_time() if self.live is not None else None
                return now, {n: (v, STALE, vt) for n, (v, _, vt) in wanted.items()}
            t = rt.now if at is None else at
            readings = rt.readings(names, at=t)
            if names is None:
                self._seen["readings"] = readings
        if self.loop_problem():
            readings = {n: (v, STALE, vt) for n, (v, _, vt) in readings.items()}
        return t, readings

    def on_tick(self, listener: Callable[[float], None]) -> None:
        """Call ``listener(t)`` after every MED tick, in the runtime's thread, lock held."""
        with self.runtime.lock:
            self.runtime.tick_listeners.append(listener)

    def on_stall(self, listener: Callable[[float], None]) -> None:
        """Call ``listener(t)`` once per MED period, with the bus time now, while the live
        loop is stopped, restarting or stalled (no tick comes then); nothing offline."""
        if self.live is not None:
            self.live.stall_listeners.append(listener)

    # -- blocks -----------------------------------------------------------------------
    def families(self) -> list[dict[str, Any]]:
        """Every registered block family: its name, its HTTP section, what its blocks are,
        example parameter changes, and the names of this cell's blocks of that family."""
        with self.runtime.lock:
            return [{"name": fam.name, "section": fam.section, "description": fam.description,
                     "examples": [dict(e) for e in fam.examples], "blocks": self.names(fam.name)}
                    for fam in registry.FAMILIES.values()]

    def names(self, family: str) -> list[str]:
        """The names of the cell's blocks of ``family``, in the order they run."""
        with self.runtime.lock:
            return [b.name for b in self.runtime.blocks.values() if b.family == family]

    def find(self, family: str, name: str) -> Block:
        """The block ``name`` of ``family``; :class:`~cell.core.errors.UnknownBlockError`
        naming the family's blocks if there is none."""
        return self.runtime.block(name, family)

    def block(self, family: str, name: str) -> dict[str, Any]:
        """A block of ``family`` as the API shows it: kind, rates, inputs, outputs,
        parameters and state."""
        with self.runtime.lock:
            return self.find(family, name).describe()

    def blocks(self, family: str) -> list[dict[str, Any]]:
        """Every block of ``family``, described as :meth:`block` does."""
        with self.runtime.lock:
            return [self.runtime.block(n).describe() for n in self.names(family)]

    def tune(self, family: str, name: str, changes: dict[str, Any],
             warnings: list[str] | None = None) -> dict[str, Any]:
        """Apply a parameter change to a block of ``family`` and save it; all or nothing.

        A safety action (:meth:`~cell.runtime.blocks.Block.safe_unsaved`: a controller
        switched off) never depends on the disk: when the tuning file cannot be written it
        stays applied, the failure is logged, shown in :meth:`health` and appended to
        ``warnings``. Any other change is undone and the error raised."""
        rt = self.runtime
        with rt.lock:
            block = rt.block(name, family)
            before = block.params()
            params = rt.set_params(name, changes, family)
            if self.tuning is not None:
                try:
                    self.tuning.record(registry.FAMILIES[family].section, name, params)
                except Exception as exc:
                    if not block.safe_unsaved(changes):
                        block.set_params(before)
                        raise
                    text = f"{family} {name}: {changes} applied but not saved: {exc}"
                    log.warning("%s", text)
                    self.unsaved[name] = text
                    if warnings is not None:
                        warnings.append(text)
                else:
                    self.unsaved.clear()  # the whole file is written: nothing left unsaved
            return params

    def load_design(self, name: str, design: dict[str, Any], source: str = "design") -> None:
        """Load a design into the observer ``name`` and save it in the tuning file, so that a
        restart keeps it (all or nothing: a bad design, or one that cannot be saved, raises
        :class:`~cell.core.errors.ConfigError` naming why, and the previous one stays)."""
        from cell.app.assemble import load_design

        with self.runtime.lock:
            block = self.runtime.blocks.get(name)
            before = block.design() if callable(getattr(block, "design", None)) else None
            load_design(self.runtime, design, source, name=name)
            if self.tuning is not None:
                try:
                    self.tuning.record_design(name, design)
                except ConfigError:
                    if before is not None:  # not saved: the previous design comes back
                        load_design(self.runtime, before, "the previous design", name=name)
                    raise

    # -- commands to the bus ----------------------------------------------------------
    def send(self, frames: Iterable[can.Message]) -> None:
        """Put frames on the bus with the runtime's next outputs."""
        self.runtime.send(frames)

    def scenario_keys(self) -> list[dict[str, Any]]:
        """Every scenario key of the DBC files: the signal it sets, its range, unit and
        start value."""
        return [k.describe() for k in scenario_keys(self.runtime.db).values()]

    def send_scenario(self, values: dict[str, Any]) -> list[dict[str, Any]]:
        """Encode the scenario message(s) carrying ``values`` at the bus time now and put
        them on the bus; returns what was sent. A bad key or value raises and sends nothing."""
        rt = self.runtime
        with rt.lock:
            frames = scenario_frames(rt.db, values, self.bus_time() or 0.0)
            rt.send(frames)
        return describe_frames(rt.db, frames)

    def trip(self) -> dict[str, Any] | None:
        """The engine's trip as the bus shows it (``None``: running, or not known)."""
        return supervision.trip(self.runtime)

    def reset_trip(self) -> dict[str, Any]:
        """Step one of a trip reset: send a request with a fresh challenge (see
        :func:`cell.runtime.supervision.request_reset`); returns the challenge and the window
        within which :meth:`confirm_reset` must follow."""
        challenge = supervision.request_reset(self.runtime, self.bus_time())
        return {"challenge": challenge, "window_s": supervision.RESET_WINDOW_S}

    def confirm_reset(self, challenge: Any) -> int:
        """Step two: confirm the pending request's ``challenge``; returns it.
        :class:`~cell.core.errors.ParamError` (nothing sent) if it is not the pending one."""
        return supervision.confirm_reset(self.runtime, challenge, self.bus_time())

    # -- health -----------------------------------------------------------------------
    def health(self) -> dict[str, Any]:
        """Status and reasons, the engine's trip, the bus, whether the live loop runs, and
        the runtime's counts (frames, bad frames, blocks' errors, streams, overruns)."""
        rt = self.runtime
        loop = self.live.status() if self.live is not None else None
        with self._held() as held:
            if not held and self._seen["health"]:
                problem = self._stuck()
                return {**self._seen["health"], "status": supervision.FAILED, "reasons": [problem],
                        "loop": {**loop, "problem": problem}}  # type: ignore[dict-item]
            counts = rt.health()
            assessed = supervision.assess(rt, self.live)
            if self.unsaved and assessed["status"] not in (supervision.WAITING, supervision.FAILED):
                assessed["status"] = supervision.DEGRADED
            assessed["reasons"] += list(self.unsaved.values())
            out = {**assessed, "bus": self.bus, "unsaved": list(self.unsaved.values()),
                   "runtime_running": self.live.running if self.live else False,
                   "undecodable": self.live.undecodable if self.live else 0, **counts,
                   "loop": loop, "limits": dict(supervision.LIMITS)}
            self._seen["health"] = out
            return out

    def frames_by_id(self) -> dict[tuple[int, bool], int]:
        """Frames received so far per ``(arbitration ID, extended)``, known or not."""
        with self.runtime.lock:
            return dict(self.runtime.frames_by_id)

    def metrics(self) -> dict[str, Any]:
        """The counts ``/metrics`` shows, taken at one instant: frames by ID (with the
        DBC message name of each known ID), bad frames by kind, late frames, ticks, overruns,
        the slowest tick, each block's step time and errors, and the bus time."""
        rt = self.runtime
        with rt.lock:
            by_id = dict(rt.frames_by_id)
            known = rt.db.by_id
            return {
                "frames_by_id": by_id,
                "messages": {k: known[k].name for k in by_id if k in known},
                "decode_errors": dict(rt.decode_errors),
                "late_frames": rt.late_frames,
                "ticks": rt.ticks,
                "tick_overruns": rt.tick_overruns,
                "tick_seconds_max": rt.tick_seconds_max,
                "tick_histogram": rt.counters.tick_histogram(),
                "block_faults": rt.faults.report(),
                "missed_cycles": dict(rt.counters.gaps.missed),
                "loop": self.live.status() if self.live is not None else None,
                "steps": [{"block": n, "family": rt.blocks[n].family, "seconds": secs, "count": count}
                          for n, (secs, count) in sorted(rt.step_time.items()) if n in rt.blocks],
                "block_errors": dict(rt.block_errors),
                "bus_time": rt.now,
            }


__all__ = ["Cell"]
