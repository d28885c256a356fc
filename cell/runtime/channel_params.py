"""Block parameters that name a channel: refused when the cell has no such channel, or when
its unit is not the one the block needs (issue 24: ``PATCH /controllers/PI_R {"feedback":
"NOPE"}`` froze the valve demand).

A block declares them in :attr:`~cell.runtime.blocks.Block.CHANNEL_PARAMS` (parameter ->
unit, ``""`` for any). A channel is known when the store holds it (a bus signal seen, or a
block's output, a user's signal mapped onto a cell channel with ``--map``) or a DBC file
defines it. A channel of no known unit is refused where a unit is needed: the block could
not tell a kPa signal from an mmH2O one. The error names the channels that would do.
"""

from __future__ import annotations

from typing import Any

from cell.core.errors import ParamError
from cell.runtime.blocks import Block
from cell.runtime.units import key as unit_key


def channel_units(runtime: Any) -> dict[str, str]:
    """Every channel the runtime knows, with its unit (``""``: none known)."""
    units = {name: info.unit for name, info in runtime.db.signals.items()}
    for name, ch in runtime.store.by_name.items():
        units[name] = ch.unit or units.get(name, "")
    return units


def check_channel_params(runtime: Any, block: Block, changes: Any) -> None:
    """Refuse (:class:`ParamError`) a change of ``block`` that names an unknown channel or
    one of the wrong unit; the block's own validation checks everything else."""
    if not isinstance(changes, dict) or not block.CHANNEL_PARAMS:
        return
    units: dict[str, str] | None = None
    for key, unit in block.CHANNEL_PARAMS.items():
        name = changes.get(key)
        if not isinstance(name, str) or not name.strip():
            continue  # not a name (or "" for none): the block words that
        name = name.strip()
        if units is None:
            units = channel_units(runtime)
        want = unit_key(unit)
        fit = sorted(n for n, u in units.items()
                     if (not unit or unit_key(u) == want) and n not in block.outputs)
        which = f"channels in {unit}" if unit else "channels"
        listing = ", ".join(fit) or "none"
        if name not in units:
            raise ParamError(key, f"{name!r} is not a channel of this cell; {which}: {listing}")
        have = units[name]
        if unit and unit_key(have) != want:
            raise ParamError(key, f"{name} is {'in ' + have if have else 'of no known unit'}, "
                                  f"{block.name} needs {unit}; {which}: {listing}")


__all__ = ["channel_units", "check_channel_params"]
