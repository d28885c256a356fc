"""The cell's registries: each kind of part is registered in one place, with one line.

A plant, an observer, a DBC file or an experiment joins the cell by registering here; the
command line, the simulator, the runtime, the HTTP service and the tuning store read these
tables and are not edited. The registry knows nothing of what registers in it: the cell's own
parts register in :mod:`cell.app.builtin`, which the composition root imports
(:func:`cell.app.load`); a plugin (an installed package with a ``testcell.plugins`` entry
point, or a module named in ``TESTCELL_PLUGINS``) registers its own in the same way when
:func:`load_plugins` imports it.

======================  ==========================================  =====================
registry                what                                        used by
======================  ==========================================  =====================
:data:`DBC_FILES`       extra DBC files (the cell's own ``dbc/``    :mod:`cell.bus.dbc`
                        folder is always loaded)
:data:`ENGINES`         engine profiles: compositions of plants     ``sim``, ``up``
:data:`FAMILIES`        block families: HTTP resource, tuning       service, tuning store
                        section
:data:`BLOCK_SETS`      factories of the runtime's native blocks    ``up``, ``replay``
:data:`EXPERIMENTS`     ``testcell experiment NAME``                the CLI
:data:`DESIGNS`         ``testcell design NAME``                    the CLI
:data:`COMMANDS`        ``testcell`` sub-commands from outside      the CLI
                        ``cell`` (``up``, from ``service``)
======================  ==========================================  =====================
"""

from __future__ import annotations

import importlib
import logging
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from cell.core.errors import ConfigError
from cell.core.options import Option

if TYPE_CHECKING:  # pragma: no cover
    import argparse

log = logging.getLogger(__name__)

#: Entry-point group of installed plugins.
ENTRY_POINT_GROUP = "testcell.plugins"
#: Environment variable naming plugin modules to import, comma-separated.
PLUGINS_ENV = "TESTCELL_PLUGINS"


class Run(Protocol):
    """What an engine profile's or a block set's ``build`` is handed: the process's
    :class:`~cell.core.settings.Settings`, of which the builds read only these."""

    engine: str | None
    duty: str | None
    seed: int
    plant: Mapping[str, Any]
    """The engine's own options by key (:attr:`EngineProfile.options`)."""
    blocks: Mapping[str, Any]
    """The block sets' own options by key (:attr:`BlockSet.options`)."""


# -- DBC files ------------------------------------------------------------------------------
DBC_FILES: list[Path] = []


def dbc_file(path: str | Path) -> Path:
    """Register a DBC file (or a folder of them) to load beside the cell's own ``dbc/``."""
    p = Path(path).resolve()
    if p not in DBC_FILES:
        DBC_FILES.append(p)
    return p


# -- engine profiles ------------------------------------------------------------------------
@dataclass(frozen=True)
class EngineProfile:
    """An engine the simulator can run: a composition of plants and its duty cycles.

    ``build(settings)`` returns the :class:`~cell.plant.composition.Composition`;
    ``duties`` names the duty cycles ``--duty`` accepts, the first being the default;
    ``options`` are the simulator options that only this engine takes.
    """

    name: str
    description: str
    build: Callable[[Run], Any]
    """Returns the engine's :class:`~cell.plant.composition.Composition`."""
    duties: tuple[str, ...] = ()
    options: tuple[Option, ...] = ()
    """Simulator options of this engine only (``--valve``, ``--bp-limit``, ...)."""
    shipped_scripts: bool = False
    """Whether the formula-device scripts shipped with the cell (seed 004's back-pressure
    filters, ``cell/scripts/shipped/``) read this engine's frames and load by default."""

    @property
    def default_duty(self) -> str | None:
        return self.duties[0] if self.duties else None


ENGINES: dict[str, EngineProfile] = {}
DEFAULT_ENGINE = "large-diesel"


def engine(profile: EngineProfile) -> EngineProfile:
    """Register an engine profile (``testcell sim --engine NAME``)."""
    return _register(ENGINES, "engine profile", profile.name, profile)


def engine_profile(name: str) -> EngineProfile:
    try:
        return ENGINES[name]
    except KeyError:
        if not ENGINES:
            raise ConfigError(f"--engine {name!r}: no engine profile is registered; the "
                              "composition root registers them (cell.app.load())") from None
        raise ConfigError(f"--engine {name!r} is not an engine profile; choose one of: "
                          f"{', '.join(ENGINES)}") from None


# -- block families -------------------------------------------------------------------------
@dataclass(frozen=True)
class BlockFamily:
    """A family of tunable blocks: its HTTP resource (``/{section}``) and tuning section.

    ``examples`` are PATCH bodies shown in the OpenAPI description.
    """

    name: str
    section: str
    description: str = ""
    examples: tuple[dict[str, Any], ...] = ()


