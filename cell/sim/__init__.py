"""The simulator process (``testcell sim``): the plant on a CAN bus, or into a log file.

Live, :func:`run` steps the :class:`~cell.plant.Plant` against ``time.monotonic()`` (real
time, or ``speed`` times faster), sends every SIM frame of the DBC at its cycle time and
applies the VALVE_DEMAND frames it receives. Offline, :func:`write_log` writes the same
frames to any log python-can writes (candump ``.log``, ``.asc``, ``.blf``, ``.csv``), as fast
as it can. Only CAN frames pass between the simulator and the runtime (DESIGN.md).
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import threading
import time
from dataclasses import replace
from pathlib import Path

import can
from tqdm import tqdm

from .. import dbc as dbc_mod
from ..bus import CellBus, open_bus
from ..dbc import CellDatabase, FrameDecodeError
from ..errors import ConfigError
from ..plant import CYCLES, TRIPPED, Plant, PlantParams

logger = logging.getLogger(__name__)

DEMAND_MESSAGE = "VALVE_DEMAND"
_DEMAND_SIGNALS = (("L", "VALVE_DEMAND_L"), ("R", "VALVE_DEMAND_R"))


def _make_plant(
    cycle: str,
    seed: int,
    initial_valve: float | None,
    bp_limit: float | None,
    params: PlantParams | None,
) -> Plant:
    if bp_limit is not None:
        params = replace(params or PlantParams(), bp_limit=float(bp_limit))
    return Plant(cycle, seed=seed, params=params, initial_valve=initial_valve)


def apply_demand(plant: Plant, db: CellDatabase, msg: can.Message) -> bool:
    """Apply one received frame to the plant if it is a VALVE_DEMAND; True when applied.

    Frames that do not decode, and frames of other messages, are ignored.
    """
    try:
        message, values = db.decode(msg)
    except FrameDecodeError:
        return False
    if message.name != DEMAND_MESSAGE:
        return False
    for bank, sig in _DEMAND_SIGNALS:
        v = values.get(sig)
        if v is not None and math.isfinite(v):
            plant.set_demand(bank, v)
    return True


def _drain(bus: CellBus, db: CellDatabase, plant: Plant, until: float | None) -> None:
    """Receive and apply frames until ``until`` (monotonic), or only what is queued (None)."""
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
        apply_demand(plant, db, msg)


def run(
    bus: CellBus,
    cycle: str = "rated",
    seed: int = 0,
    speed: float = 1.0,
    duration: float | None = None,
    initial_valve: float | None = None,
    bp_limit: float | None = None,
    stop_event: threading.Event | None = None,
    db: CellDatabase | None = None,
    params: PlantParams | None = None,
) -> Plant:
    """Run the plant on ``bus`` in real time (or ``speed`` times faster).

    Parameters
    ----------
    bus:
        An open :class:`cell.bus.CellBus`; frames are sent on it and VALVE_DEMAND frames
        are read from it without blocking the plant.
    cycle, seed, initial_valve, params:
        As for :class:`cell.plant.Plant`.
    speed:
        Simulation seconds per wall-clock second (> 0).
    duration:
        Stop after this many simulation seconds; ``None`` runs until ``stop_event``.
    bp_limit:
        Engine-protection limit in mmH2O (default ``PlantParams.bp_limit``, 1200).
    stop_event:
        Set it to stop the loop cleanly.
    db:
        The DBC codec (default: the cell's ``testcell.dbc``).

    Returns
    -------
    Plant
        The plant in its final state.

    Frames are stamped with the wall-clock start time plus simulation time, so at
    ``speed`` = 1 a frame's timestamp is its send time.
    """
    if not speed > 0 or not math.isfinite(speed):
        raise ConfigError(f"--speed must be a number > 0, got {speed}")
    db = db or dbc_mod.load()
    plant = _make_plant(cycle, seed, initial_valve, bp_limit, params)
    n_total = None if duration is None else round(duration / plant.dt)
    wall0 = time.time()
    mono0 = time.monotonic()
    logger.info(
        "sim started on %s: duty %s, seed %d, speed x%g, valve %.1f %%, bp limit %.0f mmH2O%s",
        bus.spec,
        plant.schedule.name,
        seed,
        speed,
        plant.valves["L"].position,
        plant.bp_limit,
        "" if duration is None else f", {duration:g} s",
    )
    tripped = False
    while True:
        if stop_event is not None and stop_event.is_set():
            break
        if n_total is not None and plant.k >= n_total:
            break
        due = mono0 + plant.t / speed
        if time.monotonic() < due:
            # idle until the next step is due, applying demands as they arrive
            _drain(bus, db, plant, min(due, time.monotonic() + 0.05))
            continue
        for msg in plant.frames(db, wall0):
            bus.send(msg)
        _drain(bus, db, plant, None)
        plant.step()
        if not tripped and plant.state == TRIPPED:
            tripped = True
            logger.warning(
                "engine tripped at t=%.2f s: EXH_BP_%s above the %.0f mmH2O limit",
                plant.t,
                plant.trip_bank,
                plant.bp_limit,
            )
    return plant


def write_log(
    path: str | Path,
    cycle: str = "rated",
    seed: int = 0,
    duration: float | None = None,
    *,
    t0: float = 0.0,
    initial_valve: float | None = None,
    bp_limit: float | None = None,
    params: PlantParams | None = None,
    db: CellDatabase | None = None,
    progress: bool = True,
) -> int:
    """Write an open-loop run to a CAN log as fast as possible; return the frame count.

    Parameters
    ----------
    path:
        Output file; python-can's ``can.Logger`` picks the format from the suffix
        (candump ``.log``, ``.asc``, ``.blf``, ``.csv``, ...).
    duration:
        Simulation seconds (default: the duty cycle's nominal length).
    t0:
        Timestamp of the first frame, s.
    progress:
        Show a tqdm progress bar over simulation time.

    The frames are those of :func:`cell.plant.simulate`: every SIM message at its DBC cycle
    time, truth included, so the log carries its own answer key.
    """
    db = db or dbc_mod.load()
    plant = _make_plant(cycle, seed, initial_valve, bp_limit, params)
    if duration is None:
        duration = plant.schedule.duration
    if duration < 0 or not math.isfinite(duration):
        raise ConfigError(f"--duration must be >= 0 s, got {duration}")
    path = Path(path)
    try:
        writer = can.Logger(str(path))
    except ValueError as exc:
        raise ConfigError(f"--out {path}: {exc}") from exc
    except OSError as exc:
        raise ConfigError(f"--out {path}: cannot write: {exc.strerror or exc}") from exc
    n = round(duration / plant.dt)
    per_second = round(1.0 / plant.dt)
    count = 0
    with (
        writer,
        tqdm(
            total=round(duration, 2),
            unit="s",
            desc=f"sim {plant.schedule.name}",
            disable=not progress,
        ) as bar,
    ):
        for k in range(n):
            for msg in plant.frames(db, t0):
                writer.on_message_received(msg)
                count += 1
            plant.step()
            if (k + 1) % per_second == 0:
                bar.update(1)
        bar.update(bar.total - bar.n)
    return count


# -- command line ---------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``testcell sim`` options to ``parser``."""
    parser.add_argument(
        "--bus",
        default=None,
        help="python-can bus: auto (default), virtual, "
        "udp_multicast, socketcan or INTERFACE:CHANNEL",
    )
    parser.add_argument(
        "--duty",
        default="rated",
        metavar="{" + ",".join(CYCLES) + "}",
        help="duty cycle (default rated: idle, ramp, rated held)",
    )
    parser.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="simulation seconds per wall-clock second (default 1)",
    )
    parser.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    parser.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="S",
        help="stop after S simulation seconds (default: run until stopped; "
        "with --out, the duty cycle's nominal length)",
    )
    parser.add_argument(
        "--valve",
        type=float,
        default=None,
        metavar="PERCENT",
        help="initial valve opening in %% (default: the 680 mmH2O opening at rated)",
    )
    parser.add_argument(
        "--bp-limit",
        type=float,
        default=None,
        metavar="MMH2O",
        help="engine-protection back-pressure limit (default 1200)",
    )
    parser.add_argument(
        "--out",
        default=None,
        metavar="LOG",
        help="write a CAN log (.log, .asc, .blf, .csv) as fast as possible instead of using a bus",
    )


