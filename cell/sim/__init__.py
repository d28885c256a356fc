"""The simulator process (``testcell sim``): an engine profile on a CAN bus, or into a log.

Live, :func:`run` steps the engine's plants against ``time.monotonic()`` (real time, or
``speed`` times faster), sends every frame the DBC says the simulator sends at its cycle
time, and hands the frames it receives (demands, scenario commands) to the plants that
consume them. Offline, :func:`write_log` writes the same frames to any log python-can writes
(candump ``.log``, ``.asc``, ``.blf``, ``.csv``) as fast as it can, through the one lockstep
loop (:mod:`cell.sim.lockstep`). Only CAN frames pass between the simulator and the runtime
(DESIGN.md).

Live, the bus stamps every received frame with the wall clock, so the simulator's E2E age
check and its command watchdog run on the wall clock (``time.time()``), in bus seconds:
at ``--speed 20`` a 3-cycle watchdog still waits 0.3 s of wall clock for the runtime's demand.

Nothing on the bus stops the loop: a datagram or frame that python-can cannot receive or
the DBC cannot decode is counted (``undecodable``, in ``SIM_STATUS``) and skipped.

The simulator never outlives its parent (:class:`ParentWatch`): on Linux it asks the kernel
for SIGHUP when its parent dies (``PR_SET_PDEATHSIG``), and it also polls its parent's pid
(``--parent-pid PID``, default: the parent it was started by). When the parent is gone the
plants go to their safe state (valves open, engine idle), ``SAFE_STATE`` = ``PARENT_LOST``
goes out for :data:`PARENT_LOST_REPORT_S`, and the process exits.
"""

from __future__ import annotations

import argparse
import ctypes
import logging
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
from tqdm import tqdm

from cell.bus import dbc as dbc_mod
from cell.core import registry
from cell.bus.interface import CellBus, open_bus
from cell.bus.dbc import CellDatabase
from cell.core.errors import ConfigError
from cell.plant.composition import Composition
from cell.core.settings import Settings, add_sim_options
from cell.sim.simulator import DEMAND_TIMEOUT_CYCLES, Simulator

logger = logging.getLogger(__name__)

#: Signals whose changes the live simulator logs, with their DBC value names.
_WATCHED = ("ENGINE_STATE", "TRIP_REASON", "RESET_STATE", "SAFE_STATE")
#: How long the simulator reports its safe state on the bus after its parent died, s.
PARENT_LOST_REPORT_S = 2.0
#: How often the live loop polls its parent, s.
PARENT_POLL_S = 0.05
#: Linux prctl option: signal this process when its parent dies.
_PR_SET_PDEATHSIG = 1


class ParentWatch:
    """Notices the death of the process that started the simulator.

    Parameters
    ----------
    parent_pid:
        The parent to watch; ``None``: the process's parent at start (none when that is
        pid 1, i.e. already orphaned or run as a container's init).

    ``lost()`` is true once the parent has died: the kernel's ``PR_SET_PDEATHSIG`` signal
    (SIGHUP, Linux, set by :meth:`arm`) sets it at once, and ``os.getppid()`` differing from
    the watched pid (the simulator was re-parented) sets it at the next poll.
    """

    def __init__(self, parent_pid: int | None = None) -> None:
        ppid = os.getppid()
        self.pid = parent_pid if parent_pid is not None else (ppid if ppid > 1 else None)
        self._signalled = False

    def arm(self) -> None:
        """Ask the kernel for SIGHUP on the parent's death (Linux; main thread only)."""
        if self.pid is None or threading.current_thread() is not threading.main_thread():
            return
        signal.signal(signal.SIGHUP, self._on_signal)
        if sys.platform.startswith("linux"):
            try:
                libc = ctypes.CDLL(None, use_errno=True)
                if libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGHUP), 0, 0, 0) != 0:
                    logger.debug("prctl(PR_SET_PDEATHSIG) failed: errno %d", ctypes.get_errno())
            except (OSError, AttributeError) as exc:  # no libc prctl: polling only
                logger.debug("no prctl: %s", exc)

    def _on_signal(self, signum: int, frame: object) -> None:
        self._signalled = True

    def lost(self) -> bool:
        if self.pid is None:
            return False
        return self._signalled or os.getppid() != self.pid


