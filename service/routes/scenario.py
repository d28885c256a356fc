"""``/scenario``: scenario commands to the simulator, as CAN frames (see :mod:`cell.bus.scenario`)."""

from typing import Any

from fastapi import APIRouter, Body

from cell.core import registry

from ..deps import CellDep

#: The bus signals each engine's plants read (its composition's external inputs), by engine.
_READ: dict[str, frozenset[str]] = {}


def engine_reads(settings: Any) -> frozenset[str] | None:
    """The signals the running simulator's engine reads from the bus; ``None`` when the cell
    runs no simulator of its own (``--no-sim``) or its engine is not known."""
    if settings is None or getattr(settings, "no_sim", False):
        return None
    name = getattr(settings, "engine", None) or registry.DEFAULT_ENGINE
    if name not in _READ:
        try:
            composition = registry.engine_profile(name).build(settings.for_simulator())
        except Exception:  # an engine that cannot be built here: say nothing about it
            return None
        _READ[name] = frozenset(composition.external)
    return _READ[name]

router = APIRouter(prefix="/scenario", tags=["scenario"])


@router.get("", name="list scenario keys",
            description="Every scenario key of the DBC files: the signal it sets, its range, "
                        "unit and start value, and `read_by_engine`: whether the running "
                        "simulator's engine reads that signal (`null` with no simulator of "
                        "the cell's own).")
def list_keys(cell: CellDep) -> list[dict[str, Any]]:
    reads = engine_reads(cell.settings)
    return [{**k, "read_by_engine": None if reads is None else k["signal"] in reads}
            for k in cell.scenario_keys()]


@router.post("", name="send a scenario command",
             description="Encode the scenario message(s) carrying the given keys (a key is a "
                         "SCENARIO-to-SIM signal's name in lower case; signals not given take "
                         "their start value) and put them on the bus. 422 names an unknown key "
                         "or a value outside its DBC range; nothing is sent then.")
def send(cell: CellDep, values: dict[str, Any] = Body(..., examples=[{"osc": 0.5}])
         ) -> dict[str, Any]:
    return {"sent": cell.send_scenario(values), "bus": cell.bus}
