"""The ``testcell`` command: ``sim``, ``replay``, ``sweep``, ``tune``, ``experiment``,
``design`` and ``scenario``, and the commands registered from outside ``cell``
(:data:`cell.core.registry.COMMANDS`): ``up``, which serves the HTTP API, comes from
:mod:`service.up`."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from cell import __version__, app
from cell.app.assemble import build_runtime
from cell.app.commands import DESIGNS, EXPERIMENTS
from cell.core import registry
from cell.core.errors import BusError, ConfigError, TestcellError
from cell.core.settings import LOG_LEVELS, Settings, add_block_options

log = logging.getLogger("testcell")


# -- replay ------------------------------------------------------------------------------
def cmd_replay(settings: Settings, args: argparse.Namespace) -> int:
    from cell.runtime.replay import replay
    from cell.analysis.figures import plot_channels
    from cell.bus.signal_tables import WRITERS

    if Path(args.out).suffix.lower() not in WRITERS:
        raise ConfigError(f"--out {args.out}: unknown table format; use one of {', '.join(WRITERS)}")
    runtime, _ = build_runtime(settings)
    channels = [c.strip() for c in args.channels.split(",") if c.strip()] if args.channels else None
    result = replay(runtime, args.log, args.out, channels=channels,
                    progress=False if args.quiet else None)
    print(f"{args.log}: {result.summary()}; {len(result.rows)} ticks -> {args.out}",
          file=sys.stderr)
    if args.plot:
        # the back-pressure channels when the log has them, else what the replay computed
        wanted = channels or [c for c in PLOT_DEFAULT if c in result.columns] or result.columns[1:9]
        units = {n: runtime.store.unit_of(n) for n in wanted}
        plot_channels(args.plot, result.columns, result.rows, wanted, title=str(args.log),
                      units=units)
        print(f"plot -> {args.plot}", file=sys.stderr)
    if result.error is not None:
        print(f"testcell replay: stopped at {result.error}; rows up to it were written to "
              f"{args.out}", file=sys.stderr)
        return 1
    return 0


PLOT_DEFAULT = ["EXH_BP_R", "EXH_BP_R_TRUE", "EXH_BP_R_MAF", "EXH_BP_R_Kalman"]


def cmd_sim(settings: Settings, args: argparse.Namespace) -> int:
    from cell import sim

    return sim.main(args, settings)


def _with_args_only(main):
    """A command that takes only its parsed options (sweep, tune, experiment)."""
    return lambda settings, args: main(args)


# -- parser ------------------------------------------------------------------------------
def add_runtime_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cycle", default=None, metavar="HZ|FAS=..,MED=..,SLO=..",
                   help="task rates in Hz: a number sets MED (default 10); or name any of "
                        "FAS/MED/SLO (defaults 50/10/1)")
    p.add_argument("--dbc", action="append", default=None, metavar="PATH",
                   help="add a DBC file, or a folder of them, to the cell's own dbc/*.dbc "
                        "(repeatable): your ECU and DAQ frames decode into channels")
    p.add_argument("--plausibility", type=Path, default=None, metavar="FILE",
                   help="YAML or JSON list of {signal, min, max, rate}: ranges and rate limits "
                        "(units/s) over the DBC's; a value outside them is invalid")
    p.add_argument("--design", action="append", dest="designs", default=None, metavar="FILE",
                   help="load a design file into the observer it names (repeatable; "
                        "testcell design NAME writes one)")
    p.add_argument("--map", action="append", dest="maps", default=None,
                   metavar="CELL_CHANNEL=SIGNAL|FILE",
                   help="feed a channel the cell's blocks read from your signal, converting "
                        "known units (EXH_BP_R=DAQ_BP_R: kPa to mmH2O) or as given "
                        "(EXH_BP_R=DAQ_BP_R*101.97+0); or a YAML/JSON mapping file (repeatable)")
    add_block_options(p)  # the block sets' own: --osc-init, --bias-design, --no-controllers


def build_parser() -> argparse.ArgumentParser:
    """The ``testcell`` parser, with every registered engine's options and every experiment."""
    parser = argparse.ArgumentParser(
        prog="testcell",
        description="An emulated engine test cell that speaks CAN: the plant simulator, the "
                    "cyclic runtime with its filters, observers and scripts, and the HTTP API.",
        epilog="Every option can also be set as TESTCELL_<OPTION> in the environment.")
    parser.add_argument("--version", action="version", version=f"testcell {__version__}")
    parser.add_argument("--log-level", default=None,
                        choices=LOG_LEVELS)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    for cmd in registry.COMMANDS.values():  # first: `up` leads the help
        p = sub.add_parser(cmd.name, help=cmd.help)
        cmd.add_arguments(p)
        p.set_defaults(func=cmd.run)

    sim = sub.add_parser("sim", help="run an engine's plant simulator on the bus (or write a log)")
    from cell import sim as sim_module

    sim_module.add_arguments(sim)
    sim.set_defaults(func=cmd_sim)

    rp = sub.add_parser("replay", help="run the runtime offline over a CAN log, write a table")
    rp.add_argument("log", help="CAN log: candump -L .log, .asc, .blf, .trc or python-can .csv")
    rp.add_argument("--out", required=True,
                    help="output table, by suffix .csv, .parquet or .mf4 (MDF4): time, then one "
                         "column per channel")
    rp.add_argument("--plot", default=None, metavar="PNG", help="also plot the channels to a PNG")
    rp.add_argument("--channels", default=None, help="comma-separated channels to write")
    rp.add_argument("--engine", default=None, metavar="NAME",
                    help="run only this engine's native blocks (default: every engine's; the "
                         "channels that get values are written)")
    rp.add_argument("--script", action="append", dest="scripts", metavar="FILE",
                    help="run exactly this script (.fdv, .labels with its .ravg, .ravg); repeat "
                         "for more. Without --script, replay runs what testcell up runs")
    rp.add_argument("--native", action="store_true",
                    help="with --script: also run the native filters, observers and controllers")
    rp.add_argument("--quiet", action="store_true", help="no progress bar")
    rp.add_argument("--state", default=None, type=Path, metavar="FILE",
                    help="apply a tuning file as testcell up writes it (read only)")
    add_runtime_options(rp)
    rp.set_defaults(func=cmd_replay)

    from cell.analysis import autotune as tune_module
    from cell.analysis import sweep as sweep_module

    sp = sub.add_parser("sweep", help="Kalman Q/R sweep over a CAN log (seed 004, Tables 1-2)")
    sweep_module.add_arguments(sp)
    sp.set_defaults(func=_with_args_only(sweep_module.main))
    tp = sub.add_parser("tune", help="estimate Kalman Q and R from a CAN log, no truth needed")
    tune_module.add_arguments(tp)
    tp.set_defaults(func=_with_args_only(tune_module.main))

    from cell.app import scenario as scenario_module

    sc = sub.add_parser("scenario", help="send a scenario command (KEY=VALUE) to a running "
                                         "simulator; --list shows the keys")
    scenario_module.add_arguments(sc)
    sc.set_defaults(func=lambda settings, args: scenario_module.main(args, settings))

    ex = sub.add_parser("experiment", help="run an experiment (--list shows them)")
    EXPERIMENTS.add_arguments(ex)
    ex.set_defaults(func=_with_args_only(EXPERIMENTS.main))
    de = sub.add_parser("design", help="design an observer's tables from a log (--list shows the tools)")
    DESIGNS.add_arguments(de)
    de.set_defaults(func=_with_args_only(DESIGNS.main))
    return parser


def main(argv: list[str] | None = None) -> int:
    command = "testcell"
    try:
        app.load()  # engines, blocks and experiments shape the parser
        parser = build_parser()
        args = parser.parse_args(argv)
        command = f"testcell {args.command}"
        settings = Settings.from_args(args)
        logging.basicConfig(level=settings.log_level,
                            format="%(asctime)s %(name)s %(levelname)s %(message)s")
        return args.func(settings, args)
    except (BusError, ConfigError) as exc:
        print(f"{command}: {exc}", file=sys.stderr)
        return 2
    except TestcellError as exc:
        report = exc.report() if hasattr(exc, "report") else str(exc)  # every script error
        print("\n".join(f"{command}: {line}" for line in report.splitlines()), file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `testcell ... | head`: the reader left; not an error of ours
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
