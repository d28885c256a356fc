"""``testcell up``: the simulator, the runtime and the HTTP API in one command.

The ``service`` package brings this command to ``testcell`` through the registry
(:data:`cell.core.registry.COMMANDS`), as a plugin would: ``cell`` runs without HTTP and never
imports ``service``. The package's ``testcell.plugins`` entry point (``pyproject.toml``)
imports this module when the command line loads its plugins.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

from cell import __version__
from cell.app.assemble import build_runtime
from cell.app.cell import Cell
from cell.app.cli import add_runtime_options
from cell.app.live import LiveCell
from cell.app.tuning import TuningStore, default_path
from cell.bus.interface import open_bus, resolve
from cell.core import registry
from cell.core.errors import ConfigError
from cell.core.settings import Settings, add_sim_options
from cell.estimators.contract import read_design

from .simproc import EXIT_SIM_LOST, ON_EXIT, SimSupervisor

log = logging.getLogger("testcell")


def _port(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--port must be a whole number, got {text!r}") from None
    if not 1 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"--port must be 1..65535, got {v}")
    return v


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
    # --parent-pid: the simulator watches this process and goes safe when it dies
    cmd = [sys.executable, "-m", "cell", "--log-level", settings.log_level, "sim",
           *settings.sim_argv(bus), "--parent-pid", str(os.getpid())]
    log.info("starting simulator: %s", " ".join(cmd[2:]))
    # Ctrl-C in a terminal signals the whole process group: the simulator ignores SIGINT (set
    # before the exec, so Python keeps it ignored) and up stops it itself, so that its
    # supervisor never takes a Ctrl-C for a simulator that died
    return subprocess.Popen(["/bin/sh", "-c", "trap '' INT; exec \"$@\"", "sh", *cmd])


def _stop_cell(reason: str) -> None:
    """Stop ``up`` from the simulator's watcher: SIGTERM to this process, as ``kill`` would
    (uvicorn shuts down gracefully; :func:`cmd_up` then exits with EXIT_SIM_LOST)."""
    os.kill(os.getpid(), signal.SIGTERM)


def _exit_on_sigterm(signum: int, frame: object) -> None:
    raise SystemExit(0)


def cmd_up(settings: Settings, args: argparse.Namespace) -> int:
    from cell import sim
    from service.main import create_app
    from service.security import check_bind
    from service.serve import serve

    settings = settings.for_simulator()
    spec = resolve(settings.bus)
    check_bind(settings.host, settings.token)
    _check_port_free(settings.host, settings.port)
    # uvicorn re-raises SIGTERM after its own graceful shutdown; turn it into SystemExit so
    # the finally below still stops the simulator and closes the bus
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    store = TuningStore(settings.state or default_path(settings.engine, str(spec),
                                                       settings.port, settings.name))
    store.load()
    runtime, scripts = build_runtime(settings, store)
    if not settings.no_sim:
        sim.build(settings, runtime.db)  # refuse a bad engine or frame set before starting
    # a --design given on the command line wins over the design saved by PUT
    store.restore(runtime, keep_designs=[read_design(p)["observer"] for p in settings.designs])
    bus = open_bus(spec)
    live = None
    supervisor = None
    sim_thread = None
    sim_bus = None
    sim_stop = threading.Event()
    try:
        if not settings.no_sim:
            if spec.interface == "virtual":
                # a virtual bus only exists inside this process: run the plant in a thread
                sim_bus = open_bus(spec)
                sim_thread = threading.Thread(
                    target=sim.run, name="testcell-sim", daemon=True,
                    kwargs=dict(bus=sim_bus, settings=settings, stop_event=sim_stop,
                                db=runtime.db),
                )
                sim_thread.start()
            else:
                supervisor = SimSupervisor(lambda: _start_sim_process(settings, str(spec)),
                                           on_exit=getattr(args, "on_sim_exit", "restart"),
                                           on_stop=_stop_cell).start()
        live = LiveCell(runtime, bus).start()
        cell = Cell(runtime=runtime, bus=str(spec), settings=settings, scripts=scripts,
                    tuning=store, live=live)
        log.info("testcell %s on %s; API on http://%s:%d (tuning file %s)",
                 __version__, spec, settings.host, settings.port, store.path)
        app = create_app(cell)
        app.state.simulator = supervisor  # /health and GET /simulator report it
        try:
            serve(app, host=settings.host, port=settings.port,
                  log_level=settings.log_level.lower())
        except SystemExit:
            if supervisor is None or supervisor.failed is None:
                raise
    finally:
        if live is not None:
            live.stop()  # before the bus closes, or its receive fails on a closed socket
        sim_stop.set()
        if supervisor is not None:
            supervisor.stop()
        if sim_thread is not None:
            sim_thread.join(2)
        if sim_bus is not None:
            sim_bus.shutdown()
        bus.shutdown()
    if supervisor is not None and supervisor.failed is not None:
        print(f"up: {supervisor.failed}", file=sys.stderr)
        return EXIT_SIM_LOST
    return 0


def add_arguments(up: argparse.ArgumentParser) -> None:
    """``testcell up`` options: the bus, the API's address, every simulator option, the
    tuning file and the runtime's (rates, DBC files, the block sets' own)."""
    up.add_argument("--bus", default=None,
                    help="auto (default), virtual, udp_multicast, socketcan or INTERFACE:CHANNEL; "
                         "CAN_INTERFACE/CAN_CHANNEL are honoured")
    up.add_argument("--host", default=None, help="API address (default 127.0.0.1)")
    up.add_argument("--port", type=_port, default=None, help="API port (default 8000)")
    up.add_argument("--no-sim", action="store_true", help="attach to an existing bus, no simulator")
    up.add_argument("--on-sim-exit", choices=ON_EXIT, default="restart",
                    help="when the simulator process exits: restart it with backoff (1 s, 2 s, "
                         "... default) or stop the cell (up exits with status 3)")
    add_sim_options(up)
    up.add_argument("--state", default=None, type=Path,
                    help="tuning file (default: this cell's own, "
                         "$XDG_STATE_HOME/testcell/<name>/tuning.json)")
    up.add_argument("--name", default=None,
                    help="the cell's name, which names its state folder (default: engine, bus "
                         "and API port, e.g. large-diesel_udp_multicast-239.74.163.2-43113_8000)")
    add_runtime_options(up)


UP = registry.command(registry.Command(
    "up", "start the simulator and the runtime with its HTTP API", add_arguments, cmd_up))
