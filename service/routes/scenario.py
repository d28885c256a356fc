"""``/scenario``: scenario commands to the simulator, as CAN frames (see :mod:`cell.bus.scenario`)."""

from typing import Any

from fastapi import APIRouter, Body

from cell.bus.scenario import describe_frames, scenario_frames, scenario_keys

from ..deps import CellDep

router = APIRouter(prefix="/scenario", tags=["scenario"])


@router.get("", name="list scenario keys",
            description="Every scenario key of the DBC files: the signal it sets, its range, "
                        "unit and start value.")
def list_keys(cell: CellDep) -> list[dict[str, Any]]:
    return [k.describe() for k in scenario_keys(cell.runtime.db).values()]


@router.post("", name="send a scenario command",
             description="Encode the scenario message(s) carrying the given keys (a key is a "
                         "SCENARIO-to-SIM signal's name in lower case; signals not given take "
                         "their start value) and put them on the bus. 422 names an unknown key "
                         "or a value outside its DBC range; nothing is sent then.")
def send(cell: CellDep, values: dict[str, Any] = Body(..., examples=[{"osc": 0.5}])
         ) -> dict[str, Any]:
    rt = cell.runtime
    with rt.lock:
        now = rt.now
        if cell.live is not None:
            est = cell.live.estimated_bus_time()
            now = est if est is not None else now
        frames = scenario_frames(rt.db, values, now or 0.0)
        rt.outbox.extend(frames)
    return {"sent": describe_frames(rt.db, frames), "bus": cell.bus}
