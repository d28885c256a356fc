"""``GET /simulator``: what the cell's simulator runs (engine, duty cycle, speed, seed), read-only.

The duty cycle and speed are chosen when the cell starts (``testcell up --engine ..
--duty .. --speed ..``); changing them while it runs is not part of the API yet.
"""

from typing import Any

from fastapi import APIRouter

from ..deps import CellDep

router = APIRouter(tags=["simulator"])


@router.get("/simulator")
def simulator(cell: CellDep) -> dict[str, Any]:
    """The simulator settings the cell was started with (``running``: false with ``--no-sim``
    or when the cell was not started by ``testcell up``)."""
    s = cell.settings
    if s is None:
        return {"running": False, "engine": None, "duty": None, "speed": None, "seed": None,
                "bus": cell.bus, "changeable": []}
    return {"running": not s.no_sim, "engine": s.engine, "duty": s.duty, "speed": s.speed,
            "seed": s.seed, "bus": cell.bus, "changeable": []}
