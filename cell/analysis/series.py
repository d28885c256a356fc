"""A channel of a CAN log as a series of samples, one per MED tick, with its truth.

A log written by the simulator carries its own answer key: every signal the simulator knows
the true value of has a ``<SIGNAL>_TRUE`` twin. :func:`channel_series` samples a channel (and
its truth) exactly as the runtime's blocks see it, so offline work (Q/R sweeps, tuning,
observer experiments) runs on the same numbers as the live cell. :class:`Series` also wraps
plain arrays (:meth:`Series.from_arrays`). :func:`add_log_options` and :func:`load_series`
are the command-line side shared by ``testcell sweep`` and ``testcell tune``.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cell.core.errors import ConfigError
from cell.estimators.backpressure import as_samples


@dataclass
class Series:
    """One channel sampled at every MED tick of a log, with its truth when the log has it.

    Attributes
    ----------
    t:
        Tick times (bus time, s).
    y:
        The channel's value at each tick; NaN where it was stale or had no value yet.
    truth:
        ``<channel>_TRUE`` at each tick (NaN where stale), or ``None``.
    channel, truth_channel:
        Names of the sampled channels.
    rate_hz:
        The MED rate the ticks ran at.
    source:
        Where the samples came from (a log path, or ``"array"``).
    frames:
        Frames read from the log.
    """

    t: np.ndarray
    y: np.ndarray
    truth: np.ndarray | None
    channel: str
    truth_channel: str | None = None
    rate_hz: float = 10.0
    source: str = "array"
    frames: int = 0
    unit: str = ""
    """The channel's unit (from the DBC), for axes and tables."""

    @property
    def n(self) -> int:
        return int(self.y.size)

    @property
    def valid(self) -> int:
        return int(np.isfinite(self.y).sum())

    @classmethod
    def from_arrays(
        cls,
        y: Sequence[float | None] | np.ndarray,
        truth: Sequence[float | None] | np.ndarray | None = None,
        rate_hz: float = 10.0,
        channel: str = "y",
        t0: float = 0.0,
    ) -> Series:
        """A series from plain samples at ``rate_hz`` (``None`` counts as stale)."""
        yy = as_samples(y)
        tt = None if truth is None else as_samples(truth)
        if tt is not None and tt.shape != yy.shape:
            raise ConfigError(f"truth has {tt.size} samples, the channel {yy.size}")
        t = t0 + np.arange(yy.size) / rate_hz
        return cls(t, yy, tt, channel, None if tt is None else f"{channel}_TRUE", rate_hz)


