"""A whole live cell in the test process: the simulator in a thread on a private virtual bus,
the runtime's live loop and the HTTP service on a free port (no multicast, no subprocess)."""

from __future__ import annotations

import contextlib
import itertools
import os
import threading
from dataclasses import replace

from cell import app as cell_app

from cell import sim
from cell.bus.interface import open_bus, resolve
from cell.app.assemble import build_runtime
from cell.app.cell import Cell
from cell.app.live import LiveCell
from cell.core.settings import Settings
from cell.app.tuning import TuningStore
from service.main import create_app

from .served import served

_channels = itertools.count()


@contextlib.contextmanager
def live_cell(tmp_path, routers=(), **options):
    """Yield ``(base_url, cell)`` of a cell running ``Settings(**options)`` on a virtual bus
    (with ``routers`` added to its app)."""
    cell_app.load()
    channel = f"test-{os.getpid()}-{next(_channels)}"
    settings = replace(Settings(**options), bus=f"virtual:{channel}",
                       state=tmp_path / "tuning.json").for_simulator()
    store = TuningStore(settings.state)
    store.load()
    runtime, scripts = build_runtime(settings, store)
    store.restore(runtime)
    spec = resolve(settings.bus)
    bus, sim_bus = open_bus(spec), open_bus(spec)
    stop = threading.Event()
    thread = threading.Thread(target=sim.run, name="test-sim", daemon=True,
                              kwargs=dict(bus=sim_bus, settings=settings, stop_event=stop, db=runtime.db))
    live = LiveCell(runtime, bus)
    cell = Cell(runtime=runtime, bus=str(spec), settings=settings, scripts=scripts,
                tuning=store, live=live)
    app = create_app(cell)
    for router in routers:
        app.include_router(router)
    thread.start()
    live.start()
    try:
        with served(app) as url:
            yield url, cell
    finally:
        stop.set()
        live.stop()
        thread.join(5)
        sim_bus.shutdown()
        bus.shutdown()
