"""One option of an engine or a block set: its settings key, flag, type, default and check.

Engine profiles and block sets declare their own options (:class:`Option`); the command line
offers them and :class:`~cell.core.settings.Settings` reads them from the command line and
from ``TESTCELL_<KEY>``. Nothing here knows which parts declare options.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from cell.core.errors import ConfigError


@dataclass(frozen=True)
class Option:
    """One simulator option: settings key, command-line flag, type, default and check.

    ``check(value)`` returns an error message (the flag is put in front of it) or ``None``.
    """

    key: str
    flag: str
    type: Callable[[str], Any]
    default: Any = None
    help: str = ""
    metavar: str | None = None
    check: Callable[[Any], str | None] | None = None
    switch: bool = False
    """A flag without a value (``--no-pem-sensor``): true when given; ``type`` then reads
    its ``TESTCELL_<KEY>`` value (use :func:`parse_bool`)."""

    def add_to(self, parser: argparse.ArgumentParser, note: str = "") -> None:
        if self.switch:
            parser.add_argument(self.flag, dest=self.key, action="store_true", default=None,
                                help=self.help + note)
            return
        parser.add_argument(self.flag, dest=self.key, type=self.type, default=None,
                            metavar=self.metavar, help=self.help + note)

    def validate(self, value: Any) -> None:
        problem = self.check(value) if self.check is not None and value is not None else None
        if problem:
            raise ConfigError(f"{self.flag} {problem}")


def _bool(text: str) -> bool:
    t = str(text).strip().lower()
    if t in ("1", "true", "yes", "on"):
        return True
    if t in ("0", "false", "no", "off", ""):
        return False
    raise ValueError(f"not a yes/no value: {text!r}")


#: Reads a yes/no setting (``1/0``, ``true/false``, ``yes/no``, ``on/off``).
parse_bool = _bool


def _words(text: str) -> tuple[str, ...]:
    return tuple(w.strip() for w in str(text).split(",") if w.strip())


#: Reads a comma-separated list setting (``a.dbc,b.dbc``).
words = _words
