"""The ``testcell`` command: ``up``, ``sim``, ``replay``, ``sweep``, ``tune``, ``experiment``,
``design`` and ``scenario``."""

from __future__ import annotations

import argparse
import logging
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

from . import __version__, registry
from .errors import BusError, ConfigError, TestcellError
from .settings import LOG_LEVELS, Settings, add_sim_options

log = logging.getLogger("testcell")


def _port(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--port must be a whole number, got {text!r}") from None
    if not 1 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"--port must be 1..65535, got {v}")
    return v


def build_runtime(settings: Settings, store=None):
    """The runtime ``up`` and ``replay`` share: the DBC files, the rates, the native blocks
    of the engine (:data:`cell.registry.BLOCK_SETS`; every engine's when ``settings.engine``
    is ``None``) and the scripts. With scripts given, only those run (plus the native blocks
    with ``native``); otherwise the native blocks, the saved scripts and, for an engine whose
    frames they read, the shipped ones."""
    from .dbc import load
    from .runtime import Rates, Runtime
    from .scripting import ScriptManager

    db = load(settings.dbc)
    rt = Runtime(db, rates=Rates.parse(settings.cycle))
    if not settings.scripts or settings.native:
        for block_set in registry.BLOCK_SETS.values():
            if block_set.applies_to(settings.engine):
                for block in block_set.build(settings):
                    rt.add_block(block)
    scripts = ScriptManager(rt, store)
    if settings.scripts:
        scripts.load_files([Path(p) for p in settings.scripts])
    else:
        shipped = settings.engine is None or registry.engine_profile(settings.engine).shipped_scripts
        for problem in scripts.load_defaults(shipped=shipped):
            log.warning("%s", problem)
    return rt, scripts


# -- up ----------------------------------------------------------------------------------
def _check_port_free(host: str, port: int) -> None:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            raise ConfigError(
                f"cannot serve on {host}:{port}: {exc.strerror}; choose another with --port"
            ) from None


def _start_sim_process(settings: Settings, bus: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "cell", "--log-level", settings.log_level, "sim",
           *settings.sim_argv(bus)]
    log.info("starting simulator: %s", " ".join(cmd[2:]))
    return subprocess.Popen(cmd)


def _stop_process(proc: subprocess.Popen | None) -> None:
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _exit_on_sigterm(signum: int, frame: object) -> None:
    raise SystemExit(0)


def cmd_up(settings: Settings, args: argparse.Namespace) -> int:
    import uvicorn

    from service.main import create_app

    from .bus import open_bus, resolve
    from .context import Cell
    from .live import LiveCell
    from .tuning import TuningStore

    from .sim import build as build_sim

    settings = settings.for_simulator()
    spec = resolve(settings.bus)
    _check_port_free(settings.host, settings.port)
    # uvicorn re-raises SIGTERM after its own graceful shutdown; turn it into SystemExit so
    # the finally below still stops the simulator and closes the bus
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    store = TuningStore(settings.state)
    store.load()
    runtime, scripts = build_runtime(settings, store)
    if not settings.no_sim:
        build_sim(settings, runtime.db)  # refuse a bad engine or frame set before starting
    store.restore(runtime)
    bus = open_bus(spec)
    sim_proc = None
    sim_thread = None
    sim_bus = None
    sim_stop = threading.Event()
    try:
        if not settings.no_sim:
            if spec.interface == "virtual":
                # a virtual bus only exists inside this process: run the plant in a thread
                from . import sim

                sim_bus = open_bus(spec)
                sim_thread = threading.Thread(
                    target=sim.run, name="testcell-sim", daemon=True,
                    kwargs=dict(bus=sim_bus, settings=settings, stop_event=sim_stop,
                                db=runtime.db),
                )
                sim_thread.start()
            else:
                sim_proc = _start_sim_process(settings, str(spec))
        live = LiveCell(runtime, bus).start()
        cell = Cell(runtime=runtime, bus=str(spec), tuning=store, live=live,
                    extra={"scripts": scripts, "settings": settings})
        log.info("testcell %s on %s; API on http://%s:%d (tuning file %s)",
                 __version__, spec, settings.host, settings.port, store.path)
        uvicorn.run(create_app(cell), host=settings.host, port=settings.port,
                    log_level=settings.log_level.lower())
        live.stop()
    finally:
        sim_stop.set()
        _stop_process(sim_proc)
        if sim_thread is not None:
            sim_thread.join(2)
        if sim_bus is not None:
            sim_bus.shutdown()
        bus.shutdown()
    return 0