FAMILIES: dict[str, BlockFamily] = {}


def family(fam: BlockFamily) -> BlockFamily:
    """Register a block family; its blocks get ``GET``/``PATCH /{section}/{name}``."""
    return _register(FAMILIES, "block family", fam.name, fam)


def family_of_section(section: str) -> BlockFamily | None:
    return next((f for f in FAMILIES.values() if f.section == section), None)


# -- the runtime's native blocks --------------------------------------------------------------
@dataclass(frozen=True)
class BlockSet:
    """A factory of native blocks, run by ``up`` and ``replay``.

    ``engines`` names the profiles whose frames the blocks read; ``up --engine X`` builds
    the sets of ``X`` (and those with no ``engines``); ``replay`` without ``--engine``
    builds them all, since a log may come from any engine, and writes the channels that
    got values.
    """

    name: str
    build: Callable[[Run], Sequence[Any]]
    """Returns the set's :class:`~cell.runtime.blocks.Block` instances."""
    engines: tuple[str, ...] = ()
    options: tuple[Option, ...] = ()
    """Options of these blocks only (``--osc-init``, ``--bias-design``): ``up`` and
    ``replay`` offer them, and ``build`` finds their values in ``run.blocks``."""

    def applies_to(self, engine_name: str | None) -> bool:
        return engine_name is None or not self.engines or engine_name in self.engines


BLOCK_SETS: dict[str, BlockSet] = {}


def block_set(bs: BlockSet) -> BlockSet:
    """Register a factory of native blocks."""
    return _register(BLOCK_SETS, "block set", bs.name, bs)


# -- experiments ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Experiment:
    """``testcell experiment NAME``: its options and its run.

    ``add_arguments(parser)`` adds the experiment's own options; ``run(args)`` returns the
    exit code and raises :class:`~cell.core.errors.ConfigError` for bad options before any work.
    """

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    seed: str = ""
    """The paper and figure it reproduces, shown by ``--list``."""
    description: str = field(default="", compare=False)


EXPERIMENTS: dict[str, Experiment] = {}


def experiment(exp: Experiment) -> Experiment:
    """Register an experiment (``testcell experiment NAME``)."""
    return _register(EXPERIMENTS, "experiment", exp.name, exp)


#: ``testcell design NAME``: tools that turn a log into an observer's tables (gains, biases).
#: A design has the same shape as an experiment: its options and its run.
DESIGNS: dict[str, Experiment] = {}


def design(d: Experiment) -> Experiment:
    """Register a design tool (``testcell design NAME``)."""
    return _register(DESIGNS, "design tool", d.name, d)


# -- commands -------------------------------------------------------------------------------
@dataclass(frozen=True)
class Command:
    """A ``testcell`` sub-command that a part outside ``cell`` brings: ``up``, which serves
    the HTTP API, comes from the ``service`` package this way.

    ``add_arguments(parser)`` adds its options; ``run(settings, args)`` returns the exit code.
    """

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[Any, argparse.Namespace], int]


COMMANDS: dict[str, Command] = {}


def command(cmd: Command) -> Command:
    """Register a ``testcell`` sub-command."""
    return _register(COMMANDS, "command", cmd.name, cmd)


# -- plumbing -------------------------------------------------------------------------------
def _register(table: dict[str, Any], what: str, name: str, item: Any) -> Any:
    old = table.get(name)
    if old is not None and old != item:
        raise ConfigError(f"{what} {name!r} is registered twice")
    table[name] = item
    return item


_loaded = False
_plugin_names: set[str] = set()


def load_plugins(extra: Sequence[str] = ()) -> list[str]:
    """Import every plugin, once; returns the plugin names.

    Plugins are the ``testcell.plugins`` entry points of installed packages and the modules
    named in ``TESTCELL_PLUGINS`` (comma-separated) or ``extra``. A plugin that fails to
    import stops start-up with its name and the error.
    """
    global _loaded
    names = [n.strip() for n in os.environ.get(PLUGINS_ENV, "").split(",") if n.strip()]
    names += [n for n in extra if n not in names]
    loaded = []
    if not _loaded:
        for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
            try:
                ep.load()
            except Exception as exc:
                raise ConfigError(f"plugin {ep.name} ({ep.value}) failed to load: {exc}") from exc
            loaded.append(ep.name)
        _loaded = True
    for name in names:
        if name in _plugin_names:
            continue
        try:
            importlib.import_module(name)
            _plugin_names.add(name)
        except Exception as exc:
            raise ConfigError(f"{PLUGINS_ENV}: plugin module {name!r} failed to load: "
                              f"{type(exc).__name__}: {exc}") from exc
        loaded.append(name)
    return loaded
