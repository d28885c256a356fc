from fastapi import APIRouter

from ..deps import CellDep
from ..schemas import HealthOut

router = APIRouter(tags=["health"])


@router.get("/health", response_model=HealthOut)
def health(cell: CellDep) -> HealthOut:
    """Bus, frame rate, decode errors by kind, the time of the last frame, and the sample
    streams' order and loss counts."""
    h = cell.runtime.health()
    return HealthOut(
        status="ok" if h["frames"] else "waiting",
        bus=cell.bus,
        runtime_running=cell.live.running if cell.live else False,
        **h,
    )