# -- replay ------------------------------------------------------------------------------
def cmd_replay(settings: Settings, args: argparse.Namespace) -> int:
    from .replay import replay
    from .tables import WRITERS, plot_channels

    if Path(args.out).suffix.lower() not in WRITERS:
        raise ConfigError(f"--out {args.out}: unknown table format; use one of {', '.join(WRITERS)}")
    runtime, _ = build_runtime(settings)
    channels = [c.strip() for c in args.channels.split(",") if c.strip()] if args.channels else None
    result = replay(runtime, args.log, args.out, channels=channels,
                    progress=False if args.quiet else None)
    print(f"{args.log}: {result.frames} frames, {len(result.rows)} ticks -> {args.out}",
          file=sys.stderr)
    if args.plot:
        wanted = channels or [c for c in PLOT_DEFAULT if c in result.columns]
        plot_channels(args.plot, result.columns, result.rows, wanted, title=str(args.log))
        print(f"plot -> {args.plot}", file=sys.stderr)
    if result.error is not None:
        print(f"testcell replay: stopped at {result.error}; rows up to it were written to "
              f"{args.out}", file=sys.stderr)
        return 1
    return 0


PLOT_DEFAULT = ["EXH_BP_R", "EXH_BP_R_TRUE", "EXH_BP_R_MAF", "EXH_BP_R_Kalman"]


def cmd_sim(settings: Settings, args: argparse.Namespace) -> int:
    from . import sim

    return sim.main(args, settings)


def _with_args_only(main):
    """A command that takes only its parsed options (sweep, tune, experiment)."""
    return lambda settings, args: main(args)


# -- parser ------------------------------------------------------------------------------
def _common_runtime_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cycle", default=None, metavar="HZ|FAS=..,MED=..,SLO=..",
                   help="task rates in Hz: a number sets MED (default 10); or name any of "
                        "FAS/MED/SLO (defaults 50/10/1)")
    p.add_argument("--dbc", action="append", default=None, metavar="PATH",
                   help="add a DBC file, or a folder of them, to the cell's own dbc/*.dbc "
                        "(repeatable): your ECU and DAQ frames decode into channels")
    p.add_argument("--osc-init", type=float, default=None, metavar="X",
                   help="initial OSC guess of the catalyst observer twc, normalised to fresh "
                        "(default 1)")


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

    up = sub.add_parser("up", help="start the simulator and the runtime with its HTTP API")
    up.add_argument("--bus", default=None,
                    help="auto (default), virtual, udp_multicast, socketcan or INTERFACE:CHANNEL; "
                         "CAN_INTERFACE/CAN_CHANNEL are honoured")
    up.add_argument("--host", default=None, help="API address (default 127.0.0.1)")
    up.add_argument("--port", type=_port, default=None, help="API port (default 8000)")
    up.add_argument("--no-sim", action="store_true", help="attach to an existing bus, no simulator")
    add_sim_options(up)
    up.add_argument("--no-controllers", action="store_true",
                    help="no native PI controllers (e.g. to drive the valve from a script)")
    up.add_argument("--state", default=None, type=Path,
                    help="tuning file (default $XDG_STATE_HOME/testcell/tuning.json)")
    _common_runtime_options(up)
    up.set_defaults(func=cmd_up)

    sim = sub.add_parser("sim", help="run an engine's plant simulator on the bus (or write a log)")
    from . import sim as sim_module

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
    _common_runtime_options(rp)
    rp.set_defaults(func=cmd_replay)

    from .analysis import autotune as tune_module
    from .analysis import sweep as sweep_module

    sp = sub.add_parser("sweep", help="Kalman Q/R sweep over a CAN log (seed 004, Tables 1-2)")
    sweep_module.add_arguments(sp)
    sp.set_defaults(func=_with_args_only(sweep_module.main))
    tp = sub.add_parser("tune", help="estimate Kalman Q and R from a CAN log, no truth needed")
    tune_module.add_arguments(tp)
    tp.set_defaults(func=_with_args_only(tune_module.main))

    from . import scenario as scenario_module

    sc = sub.add_parser("scenario", help="send a scenario command (KEY=VALUE) to a running "
                                         "simulator; --list shows the keys")
    scenario_module.add_arguments(sc)
    sc.set_defaults(func=lambda settings, args: scenario_module.main(args, settings))

    from . import experiments

    ex = sub.add_parser("experiment", help="run an experiment (--list shows them)")
    experiments.add_arguments(ex)
    ex.set_defaults(func=_with_args_only(experiments.main))
    de = sub.add_parser("design", help="design an observer's tables from a log (--list shows the tools)")
    experiments.DESIGN_COMMAND.add_arguments(de)
    de.set_defaults(func=_with_args_only(experiments.DESIGN_COMMAND.main))
    return parser


def main(argv: list[str] | None = None) -> int:
    command = "testcell"
    try:
        registry.load_plugins()  # engines, blocks and experiments shape the parser
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


if __name__ == "__main__":
    sys.exit(main())
