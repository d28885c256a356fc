"""``/engine``: operator commands to the engine on the bus (reset a trip)."""

from typing import Any

from fastapi import APIRouter

from ..deps import CellDep

router = APIRouter(prefix="/engine", tags=["engine"])


@router.post("/reset")
def reset_engine(cell: CellDep) -> dict[str, Any]:
    """Reset a trip of the engine protection: sends ``ENGINE_RESET`` with a new counter
    value (the simulator re-arms the protection and restarts the engine). ``/health`` shows
    the trip until the engine reports it is running again."""
    value = cell.reset_trip()
    return {"sent": {"ENGINE_RESET": value}, "trip": cell.trip()}