def check_arguments(args: argparse.Namespace) -> None:
    """Raise :class:`ConfigError` naming the option when a ``testcell sim`` value is bad."""
    duty = getattr(args, "duty", "rated")
    if duty not in CYCLES:
        raise ConfigError(
            f"--duty {duty!r} is not a duty cycle; choose one of: {', '.join(CYCLES)}"
        )
    speed = getattr(args, "speed", 1.0)
    if speed is None or not math.isfinite(speed) or speed <= 0:
        raise ConfigError(f"--speed must be a number > 0, got {speed}")
    duration = getattr(args, "duration", None)
    if duration is not None and (not math.isfinite(duration) or duration <= 0):
        raise ConfigError(f"--duration must be a number of seconds > 0, got {duration}")
    valve = getattr(args, "valve", None)
    if valve is not None and (not math.isfinite(valve) or not 0.0 <= valve <= 100.0):
        raise ConfigError(f"--valve must be an opening in 0..100 %, got {valve}")
    limit = getattr(args, "bp_limit", None)
    if limit is not None and (not math.isfinite(limit) or not 0.0 < limit <= 20000.0):
        raise ConfigError(f"--bp-limit must be in (0, 20000] mmH2O, got {limit}")


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def main(args: argparse.Namespace, stop_event: threading.Event | None = None) -> int:
    """Run ``testcell sim``; return the exit code.

    Raises :class:`ConfigError` for bad options and :class:`~cell.errors.BusError` when the
    bus cannot be used; the caller prints either as one line.
    """
    check_arguments(args)
    if getattr(args, "out", None):
        n = write_log(
            args.out,
            args.duty,
            args.seed,
            args.duration,
            initial_valve=args.valve,
            bp_limit=args.bp_limit,
        )
        logger.info("wrote %d frames to %s", n, args.out)
        return 0
    bus = open_bus(args.bus)
    if threading.current_thread() is threading.main_thread():
        # SIGTERM (testcell up stopping, docker stop) ends the run like Ctrl-C: bus closed
        signal.signal(signal.SIGTERM, _interrupt)
    try:
        run(
            bus,
            args.duty,
            args.seed,
            speed=args.speed,
            duration=args.duration,
            initial_valve=args.valve,
            bp_limit=args.bp_limit,
            stop_event=stop_event,
        )
    except KeyboardInterrupt:
        logger.info("sim stopped")
    finally:
        bus.shutdown()
    return 0
