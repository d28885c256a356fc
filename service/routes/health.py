from fastapi import APIRouter

from ..deps import CellDep
from ..schemas import HealthOut

router = APIRouter(tags=["health"])


@router.get("/health", response_model=HealthOut)
def health(cell: CellDep) -> HealthOut:
    """Status (``ok``, ``waiting`` or ``degraded`` with the reasons: bus silent or lost, the
    engine tripped, a change applied but not saved), frame rate, bad frames by kind, unknown
    frame IDs, block errors, outputs withheld for not being finite, implausible bus values by
    signal, the time of the last frame, and the sample streams' order and loss counts."""
    return HealthOut(**cell.health())