def build(settings: Settings, db: CellDatabase | None = None, t0: float = 0.0) -> Simulator:
    """The simulator of ``settings``' engine profile (default ``large-diesel``)."""
    s = settings.for_simulator()
    profile = registry.engine_profile(s.engine)
    db = db or dbc_mod.load([*registry.DBC_FILES, *s.dbc])
    cycles = s.demand_timeout_cycles
    return Simulator(profile.build(s), db, t0,
                     demand_timeout_cycles=DEMAND_TIMEOUT_CYCLES if cycles is None else cycles)


def simulate(db: CellDatabase, plant: Composition | str = "rated", seed: int = 0,
             duration: float | None = None, t0: float = 0.0, **options) -> Iterator[can.Message]:
    """Frames of an open-loop run, in time order, with no wall clock.

    ``plant`` is a composition, or a duty cycle of the ``engine`` option's profile
    (default ``large-diesel``) built with ``seed`` and the engine's ``options`` (e.g.
    ``valve=100``). Frames are stamped ``t0 + t`` for ``t`` = 0, dt, ... up to (not
    including) ``duration`` (default: the duty cycle's nominal length).
    """
    from cell.sim.lockstep import Lockstep

    if isinstance(plant, str):
        plant = build(Settings.build({"duty": plant, "seed": seed, **options}, environ={}),
                      db).plant
    sim = Simulator(plant, db, t0)
    if duration is None:
        duration = plant.duration
    yield from Lockstep(sim).frames(round(duration / sim.dt))


def _describe(sim: Simulator) -> str:
    return ", ".join(f"{k} {v}" for k, v in sim.plant.describe().items())


def _watch(sim: Simulator, seen: dict[str, float]) -> None:
    """Log a change of the engine's state or trip reason, naming the DBC's value."""
    for name in _WATCHED:
        v = sim.plant.signals.get(name)
        if v is None or seen.get(name) == v:
            continue
        if name in seen:
            choices = sim.db.message_for(name).get_signal_by_name(name).choices or {}
            label = choices.get(int(v), v)
            level = logging.WARNING if name == "ENGINE_STATE" and str(label) == "TRIPPED" \
                else logging.INFO
            logger.log(level, "at t=%.2f s %s is %s%s", sim.t, name, label,
                       " (engine tripped)" if level == logging.WARNING else "")
        seen[name] = v


def _drain(bus: CellBus, sim: Simulator, until: float | None) -> None:
    """Receive and route frames until ``until`` (monotonic), or only what is queued (None).

    A datagram python-can cannot turn into a frame (its receive path raises) is counted as
    undecodable and skipped; so is a frame the simulator cannot decode.
    """
    errors = 0
    while True:
        if until is None:
            timeout = 0.0
        else:
            timeout = until - time.monotonic()
            if timeout <= 0.0:
                return
        try:
            msg = bus.recv(timeout=timeout)
            _count_skipped(bus, sim)
        except Exception as exc:  # noqa: BLE001 - nothing from the bus may stop the plant
            sim.undecodable += 1
            errors += 1
            if errors & (errors - 1) == 0:
                logger.warning("skipped an undecodable datagram (%d so far): %s: %s",
                               sim.undecodable, type(exc).__name__, exc)
            if until is None and errors >= 64:
                return  # a receive path that only fails: back to stepping the plant
            continue
        if msg is None:
            return
        try:
            sim.receive(msg)
        except Exception as exc:  # noqa: BLE001
            sim.undecodable += 1
            logger.warning("skipped a frame the simulator cannot take (%d so far): %s: %s",
                           sim.undecodable, type(exc).__name__, exc)


