"""One settings object per process, built from the command line and the environment.

:class:`Settings` holds what every part of a process may need to know: the engine and its
simulator options, the bus, the DBC files, the runtime's rates and blocks, and the service's
address and state file. It is built once (:meth:`Settings.build`), validated as a whole, and
handed down; nothing below the command line reads ``argparse`` or ``os.environ``.

Every setting can also come from the environment as ``TESTCELL_<KEY>`` (for example
``TESTCELL_ENGINE=large-diesel``, ``TESTCELL_BP_LIMIT=900``); an option given on the command
line wins. An unknown ``TESTCELL_*`` variable, or an unknown key given to
:meth:`Settings.build`, is refused by name: a misspelt setting never passes silently.

Simulator options are declared once, as :class:`Option` (the common ones in
:data:`SIM_OPTIONS`, an engine's own in its :class:`~cell.core.registry.EngineProfile`), so
``testcell sim`` and ``testcell up`` offer the same flags, and ``up`` hands the simulator
process every one of them (:meth:`Settings.sim_argv`). A block set's own options
(:class:`~cell.core.registry.BlockSet`) are read the same way into :attr:`Settings.blocks`.
The option tables are the registry's; what fills them is the composition root's business.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from cell.core import registry
from cell.core.errors import ConfigError
from cell.core.options import Option, parse_bool, words

ENV_PREFIX = "TESTCELL_"


def _NAME_OK(name: str) -> bool:
    import re

    return re.fullmatch(r"[A-Za-z0-9_-][A-Za-z0-9._-]{0,63}", name) is not None
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")


def _positive(v: float) -> str | None:
    return None if math.isfinite(v) and v > 0 else f"must be a number > 0, got {v}"


def _duration(v: float) -> str | None:
    return None if math.isfinite(v) and v > 0 else f"must be a number of seconds > 0, got {v}"


#: Options every engine's simulator takes (the engine's own come from its profile).
SIM_OPTIONS: tuple[Option, ...] = (
    Option("engine", "--engine", str, metavar="NAME",
           help="engine profile (default large-diesel; `testcell sim --list-engines`)"),
    Option("duty", "--duty", str, metavar="CYCLE",
           help="duty cycle of the engine (default: the engine's first, rated for large-diesel)"),
    Option("speed", "--speed", float, check=_positive,
           help="simulation seconds per wall-clock second (default 1)"),
    Option("seed", "--seed", int, help="noise seed (default 0)"),
    Option("duration", "--duration", float, metavar="S", check=_duration,
           help="stop after S simulation seconds (default: run until stopped; with --out, "
                "the duty cycle's nominal length)"),
    Option("demand_timeout_cycles", "--demand-timeout-cycles", float, metavar="N",
           check=_positive,
           help="command watchdog: cycles of a demand (VALVE_DEMAND) without a valid frame "
                "before the valves open and the engine idles (default 3)"),
)


def _own_options(parts) -> dict[str, tuple[Option, list[str]]]:
    out: dict[str, tuple[Option, list[str]]] = {}
    for part in parts:
        for opt in part.options:
            out.setdefault(opt.key, (opt, []))[1].append(part.name)
    return out


def engine_options() -> dict[str, tuple[Option, list[str]]]:
    """Every registered engine's own options by key: the option and the engines taking it."""
    return _own_options(registry.ENGINES.values())


def block_options() -> dict[str, tuple[Option, list[str]]]:
    """Every registered block set's own options by key: the option and the sets taking it."""
    return _own_options(registry.BLOCK_SETS.values())


def add_block_options(parser: argparse.ArgumentParser) -> None:
    """Add every block set's own options (``--osc-init``, ``--bias-design``, ...) to ``parser``."""
    for opt, _sets in block_options().values():
        opt.add_to(parser)


def add_sim_options(parser: argparse.ArgumentParser) -> None:
    """Add every simulator option (common and every engine's own) to ``parser``."""
    for opt in SIM_OPTIONS:
        opt.add_to(parser)
    for opt, engines in engine_options().values():
        opt.add_to(parser, f" [{', '.join(engines)}]")


