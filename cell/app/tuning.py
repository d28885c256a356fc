"""Saving accepted tuning atomically and restoring it at start-up.

The file is JSON, ``{"filters": {name: {param: value}}, ...}``, and ``{"designs": {observer:
design}}`` for the designs loaded live (``PUT /observers/{name}/design``), restored before
the parameters. It is written to a
temporary file in the same folder, flushed to disk (``fsync``), renamed over the old one
(``os.replace``) and the folder synced, so a crash or ``kill -9`` at any moment leaves the
old file or the new one, never half a file. A file that cannot be read, or whose shape is
wrong, is moved aside (``tuning.json.corrupt-<time>``, never overwritten) with a warning
naming both paths, and the cell starts from its defaults. Temporary files left by a killed
writer are removed at the next load.
"""

from __future__ import annotations

import json
import logging
import os
import re

from pathlib import Path
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

from cell.core.errors import ConfigError, ParamError, UnknownBlockError
from cell.core.files import aside_path, remove_stale_temporaries, write_atomic, write_text_atomic

__all__ = ["TuningStore", "aside_path", "cell_key", "default_path", "remove_stale_temporaries",
           "state_root", "write_atomic", "write_text_atomic"]

if TYPE_CHECKING:
    from cell.runtime.scheduler import Runtime

log = logging.getLogger(__name__)

#: The section of the designs loaded live, by observer.
DESIGNS = "designs"


def state_root() -> Path:
    """Where the cells' state folders live: ``$XDG_STATE_HOME/testcell``
    (``~/.local/state/testcell``)."""
    base = os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state"
    return Path(base) / "testcell"


def cell_key(engine: str | None, bus: str | None, port: int | None,
             name: str | None = None) -> str:
    """The name of one cell's state folder: ``name`` when given (``--name``), else its
    engine, bus and API port, e.g. ``large-diesel_udp_multicast-239.74.163.3-43114_8001``,
    so two cells on one machine never share a tuning file unless told to."""
    if name:
        return name
    parts = [engine or "cell", bus or "bus", str(port) if port is not None else "port"]
    return "_".join(re.sub(r"[^A-Za-z0-9._-]+", "-", p).strip("-.") or "x" for p in parts)


def default_path(engine: str | None = None, bus: str | None = None, port: int | None = None,
                 name: str | None = None) -> Path:
    """The default tuning file of one cell: ``<state root>/<cell key>/tuning.json``."""
    return state_root() / cell_key(engine, bus, port, name) / "tuning.json"


def _shape_problem(data: Any) -> str | None:
    """What is wrong with the structure of a tuning file, or ``None``."""
    if not isinstance(data, dict):
        return "top level must be an object of sections"
    for section, entries in data.items():
        if not isinstance(entries, dict):
            return f"section {section!r} must be an object"
        if section == "scripts":
            if not isinstance(entries.get("removed", []), list) or not all(
                    isinstance(n, str) for n in entries.get("removed", [])):
                return "scripts.removed must be a list of script names"
            consts = entries.get("constants", {})
            if not isinstance(consts, dict) or not all(isinstance(v, dict) for v in consts.values()):
                return "scripts.constants must map script names to objects"
            continue
        for name, params in entries.items():
            if not isinstance(params, dict):
                return f"{section}.{name} must be an object of parameters"
    return None


class TuningStore:
    """The tuning file of one runtime: what ``PATCH`` accepted, restored on the next start."""

    def __init__(self, path: Path | str | None) -> None:
        self.path = Path(path) if path else default_path()
        self.data: dict[str, dict[str, dict[str, Any]]] = {}
        #: why the file was set aside at the last load (``None``: it was fine)
        self.problem: str | None = None

    def load(self) -> dict[str, dict[str, dict[str, Any]]]:
        """Read the file; a corrupt one is moved aside (``.corrupt-<time>``) and reported."""
        for tmp in remove_stale_temporaries(self.path):
            log.info("removed %s, left by a write that was interrupted", tmp)
        if not self.path.exists():
            self.data = {}
            return self.data
        try:
            data = json.loads(self.path.read_text())
            problem = _shape_problem(data)
            if problem:
                raise ValueError(problem)
        except (OSError, ValueError) as exc:
            aside = aside_path(self.path)
            self.path.replace(aside)
            self.problem = (f"tuning file {self.path} is unreadable ({exc}); moved to {aside}, "
                            "starting from defaults")
            log.warning("%s", self.problem)
            self.data = {}
            return self.data
        self.data = data
        return self.data

    def restore(self, runtime: Runtime, keep_designs: Iterable[str] = ()) -> list[str]:
        """Apply saved designs, then saved parameters, to the runtime's blocks; returns what
        was skipped and why.

        The ``designs`` section is loaded first (an observer in ``keep_designs``, given its
        design on the command line, keeps that one). Every section of the file that is a block
        family's (:data:`cell.core.registry.FAMILIES`) is restored; other sections belong to
        their own owners (``scripts``) and are kept.
        """
        from cell import app
        from cell.app.assemble import load_design
        from cell.core import registry

        app.load()
        skipped = []
        keep = set(keep_designs)
        for name, design in self.data.get(DESIGNS, {}).items():
            if name in keep:
                continue
            try:
                load_design(runtime, design, f"tuning file {self.path}: {DESIGNS}.{name}", name=name)
            except ConfigError as exc:
                skipped.append(f"{DESIGNS}/{name}: {exc}")
                log.warning("tuning file %s: not restoring the design of %s: %s", self.path,
                            name, exc)
        for section, entries in self.data.items():
            fam = registry.family_of_section(section)
            if fam is None:
                continue
            for name, params in list(entries.items()):
                block = runtime.blocks.get(name)
                volatile = getattr(block, "VOLATILE", ())
                params = {k: v for k, v in params.items() if k not in volatile}
                try:
                    runtime.set_params(name, params, family=fam.name)
                except (UnknownBlockError, ParamError) as exc:
                    skipped.append(f"{section}/{name}: {exc}")
                    log.warning("tuning file %s: not restoring %s/%s: %s", self.path, section,
                                name, exc)
        return skipped

    def record(self, section: str, name: str, params: dict[str, Any]) -> None:
        """Remember a block's accepted parameters and save the whole file atomically."""
        self.data.setdefault(section, {})[name] = params
        self.save()

    def record_design(self, name: str, design: dict[str, Any]) -> None:
        """Remember the design loaded into observer ``name`` and save the whole file
        atomically (:class:`ConfigError` when it cannot be written; the memory is undone)."""
        designs = self.data.setdefault(DESIGNS, {})
        before = designs.get(name)
        designs[name] = design
        try:
            self.save()
        except ConfigError:
            if before is None:
                designs.pop(name)
                if not designs:
                    self.data.pop(DESIGNS)
            else:
                designs[name] = before
            raise

    def save(self) -> None:
        try:
            write_atomic(self.path, self.data)
        except OSError as exc:
            raise ConfigError(f"cannot save tuning to {self.path}: {exc}") from exc
