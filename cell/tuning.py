"""Saving accepted tuning atomically and restoring it at start-up.

The file is JSON, ``{"filters": {name: {param: value}}, ...}``. It is written to a
temporary file in the same folder and renamed over the old one, so a crash mid-write
never leaves half a file. A file that cannot be read is moved aside, never overwritten.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from .errors import ConfigError, ParamError, UnknownBlockError
from .runtime import Runtime

log = logging.getLogger(__name__)


def default_path() -> Path:
    base = os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state"
    return Path(base) / "testcell" / "tuning.json"


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` by write-then-rename in the same folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_atomic(path: Path, data: dict[str, Any]) -> None:
    """Write JSON to ``path`` atomically."""
    write_text_atomic(path, json.dumps(data, indent=2, sort_keys=True) + "\n")


class TuningStore:
    """The tuning file of one runtime: what ``PATCH`` accepted, restored on the next start."""

    def __init__(self, path: Path | str | None) -> None:
        self.path = Path(path) if path else default_path()
        self.data: dict[str, dict[str, dict[str, Any]]] = {}

    def load(self) -> dict[str, dict[str, dict[str, Any]]]:
        """Read the file; a corrupt one is moved aside (``.corrupt-<time>``) and reported."""
        if not self.path.exists():
            self.data = {}
            return self.data
        try:
            data = json.loads(self.path.read_text())
            if not isinstance(data, dict) or not all(isinstance(v, dict) for v in data.values()):
                raise ValueError("top level must be an object of sections")
        except (OSError, ValueError) as exc:
            aside = self.path.with_name(f"{self.path.name}.corrupt-{int(time.time())}")
            self.path.replace(aside)
            log.warning("tuning file %s is unreadable (%s); moved to %s, starting from defaults",
                        self.path, exc, aside)
            self.data = {}
            return self.data
        self.data = data
        return self.data

    def restore(self, runtime: Runtime) -> list[str]:
        """Apply saved parameters to the runtime's blocks; returns what was skipped and why.

        Every section of the file that is a block family's (:data:`cell.registry.FAMILIES`)
        is restored; other sections belong to their own owners (``scripts``) and are kept.
        """
        from . import registry

        registry.load_plugins()
        skipped = []
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

    def save(self) -> None:
        try:
            write_atomic(self.path, self.data)
        except OSError as exc:
            raise ConfigError(f"cannot save tuning to {self.path}: {exc}") from exc