def _count_skipped(bus: CellBus, sim: Simulator) -> None:
    """Add to the simulator's count the datagrams the bus itself skipped as undecodable
    (:class:`~cell.bus.interface.CellBus` counts and skips them inside ``recv``)."""
    skipped = getattr(bus, "undecodable", 0)
    seen = getattr(sim, "bus_undecodable_seen", 0)
    if skipped > seen:
        sim.undecodable += skipped - seen
        sim.bus_undecodable_seen = skipped


def run(bus: CellBus, settings: Settings, stop_event: threading.Event | None = None,
        db: CellDatabase | None = None, counts: dict[str, int] | None = None,
        parent: ParentWatch | None = None) -> Composition:
    """Run the engine of ``settings`` on ``bus`` in real time (or ``settings.speed`` faster).

    Frames are stamped with the wall-clock start time plus simulation time, so at speed 1 a
    frame's timestamp is its send time. Stops after ``settings.duration`` simulation seconds
    (``None``: until ``stop_event`` is set), or :data:`PARENT_LOST_REPORT_S` after
    ``parent`` died. Returns the composition in its final state.
    ``counts["sent"]`` (when given) counts the frames put on the bus, as they go.
    """
    speed = settings.speed
    if not speed > 0 or not math.isfinite(speed):
        raise ConfigError(f"--speed must be a number > 0, got {speed}")
    sim = build(settings, db)
    sim.t0 = time.time()
    sim.clock = time.time  # the clock the bus stamps received frames with
    n_total = None if settings.duration is None else round(settings.duration / sim.dt)
    mono0 = time.monotonic()
    logger.info("sim started on %s: %s, speed x%g%s", bus.spec, _describe(sim), speed,
                "" if settings.duration is None else f", {settings.duration:g} s")
    seen: dict[str, float] = {}
    _watch(sim, seen)
    counts = counts if counts is not None else {}
    counts.setdefault("sent", 0)
    lost_at = None
    next_poll = 0.0
    while True:
        if stop_event is not None and stop_event.is_set():
            break
        if n_total is not None and sim.k >= n_total:
            break
        now = time.monotonic()
        if parent is not None and lost_at is None and now >= next_poll:
            next_poll = now + PARENT_POLL_S
            if parent.lost():
                lost_at = now
                sim.parent_lost()
                logger.warning("at t=%.2f s the parent process %s died: safe state (valves "
                               "open, engine idle); exiting in %g s", sim.t, parent.pid,
                               PARENT_LOST_REPORT_S)
        if lost_at is not None and now - lost_at >= PARENT_LOST_REPORT_S:
            break
        due = mono0 + sim.t / speed
        if now < due:
            # idle until the next step is due, applying demands as they arrive
            _drain(bus, sim, min(due, now + PARENT_POLL_S))
            continue
        frames = sim.frames()
        for msg in frames:
            bus.send(msg)
        counts["sent"] += len(frames)
        _drain(bus, sim, None)
        sim.step()
        _watch(sim, seen)
    if sim.e2e.discarded or sim.undecodable:
        logger.info("sim discarded %s; undecodable %d", sim.discards(), sim.undecodable)
    return sim.plant


