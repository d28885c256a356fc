"""``GET /simulator``: what the cell's simulator runs (engine, duty cycle, speed, seed), and
whether its process runs, read-only.

The duty cycle and speed are chosen when the cell starts (``testcell up --engine ..
--duty .. --speed ..``); changing them while it runs is not part of the API yet. The
process is supervised by ``up`` (:mod:`service.simproc`): ``running`` is whether it runs now,
with ``pid``, ``restarts`` and the last exit (``exit_code``, ``signal``, ``last_exit``).
"""

from typing import Any

from fastapi import APIRouter, Request

from ..deps import CellDep

router = APIRouter(tags=["simulator"])


@router.get("/simulator")
def simulator(cell: CellDep, request: Request) -> dict[str, Any]:
    """The simulator settings the cell was started with (``running``: false with ``--no-sim``,
    when the cell was not started by ``testcell up``, or while the process is down)."""
    s = cell.settings
    if s is None:
        return {"running": False, "engine": None, "duty": None, "speed": None, "seed": None,
                "bus": cell.bus, "changeable": []}
    out = {"running": not s.no_sim, "engine": s.engine, "duty": s.duty, "speed": s.speed,
           "seed": s.seed, "bus": cell.bus, "changeable": []}
    sim = getattr(request.app.state, "simulator", None)  # the process testcell up started
    if sim is not None:
        out.update(sim.status())
    return out
