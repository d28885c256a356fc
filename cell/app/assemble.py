"""Assembling a cell's runtime from settings: what ``up`` and ``replay`` share."""

from __future__ import annotations

import logging
from pathlib import Path

from cell.bus.dbc import load
from cell.core import registry
from cell.core.settings import Settings
from cell.runtime.plausibility import read_file
from cell.runtime.scheduler import Rates, Runtime
from cell.scripts.manager import ScriptManager

log = logging.getLogger(__name__)


def build_runtime(settings: Settings, store=None):
    """The runtime ``up`` and ``replay`` share: the DBC files, the rates, the native blocks
    of the engine (:data:`cell.core.registry.BLOCK_SETS`; every engine's when ``settings.engine``
    is ``None``) and the scripts. With scripts given, only those run (plus the native blocks
    with ``native``); otherwise the native blocks, the saved scripts and, for an engine whose
    frames they read, the shipped ones."""
    db = load([*registry.DBC_FILES, *settings.dbc])
    rt = Runtime(db, rates=Rates.parse(settings.cycle))
    if settings.plausibility is not None:
        rt.plausibility.override(read_file(settings.plausibility))
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
