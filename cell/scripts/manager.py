"""Managing the cell's scripts: the shipped ones, hot swap, constants, and their files.

Scripts live in the runtime as blocks named after their file (``kalman.fdv``,
``kalman.labels``). A CyFlex-style set is the ``.labels`` file and the ``.ravg`` file of the
same stem; it is addressed by its ``.labels`` name, and ``PUT``-ing its ``.ravg`` name
replaces the running averages of the set. Scripts put by users are saved as files in
``<state>/scripts/``; constants and removals are saved in the tuning file. All writes are
atomic; a script that does not compile never replaces the running one.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from cell.core.errors import ConfigError, UnknownBlockError
from cell.scripts import ScriptBlock, ScriptError, load_script, shipped_scripts
from cell.scripts.dialects import suffix_of
from cell.runtime.scheduler import Runtime
from cell.core.files import aside_path, write_text_atomic


def remove_stale_temporaries_in(folder: Path) -> None:
    """Delete the temporary files (``.NAME.xxxx``) a writer killed mid-write left."""
    for tmp in folder.glob(".*"):
        if tmp.is_file():
            tmp.unlink(missing_ok=True)

log = logging.getLogger(__name__)


class TuningStore(Protocol):
    """What the manager needs of the tuning store (:class:`cell.app.tuning.TuningStore`):
    its file, its data, and saving it."""

    path: Path
    data: dict[str, Any]

    def save(self) -> None: ...


@dataclass
class Sources:
    """The text of one script: its main file and, for a CyFlex-style set, its ``.ravg``."""

    text: str
    ravg: str | None = None
    shipped: bool = False


class ScriptManager:
    """Load, swap, tune and remove the scripts of one runtime.

    Parameters
    ----------
    runtime:
        The runtime the script blocks run in.
    store:
        Tuning file (constants and removed scripts); ``None`` keeps nothing.
    folder:
        Where user scripts are saved; default ``scripts/`` beside the tuning file.
    """

    def __init__(self, runtime: Runtime, store: TuningStore | None = None,
                 folder: Path | None = None) -> None:
        self.runtime = runtime
        self.store = store
        self.folder = folder or (store.path.parent / "scripts" if store else None)
        self.sources: dict[str, Sources] = {}

    # -- names ------------------------------------------------------------------------
    @staticmethod
    def block_name(name: str) -> str:
        """The block a file name belongs to: ``x.ravg`` belongs to the set ``x.labels``."""
        return name[: -len(".ravg")] + ".labels" if suffix_of(name) == ".ravg" else name

    def names(self) -> list[str]:
        return list(self.sources)

    def block(self, name: str) -> ScriptBlock:
        if name not in self.sources:
            raise UnknownBlockError("script", name, self.names())
        return self.runtime.blocks[name]  # type: ignore[return-value]

    # -- start-up -----------------------------------------------------------------------
    def load_defaults(self, shipped: bool = True) -> list[str]:
        """Load the shipped scripts (unless removed), the saved ones, and saved constants.

        Returns the problems met (a saved script that no longer compiles is reported and
        skipped, never deleted).
        """
        problems = []
        removed = set(self._section().get("removed", []))
        entries: dict[str, Sources] = {}
        if shipped:
            for name, text, ravg in shipped_scripts():
                if name not in removed:
                    entries[name] = Sources(text, ravg, shipped=True)
        if self.folder and self.folder.is_dir():
            remove_stale_temporaries_in(self.folder)
            for path in sorted(self.folder.iterdir()):
                try:
                    if suffix_of(path.name) in (".fdv", ".labels"):
                        ravg = path.with_suffix(".ravg")
                        entries[path.name] = Sources(path.read_text(encoding="utf-8"),
                                                     ravg.read_text(encoding="utf-8")
                                                     if ravg.exists() else None)
                    elif suffix_of(path.name) == ".ravg" and not path.with_suffix(".labels").exists():
                        entries[path.name] = Sources(path.read_text(encoding="utf-8"))
                except (OSError, UnicodeDecodeError) as exc:
                    aside = aside_path(path)
                    path.replace(aside)
                    problems.append(f"{path.name}: unreadable ({exc}); moved to {aside}")
                    log.warning("saved script %s is unreadable (%s); moved to %s", path, exc, aside)
        for name, src in entries.items():
            try:
                self._install(name, src)
            except (ScriptError, ConfigError) as exc:
                problems.append(f"{name}: {exc}")
                log.warning("script %s not loaded: %s", name, exc)
        for name, consts in self._section().get("constants", {}).items():
            if name in self.sources:
                try:
                    self.block(name).set_constants(consts)
                except ValueError as exc:
                    problems.append(f"{name}: saved constants refused: {exc}")
        return problems

    def load_files(self, paths: list[Path]) -> list[str]:
        """Load scripts from files (``replay --script``); a ``.labels`` takes its ``.ravg``."""
        loaded = []
        for path in paths:
            path = Path(path)
            if not path.exists():
                raise ConfigError(f"--script {path}: file not found")
            suffix = suffix_of(path.name)
            if suffix == ".ravg" and path.with_suffix(".labels").exists():
                if any(Path(p).resolve() == path.with_suffix(".labels").resolve() for p in paths):
                    continue  # loaded with its .labels
            ravg = path.with_suffix(".ravg") if suffix == ".labels" else None
            src = Sources(path.read_text(), ravg.read_text() if ravg and ravg.exists() else None)
            self._install(path.name, src)
            loaded.append(path.name)
        return loaded

    # -- changes ------------------------------------------------------------------------
    def _compile(self, name: str, src: Sources) -> ScriptBlock:
        return load_script(name, src.text, src.ravg, rates=self.runtime.rates)

    def _install(self, name: str, src: Sources) -> tuple[ScriptBlock, list[str]]:
        """Compile and swap in at the next tick; the old block stays if anything fails."""
        new = self._compile(name, src)
        rt = self.runtime
        with rt.lock:
            old = rt.blocks.get(name)
            if old is not None and name not in self.sources:
                raise ConfigError(f"{name} is a {old.family}, not a script")
            kept: list[str] = []
            if old is not None:
                kept = new.adopt_state(old)
                rt.remove_block(name)
            try:
                rt.add_block(new)
            except ConfigError:
                if old is not None:
                    rt.add_block(old)
                raise
            for out, unit in getattr(new, "units", {}).items():
                ch = rt.channels[out]  # add_block made it
                ch.unit = ch.unit or (unit if unit and unit != "none" else "")
            self.sources[name] = src
        return new, kept

    def put(self, file_name: str, text: str) -> tuple[ScriptBlock, list[str]]:
        """Create or replace a script (or the ``.ravg`` of a set) from its text.

        Raises :class:`ScriptError` (nothing changes) when it does not compile, and
        :class:`ConfigError` when another block already produces one of its outputs.
        """
        name = self.block_name(file_name)
        old = self.sources.get(name)
        if suffix_of(file_name) == ".ravg" and (old is not None or file_name != name):
            if old is None:  # the labels of this set do not exist: a running-average-only set
                name, src = file_name, Sources(text)
            else:
                src = Sources(old.text, text)
        elif suffix_of(file_name) == ".labels":
            src = Sources(text, old.ravg if old else None)
        else:
            src = Sources(text)
        block, kept = self._install(name, src)
        self._save_source(name, src)
        self._forget_removal(name)
        return block, kept

    def set_constants(self, name: str, changes: dict[str, Any]) -> dict[str, float]:
        rt = self.runtime
        with rt.lock:
            block = self.block(name)
            before = block.constants()
            consts = block.set_constants(changes)
            try:
                self._save_section(lambda sec: sec.setdefault("constants", {}).__setitem__(name, consts))
            except Exception:
                block.set_constants(before)
                raise
            return consts

    def delete(self, name: str) -> None:
        name = self.block_name(name)
        rt = self.runtime
        with rt.lock:
            self.block(name)
            rt.remove_block(name)
            src = self.sources.pop(name)
        if self.folder:
            for path in (self.folder / name, (self.folder / name).with_suffix(".ravg")):
                path.unlink(missing_ok=True)
        if src.shipped:
            self._save_section(lambda sec: sec.setdefault("removed", []).append(name)
                               if name not in sec.get("removed", []) else None)
        self._save_section(lambda sec: sec.get("constants", {}).pop(name, None))

    # -- persistence --------------------------------------------------------------------
    def _section(self) -> dict[str, Any]:
        return self.store.data.get("scripts", {}) if self.store else {}

    def _save_section(self, change) -> None:
        if self.store is None:
            return
        sec = self.store.data.setdefault("scripts", {})
        change(sec)
        self.store.save()

    def _forget_removal(self, name: str) -> None:
        if name in self._section().get("removed", []):
            self._save_section(lambda sec: sec["removed"].remove(name))

    def _save_source(self, name: str, src: Sources) -> None:
        if not self.folder:
            return
        if src.shipped:
            return
        write_text_atomic(self.folder / name, src.text)
        if src.ravg is not None and suffix_of(name) == ".labels":
            write_text_atomic((self.folder / name).with_suffix(".ravg"), src.ravg)

    def unknown_inputs(self, name: str) -> list[str]:
        """Inputs of a script that no channel of the cell provides: no DBC signal, no block
        output, no channel seen. Its outputs would stay stale, so callers warn by name."""
        rt = self.runtime
        with rt.lock:
            block = self.block(name)
            known = set(rt.db.signals) | set(rt.producer) | set(rt.channels)
            return [i for i in block.inputs if i not in known]

    def describe(self, name: str) -> dict[str, Any]:
        with self.runtime.lock:
            block = self.block(name)
            d = block.describe()
            src = self.sources[name]
            d["ravg_source"] = src.ravg
            d["shipped"] = src.shipped
            rt = self.runtime
            chans = rt.channels
            d["status"] = {out: chans[out].status for out in block.outputs if out in chans}
            return d
