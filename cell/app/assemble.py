"""Assembling a cell's runtime from settings: what ``up`` and ``replay`` share."""

from __future__ import annotations

import logging
from pathlib import Path

from typing import Any

from cell.bus.dbc import load
from cell.core import registry
from cell.core.errors import ConfigError
from cell.core.settings import Settings
from cell.runtime import mapping
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
    for path in settings.designs:
        load_design_file(rt, path)
    if settings.state is not None and store is None:
        restore_state(rt, settings.state)
    scripts = ScriptManager(rt, store)
    if settings.scripts:
        scripts.load_files([Path(p) for p in settings.scripts])
    else:
        shipped = settings.engine is None or registry.engine_profile(settings.engine).shipped_scripts
        for problem in scripts.load_defaults(shipped=shipped):
            log.warning("%s", problem)
    if settings.maps:  # after every block: a mapping names a channel some block reads
        for line in mapping.install(rt, settings.maps).describe():
            log.info("mapped %s", line)
    return rt, scripts


def load_design(rt: Runtime, design: Any, source: str, name: str | None = None) -> str:
    """Load a design object into the observer it names (``name``: the one it must name);
    returns the observer's name. :class:`ConfigError` names an observer that is not in the
    runtime, one that takes no design, or what is wrong with the design (the previous one
    stays)."""
    from cell.core.errors import UnknownBlockError

    if not isinstance(design, dict) or not isinstance(design.get("observer"), str):
        raise ConfigError(f"{source}: field 'observer' (the observer it is for) is missing")
    who = design["observer"]
    if name is not None and who != name:
        raise ConfigError(f"{source}: names observer {who!r}, not {name!r}")
    try:
        block = rt.block(who, "observer")
    except UnknownBlockError:
        known = [b.name for b in rt.blocks.values() if b.family == "observer"]
        raise ConfigError(f"{source}: names observer {who!r}, which this cell does not run "
                          f"(its observers: {', '.join(known) or 'none'})") from None
    if not callable(getattr(block, "load_design", None)):
        raise ConfigError(f"{source}: observer {who!r} takes no design")
    block.load_design(design, source)
    return who


def load_design_file(rt: Runtime, path: str | Path) -> str:
    """Read a design file (``--design FILE``) and load it (:func:`load_design`)."""
    from cell.estimators.contract import read_design

    return load_design(rt, read_design(path), str(path))


def restore_state(rt: Runtime, path: str | Path) -> list[str]:
    """Apply a tuning file as ``up`` writes it (``--state FILE`` of ``replay`` and the
    experiments), read only: the file is never written. A missing or unreadable file is
    refused (:class:`ConfigError`), not set aside."""
    import json

    from cell.app.tuning import TuningStore, _shape_problem

    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"--state {path}: no such file") from None
    except (OSError, ValueError) as exc:
        raise ConfigError(f"--state {path}: not a readable tuning file: {exc}") from None
    problem = _shape_problem(data)
    if problem:
        raise ConfigError(f"--state {path}: {problem}")
    store = TuningStore(path)
    store.data = data
    return store.restore(rt)
