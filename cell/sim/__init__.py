"""The simulator process (``testcell sim``): an engine profile on a CAN bus, or into a log.

Live, :func:`run` steps the engine's plants against ``time.monotonic()`` (real time, or
``speed`` times faster), sends every frame the DBC says the simulator sends at its cycle
time, and hands the frames it receives (demands, scenario commands) to the plants that
consume them. Offline, :func:`write_log` writes the same frames to any log python-can writes
(candump ``.log``, ``.asc``, ``.blf``, ``.csv``) as fast as it can, through the one lockstep
loop (:mod:`cell.sim.lockstep`). Only CAN frames pass between the simulator and the runtime
(DESIGN.md).
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
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
from cell.sim.simulator import Simulator

logger = logging.getLogger(__name__)

#: Signals whose changes the live simulator logs, with their DBC value names.
_WATCHED = ("ENGINE_STATE", "TRIP_REASON")


def build(settings: Settings, db: CellDatabase | None = None, t0: float = 0.0) -> Simulator:
    """The simulator of ``settings``' engine profile (default ``large-diesel``)."""
    s = settings.for_simulator()
    profile = registry.engine_profile(s.engine)
    db = db or dbc_mod.load([*registry.DBC_FILES, *s.dbc])
    return Simulator(profile.build(s), db, t0)


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
    """Receive and route frames until ``until`` (monotonic), or only what is queued (None)."""
    while True:
        if until is None:
            timeout = 0.0
        else:
            timeout = until - time.monotonic()
            if timeout <= 0.0:
                return
        msg = bus.recv(timeout=timeout)
        if msg is None:
            return
        sim.receive(msg)


def run(bus: CellBus, settings: Settings, stop_event: threading.Event | None = None,
        db: CellDatabase | None = None, counts: dict[str, int] | None = None) -> Composition:
    """Run the engine of ``settings`` on ``bus`` in real time (or ``settings.speed`` faster).

    Frames are stamped with the wall-clock start time plus simulation time, so at speed 1 a
    frame's timestamp is its send time. Stops after ``settings.duration`` simulation seconds
    (``None``: until ``stop_event`` is set). Returns the composition in its final state.
    ``counts["sent"]`` (when given) counts the frames put on the bus, as they go.
    """
    speed = settings.speed
    if not speed > 0 or not math.isfinite(speed):
        raise ConfigError(f"--speed must be a number > 0, got {speed}")
    sim = build(settings, db)
    sim.t0 = time.time()
    n_total = None if settings.duration is None else round(settings.duration / sim.dt)
    mono0 = time.monotonic()
    logger.info("sim started on %s: %s, speed x%g%s", bus.spec, _describe(sim), speed,
                "" if settings.duration is None else f", {settings.duration:g} s")
    seen: dict[str, float] = {}
    _watch(sim, seen)
    counts = counts if counts is not None else {}
    counts.setdefault("sent", 0)
    while True:
        if stop_event is not None and stop_event.is_set():
            break
        if n_total is not None and sim.k >= n_total:
            break
        due = mono0 + sim.t / speed
        if time.monotonic() < due:
            # idle until the next step is due, applying demands as they arrive
            _drain(bus, sim, min(due, time.monotonic() + 0.05))
            continue
        frames = sim.frames()
        for msg in frames:
            bus.send(msg)
        counts["sent"] += len(frames)
        _drain(bus, sim, None)
        sim.step()
        _watch(sim, seen)
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
    bus = open_bus(settings.bus)
    if threading.current_thread() is threading.main_thread():
        # SIGTERM (testcell up stopping, docker stop) ends the run like Ctrl-C: bus closed
        signal.signal(signal.SIGTERM, _interrupt)
    counts = {"sent": 0}
    try:
        run(bus, sim_settings, stop_event=stop_event, counts=counts)
    except KeyboardInterrupt:
        logger.info("sim stopped")
    finally:
        bus.shutdown()
        logger.info("sim sent %d frames", counts["sent"])
    return 0
