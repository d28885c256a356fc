"""``/scenario``: scenario commands to the simulator, as CAN frames (see :mod:`cell.bus.scenario`)."""

from typing import Any

from fastapi import APIRouter, Body

from ..deps import CellDep

router = APIRouter(prefix="/scenario", tags=["scenario"])


@router.get("", name="list scenario keys",
            description="Every scenario key of the DBC files: the signal it sets, its range, "
                        "unit and start value.")
def list_keys(cell: CellDep) -> list[dict[str, Any]]:
    return cell.scenario_keys()


@router.post("", name="send a scenario command",
             description="Encode the scenario message(s) carrying the given keys (a key is a "
                         "SCENARIO-to-SIM signal's name in lower case; signals not given take "
                         "their start value) and put them on the bus. 422 names an unknown key "
                         "or a value outside its DBC range; nothing is sent then.")
def send(cell: CellDep, values: dict[str, Any] = Body(..., examples=[{"osc": 0.5}])
         ) -> dict[str, Any]:
    return {"sent": cell.send_scenario(values), "bus": cell.bus}
