from fastapi import APIRouter, Request

from ..deps import CellDep
from ..schemas import HealthOut

router = APIRouter(tags=["health"])


@router.get("/health", response_model=HealthOut)
def health(cell: CellDep, request: Request) -> HealthOut:
    """Status (``ok``, ``waiting``, ``failed`` with the reason while the live loop is stopped,
    restarting or stalled, or ``degraded`` with the reasons: bus silent or lost, the engine
    tripped, a change applied but not saved, frames lost, lag, tick overruns per minute, a
    faulted block, a recent stall, the simulator process exited, a second sender on the bus),
    block faults and their backoff, the live loop's counts, frame rate, bad frames by kind,
    unknown frame IDs, block errors, outputs withheld for not being finite, implausible bus
    values by signal, the time of the last frame, and the sample streams' order and loss counts."""
    report = cell.health()
    sim = getattr(request.app.state, "simulator", None)  # testcell up's supervised child
    if sim is not None:
        report["simulator"] = sim.status()
        lost = sim.reasons()
        if lost:
            report["reasons"] = [*lost, *report["reasons"]]
            if report["status"] in ("ok", "waiting"):  # a cell without its simulator is degraded
                report["status"] = "degraded"
    return HealthOut(**report)