def channel_series(
    log_path: str | Path,
    channel: str,
    truth: str | bool | None = None,
    rates: Any = None,
    progress: bool | None = None,
    db: Any = None,
    maps: Any = (),
) -> Series:
    """Sample ``channel`` (and its truth) at every MED tick of a CAN log.

    The log runs through a :class:`cell.runtime.scheduler.Runtime` with no blocks, so the samples are
    exactly the inputs the runtime's filters see: at each tick, the latest frame value at
    or before the tick, NaN when the channel is stale or has no value yet. Stale ticks are
    kept; :func:`cell.estimators.backpressure.kalman_bank` holds its state over them as the
    runtime does.

    Parameters
    ----------
    log_path:
        A CAN log python-can reads (candump ``.log``, ``.asc``, ``.trc``, ``.csv``, ``.blf``).
    channel:
        The signal to sample, e.g. ``EXH_BP_R``.
    truth:
        ``None`` (default) samples ``<channel>_TRUE`` when the log has it; a name samples
        that channel (which must be in the log); ``False`` samples no truth.
    rates:
        :class:`cell.runtime.scheduler.Rates` (default 50/10/1 Hz); samples are taken at MED.
    progress:
        Progress bar over the log (tqdm); ``None`` lets tqdm decide, ``False`` hides it.
    db:
        The DBC codec (default: the cell's).
    maps:
        ``--map`` arguments (:mod:`cell.runtime.mapping`): a user's signal as ``channel``.

    Returns
    -------
    Series

    Raises
    ------
    ConfigError
        The log is missing, or has no ``channel`` (the message lists the channels it has),
        or no ``truth`` channel when one was named.
    LogFormatError
        A malformed log line; the message carries the file and line number.
    """
    from cell.bus.dbc import load
    from cell.sim.lockstep import feed
    from cell.runtime.replay import read_log
    from cell.runtime.scheduler import Runtime

    rt = Runtime(db or load(), rates=rates)
    truth_name = f"{channel}_TRUE" if truth is None or truth is True else truth or None
    if maps:
        from cell.runtime import mapping

        reads = {channel} | ({truth_name} if truth_name else set())
        rt.set_map(mapping.check(mapping.parse_maps(maps), rt.db, reads))
    times: list[float] = []
    ys: list[float] = []
    ts: list[float] = []
    nan = math.nan

    def value(name: str | None, t: float) -> float:
        ch = rt.channels.get(name) if name else None
        if ch is None:
            return nan
        status, _ = ch.status_at(t)
        return ch.value if status == "ok" and ch.value is not None else nan

    def on_tick(t: float) -> None:
        times.append(t)
        ys.append(value(channel, t))
        ts.append(value(truth_name, t))

    fed = feed(rt, read_log(log_path, progress=progress), on_tick)
    if fed.error is not None:
        raise fed.error
    frames = fed.frames
    known = sorted(rt.channels)
    if channel not in rt.channels:
        raise ConfigError(
            f"--channel {channel}: no such channel in {log_path} ({frames} frames); "
            f"channels in the log: {', '.join(known) or 'none'}"
        )
    if truth_name is not None and truth_name not in rt.channels:
        if truth is None:
            truth_name = None
        else:
            raise ConfigError(
                f"--truth {truth_name}: no such channel in {log_path}; "
                f"channels in the log: {', '.join(known)}"
            )
    return Series(
        t=np.asarray(times, dtype=float),
        y=np.asarray(ys, dtype=float),
        truth=None if truth_name is None else np.asarray(ts, dtype=float),
        channel=channel,
        truth_channel=truth_name,
        rate_hz=rt.rates.MED,
        source=str(log_path),
        frames=frames,
        unit=rt.channels[channel].unit,
    )


# -- command line ---------------------------------------------------------------------------
def add_log_options(parser: argparse.ArgumentParser) -> None:
    """Options shared by the commands that read a channel from a log (``sweep``, ``tune``)."""
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--cycle", default=None, metavar="HZ|FAS=..,MED=..,SLO=..",
                        help="task rates; samples are taken at MED (default 10 Hz)")
    parser.add_argument("--dbc", action="append", default=None, metavar="PATH",
                        help="a DBC file or folder added to the cell's own (repeatable)")
    parser.add_argument("--map", action="append", dest="maps", default=None,
                        metavar="CHANNEL=SIGNAL|FILE",
                        help="read --channel from your signal, converting known units "
                             "(EXH_BP_R=DAQ_BP_R) or as given (EXH_BP_R=DAQ_BP_R*101.97+0); "
                             "or a YAML/JSON mapping file (repeatable)")


def load_series(args: argparse.Namespace) -> Series:
    """The series a ``sweep``/``tune`` command line asks for."""
    from cell.bus.dbc import load
    from cell.runtime.scheduler import Rates

    truth: str | bool | None = getattr(args, "truth", None)
    if getattr(args, "no_truth", False):
        truth = False
    dbc = getattr(args, "dbc", None) or []
    db = load(tuple(dbc))
    return channel_series(
        args.log, args.channel, truth=truth, rates=Rates.parse(getattr(args, "cycle", None)),
        progress=False if getattr(args, "quiet", False) else None,
        db=db, maps=getattr(args, "maps", None) or (),
    )


__all__ = ["Series", "add_log_options", "as_samples", "channel_series", "load_series"]
