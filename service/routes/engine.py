"""``/engine``: operator commands to the engine on the bus (reset a trip, in two steps)."""

from typing import Any

from fastapi import APIRouter
from pydantic import BaseModel, StrictInt

from ..deps import CellDep

router = APIRouter(prefix="/engine", tags=["engine"])


class Confirm(BaseModel):
    """The confirm of a reset request: the challenge ``POST /engine/reset`` returned."""

    challenge: StrictInt


@router.post("/reset")
def reset_engine(cell: CellDep) -> dict[str, Any]:
    """Step one of a trip reset: sends a reset request (``ENGINE_RESET_REQ``) carrying a
    fresh challenge, and returns it. Nothing is reset until ``POST /engine/reset/confirm``
    sends that challenge back within ``window_s``; the simulator then clears the trip only
    if its cause has cleared. ``/health`` shows the trip until the engine runs again."""
    step = cell.reset_trip()
    return {**step, "sent": {"ENGINE_RESET_REQ": step["challenge"]},
            "confirm": "/engine/reset/confirm", "trip": cell.trip()}


@router.post("/reset/confirm")
def confirm_reset(body: Confirm, cell: CellDep) -> dict[str, Any]:
    """Step two: sends the confirm (``ENGINE_RESET_CONFIRM``) of the pending request; 422
    (nothing sent) when ``challenge`` is not the pending request's."""
    value = cell.confirm_reset(body.challenge)
    return {"sent": {"ENGINE_RESET_CONFIRM": value}, "trip": cell.trip()}