#: How a ``TESTCELL_<KEY>`` value is read (others are text).
_ENV_PARSERS: dict[str, Callable[[str], Any]] = {
    "seed": int, "speed": float, "duration": float, "port": int, "state": Path,
    "demand_timeout_cycles": float, "plausibility": Path,
    "native": parse_bool, "no_sim": parse_bool, "protect_reads": parse_bool,
    "max_body": int, "max_script": int,
    "dbc": words, "scripts": words, "plugins": words, "designs": words, "maps": words,
}


@dataclass(frozen=True)
class Settings:
    """The settings of one process (see the module notes)."""

    # -- the simulator ------------------------------------------------------------------
    engine: str | None = None
    """Engine profile; ``None``: the default for ``sim``/``up``, every engine for ``replay``."""
    duty: str | None = None
    seed: int = 0
    speed: float = 1.0
    duration: float | None = None
    demand_timeout_cycles: float | None = None
    """The command watchdog's timeout in cycles of the demand (``None``: 3)."""
    plant: Mapping[str, Any] = field(default_factory=dict)
    """The engine's own options, by key (``valve``, ``bp_limit``, ...)."""
    # -- the bus and its frames ---------------------------------------------------------
    bus: str | None = None
    dbc: tuple[str, ...] = ()
    """The user's DBC files or folders, added to the cell's own."""
    # -- the runtime --------------------------------------------------------------------
    cycle: str | None = None
    scripts: tuple[str, ...] = ()
    native: bool = False
    blocks: Mapping[str, Any] = field(default_factory=dict)
    """The block sets' own options, by key (``osc_init``, ``bias_design``, ...)."""
    plausibility: Path | None = None
    """A cell file of signal ranges and rate limits over the DBC's (:mod:`cell.runtime.plausibility`)."""
    designs: tuple[str, ...] = ()
    """Design files (``--design FILE``, repeatable), each naming its observer."""
    maps: tuple[str, ...] = ()
    """A user's signals on the cell's channels (``--map CELL_CHANNEL=SIGNAL`` or a mapping
    file, repeatable; :mod:`cell.runtime.mapping`)."""
    # -- the service --------------------------------------------------------------------
    host: str = "127.0.0.1"
    port: int = 8000
    state: Path | None = None
    """The tuning file; ``None``: the cell's own default (:func:`cell.app.tuning.default_path`)."""
    name: str | None = None
    """The cell's name: its default state folder (``--name``; else engine, bus and port)."""
    no_sim: bool = False
    token: str | None = field(default=None, repr=False)
    """Bearer token every state-changing request needs (``TESTCELL_TOKEN``; never a flag,
    so it does not show in the process list)."""
    protect_reads: bool = False
    """With a token: reads need it too."""
    max_body: int = 1024 * 1024
    """Largest request body in bytes (413 above)."""
    max_script: int = 256 * 1024
    """Largest script in bytes (413 above)."""
    # -- the process --------------------------------------------------------------------
    log_level: str = "INFO"
    plugins: tuple[str, ...] = ()

    # -- building -----------------------------------------------------------------------
    @classmethod
    def keys(cls) -> list[str]:
        """Every setting's key: the fields, then every engine's own options."""
        return ([f.name for f in fields(cls) if f.name not in ("plant", "blocks")]
                + list(engine_options()) + list(block_options()))

    @classmethod
    def build(cls, given: Mapping[str, Any] | None = None,
              environ: Mapping[str, str] | None = None) -> Settings:
        """Settings from ``given`` (e.g. the command line's options) over the environment.

        ``given`` maps keys to values (``None`` values are ignored: an option not given);
        ``environ`` defaults to ``os.environ``. Raises :class:`ConfigError` naming an unknown
        key or ``TESTCELL_*`` variable, or a value that does not parse or pass its check.
        """
        environ = os.environ if environ is None else environ
        fieldnames = {f.name for f in fields(cls)}
        eng = {**engine_options(), **block_options()}
        known = set(cls.keys())
        values: dict[str, Any] = {}
        for var, text in environ.items():
            if not var.startswith(ENV_PREFIX):
                continue
            key = var[len(ENV_PREFIX):].lower()
            if key not in known:
                raise ConfigError(f"{var}: unknown setting {key!r}; known: "
                                  f"{', '.join(ENV_PREFIX + k.upper() for k in sorted(known))}")
            values[key] = cls._parse(var, key, text, eng)
        for key, value in (given or {}).items():
            if key not in known:
                raise ConfigError(f"unknown setting {key!r}; known: {', '.join(sorted(known))}")
            if value is not None:
                values[key] = value
        own = engine_options()
        plant = {k: values.pop(k) for k in list(values) if k in own and k not in fieldnames}
        blocks = {k: values.pop(k) for k in list(values) if k in eng and k not in fieldnames}
        settings = cls(**values, plant=plant, blocks=blocks)
        settings.check()
        return settings

    @staticmethod
    def _parse(var: str, key: str, text: str, eng: Mapping[str, tuple[Option, list[str]]]
               ) -> Any:
        parse = eng[key][0].type if key in eng else _ENV_PARSERS.get(key, str)
        try:
            return parse(text)
        except ValueError as exc:
            raise ConfigError(f"{var}={text!r}: {exc}") from None

    @classmethod
    def from_args(cls, args: argparse.Namespace, environ: Mapping[str, str] | None = None
                  ) -> Settings:
        """Settings from a parsed command line: every option that is a setting key."""
        known = set(cls.keys())
        given = {k: v for k, v in vars(args).items() if k in known}
        for key in ("dbc", "scripts", "plugins", "designs", "maps"):
            if given.get(key) is not None:
                given[key] = tuple(str(p) for p in given[key])
        for key in ("native", "no_sim"):
            if given.get(key) is False:
                given[key] = None  # a flag not given leaves the environment's value
        return cls.build(given, environ)

    def check(self) -> None:
        """Validate every value; :class:`ConfigError` names the option."""
        for key in ("max_body", "max_script"):
            value = getattr(self, key)
            if not isinstance(value, int) or not 1024 <= value <= 64 * 1024 * 1024:
                raise ConfigError(f"TESTCELL_{key.upper()} must be 1024..67108864 bytes, got {value}")
        if self.token is not None and not self.token.strip():
            raise ConfigError("TESTCELL_TOKEN is empty: set a token, or unset the variable")
        if self.name is not None and not _NAME_OK(self.name):
            raise ConfigError(f"--name {self.name!r}: a cell's name is 1-64 letters, digits, "
                              f"'.', '_' or '-', not starting with '.'")
        if self.log_level not in LOG_LEVELS:
            raise ConfigError(f"--log-level {self.log_level!r}: choose one of {', '.join(LOG_LEVELS)}")
        by_key = {o.key: o for o in SIM_OPTIONS}
        for key in ("speed", "duration", "demand_timeout_cycles"):
            by_key[key].validate(getattr(self, key))
        if self.engine is not None:
            profile = registry.engine_profile(self.engine)
            if self.duty is not None and profile.duties and self.duty not in profile.duties:
                raise ConfigError(f"--duty {self.duty!r} is not a duty cycle of {profile.name}; "
                                  f"choose one of: {', '.join(profile.duties)}")
        eng = engine_options()
        for key, value in self.plant.items():
            opt, engines = eng[key]
            opt.validate(value)
            if self.engine is not None and self.engine not in engines:
                raise ConfigError(f"{opt.flag} is an option of {', '.join(engines)}, not of "
                                  f"{self.engine}")
        own = block_options()
        for key, value in self.blocks.items():
            own[key][0].validate(value)

    # -- using ----------------------------------------------------------------------------
    def for_simulator(self) -> Settings:
        """These settings with the engine and duty cycle resolved to their defaults."""
        engine = self.engine or registry.DEFAULT_ENGINE
        profile = registry.engine_profile(engine)
        resolved = replace(self, engine=engine, duty=self.duty or profile.default_duty)
        if self.engine is None:
            resolved.check()  # an engine's own option given without --engine: the default's?
        return resolved

    def sim_argv(self, bus: str) -> list[str]:
        """``testcell sim`` arguments that hand the simulator every simulator setting."""
        s = self.for_simulator()
        argv = ["--bus", bus]
        for opt in SIM_OPTIONS:
            value = getattr(s, opt.key)
            if value is not None:
                argv += [opt.flag, str(value)]
        eng = engine_options()
        for key, value in s.plant.items():
            opt = eng[key][0]
            if opt.switch:
                argv += [opt.flag] if value else []
            elif value is not None:
                argv += [opt.flag, str(value)]
        for path in s.dbc:
            argv += ["--dbc", path]
        return argv
