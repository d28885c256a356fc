"""Loading scripts by name: the dialect registry and the shipped scripts.

The dialect of a script comes from the suffix of its name (``.fdv``, ``.labels``,
``.ravg``); :data:`DIALECTS` maps each suffix to its loader. The shipped scripts
(seed 004's Kalman filters of Figures 2-3 and 5-6, and a moving average in each dialect)
are package data in ``cell/scripts/shipped/``.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib import resources
from typing import Any

from cell.scripts.block import ScriptBlock
from cell.scripts.cyflex import CyflexBlock
from cell.scripts.errors import ScriptError
from cell.scripts.fdv import FdvBlock

Loader = Callable[[str, str, "str | None", Any], ScriptBlock]


def _load_fdv(name: str, text: str, ravg_text: str | None, rates: Any) -> ScriptBlock:
    if ravg_text is not None:
        raise ScriptError(name, 1, 1, "a .fdv script takes no running-average file")
    return FdvBlock(name, text, rates=rates)


def _load_labels(name: str, text: str, ravg_text: str | None, rates: Any) -> ScriptBlock:
    return CyflexBlock(name, text, ravg_text, rates=rates)


def _load_ravg(name: str, text: str, ravg_text: str | None, rates: Any) -> ScriptBlock:
    """A ``.ravg`` file on its own: a set with running averages and no labels."""
    if ravg_text is not None:
        raise ScriptError(name, 1, 1, "a .ravg script is itself the running-average file")
    return CyflexBlock(name, "", text, rates=rates, ravg_name=name)


#: Script-name suffix -> loader ``(name, text, ravg_text, rates) -> ScriptBlock``.
DIALECTS: dict[str, Loader] = {
    ".fdv": _load_fdv,
    ".labels": _load_labels,
    ".ravg": _load_ravg,
}


def suffix_of(name: str) -> str:
    dot = name.rfind(".")
    return name[dot:].lower() if dot >= 0 else ""


def load_script(
    name: str, text: str, ravg_text: str | None = None, rates: Any = None
) -> ScriptBlock:
    """Compile a script; its dialect comes from the suffix of ``name``.

    Parameters
    ----------
    name:
        Script name such as ``kalman.fdv`` or ``kalman.labels``; becomes the block name.
    text:
        The script text.
    ravg_text:
        For a ``.labels`` script, the Running Averages file of the same stem (seed 004,
        Figure 2), or ``None``.
    rates:
        FAS/MED/SLO rates in Hz (mapping or :class:`cell.runtime.scheduler.Rates`); default 50/10/1.

    Raises
    ------
    ScriptError
        Unknown suffix, or the script does not compile (``errors`` lists every error).
    """
    if not isinstance(name, str) or not name:
        raise ScriptError(str(name), 1, 1, "a script needs a name ending in "
                          + ", ".join(DIALECTS))
    loader = DIALECTS.get(suffix_of(name))
    if loader is None:
        got = suffix_of(name) or "no suffix"
        raise ScriptError(name, 1, 1, f"unknown script dialect {got!r}; known suffixes: "
                          + ", ".join(DIALECTS), expected="a name ending in " + ", ".join(DIALECTS))
    return loader(name, text, ravg_text, rates)


#: Shipped scripts: (name, companion .ravg file or None).
SHIPPED = (
    ("kalman.fdv", None),
    ("kalman.labels", "kalman.ravg"),
    ("maf.fdv", None),
    ("maf.labels", "maf.ravg"),
)


def shipped_scripts() -> list[tuple[str, str, str | None]]:
    """The shipped scripts as ``(name, text, ravg_text)``, ready for :func:`load_script`."""
    folder = resources.files(__package__).joinpath("shipped")
    out = []
    for name, ravg in SHIPPED:
        text = folder.joinpath(name).read_text(encoding="utf-8")
        ravg_text = folder.joinpath(ravg).read_text(encoding="utf-8") if ravg else None
        out.append((name, text, ravg_text))
    return out


def load_shipped(rates: Any = None) -> list[ScriptBlock]:
    """Compile every shipped script."""
    return [load_script(n, t, r, rates) for n, t, r in shipped_scripts()]