def write_log(path: str | Path, settings: Settings | str, seed: int = 0,
              duration: float | None = None, *, t0: float = 0.0, progress: bool = True,
              db: CellDatabase | None = None, **options) -> int:
    """Write an open-loop run to a CAN log as fast as possible; return the frame count.

    ``settings`` are the process's settings, or a duty cycle name with ``seed``,
    ``duration`` and the engine's ``options`` (``engine="large-diesel"``, ``valve=100``...).
    ``path``'s suffix picks python-can's writer (candump ``.log``, ``.asc``, ``.blf``,
    ``.csv``, ...). The run lasts ``settings.duration`` (default: the duty cycle's nominal
    length); every frame the simulator sends is written, truth included, so the log carries
    its own answer key. A tqdm bar shows progress over simulation time.
    """
    from cell.sim.lockstep import Lockstep

    if isinstance(settings, str):
        settings = Settings.build({"duty": settings, "seed": seed, "duration": duration,
                                   **options}, environ={})

    settings = settings.for_simulator()
    sim = build(settings, db, t0)
    duration = settings.duration if settings.duration is not None else sim.plant.duration
    if duration is None or duration < 0 or not math.isfinite(duration):
        raise ConfigError(f"--duration must be >= 0 s, got {duration}")
    path = Path(path)
    try:
        writer = can.Logger(str(path))
    except ValueError as exc:
        raise ConfigError(f"--out {path}: {exc}") from exc
    except OSError as exc:
        raise ConfigError(f"--out {path}: cannot write: {exc.strerror or exc}") from exc
    per_second = round(1.0 / sim.dt)
    count = 0
    desc = f"sim {settings.engine} {settings.duty}"
    with writer, tqdm(total=round(duration, 2), unit="s", desc=desc, disable=not progress) as bar:
        for k, frames in Lockstep(sim).steps(round(duration / sim.dt), frames=True):
            for msg in frames:
                writer.on_message_received(msg)
            count += len(frames)
            if (k + 1) % per_second == 0:
                bar.update(1)
        bar.update(bar.total - bar.n)
    return count


# -- command line ---------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``testcell sim`` options to ``parser``."""
    parser.add_argument("--bus", default=None,
                        help="python-can bus: auto (default), virtual, udp_multicast, socketcan "
                             "or INTERFACE:CHANNEL")
    add_sim_options(parser)
    parser.add_argument("--dbc", action="append", default=None, metavar="PATH",
                        help="add a DBC file or folder to the cell's own (repeatable)")
    parser.add_argument("--out", default=None, metavar="LOG",
                        help="write a CAN log (.log, .asc, .blf, .csv) as fast as possible "
                             "instead of using a bus")
    parser.add_argument("--list-engines", action="store_true",
                        help="list the engine profiles and their duty cycles, then exit")
    parser.add_argument("--parent-pid", type=int, default=None, metavar="PID",
                        help="the process commanding this simulator (default: its parent); "
                             "when it dies the plant goes safe, reports it for 2 s and exits")


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def main(args: argparse.Namespace, settings: Settings | None = None,
         stop_event: threading.Event | None = None) -> int:
    """Run ``testcell sim``; return the exit code.

    Raises :class:`ConfigError` for bad options and :class:`~cell.core.errors.BusError` when the
    bus cannot be used; the caller prints either as one line.
    """
    if getattr(args, "list_engines", False):
        for p in registry.ENGINES.values():
            print(f"{p.name:<14} {p.description}\n{'':<14} duty cycles: {', '.join(p.duties)}")
        return 0
    settings = settings or Settings.from_args(args)
    sim_settings = settings.for_simulator()
    if args.out:
        n = write_log(args.out, sim_settings)
        logger.info("wrote %d frames to %s", n, args.out)
        return 0
    build(sim_settings)  # refuse a bad engine, duty or DBC before opening the bus
    parent = None
    if stop_event is None:  # a process of its own, not a thread of `up --bus virtual`
        parent = ParentWatch(getattr(args, "parent_pid", None))
        parent.arm()
    bus = open_bus(settings.bus)
    if threading.current_thread() is threading.main_thread():
        # SIGTERM (testcell up stopping, docker stop) ends the run like Ctrl-C: bus closed
        signal.signal(signal.SIGTERM, _interrupt)
    counts = {"sent": 0}
    try:
        run(bus, sim_settings, stop_event=stop_event, counts=counts, parent=parent)
    except KeyboardInterrupt:
        logger.info("sim stopped")
    finally:
        bus.shutdown()
        logger.info("sim sent %d frames", counts["sent"])
    if parent is not None and parent.lost():
        # an orphan leaves at once: nothing is left to flush but the log, and the
        # interpreter's teardown of a loaded process can take seconds on a busy machine
        logger.info("sim exits: its parent died")
        logging.shutdown()
        os._exit(0)
    return 0
