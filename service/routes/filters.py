from typing import Any

from fastapi import APIRouter, Body

from ..deps import CellDep
from ..schemas import BlockOut

router = APIRouter(prefix="/filters", tags=["filters"])


@router.get("", response_model=list[BlockOut])
def list_filters(cell: CellDep) -> list[BlockOut]:
    """Every filter with its parameters and state."""
    rt = cell.runtime
    with rt.lock:
        return [BlockOut(**rt.block(n).describe()) for n in cell.names("filter")]


@router.get("/{name}", response_model=BlockOut)
def get_filter(name: str, cell: CellDep) -> BlockOut:
    rt = cell.runtime
    with rt.lock:
        return BlockOut(**cell.find("filter", name).describe())


@router.patch("/{name}", response_model=BlockOut)
def patch_filter(
    name: str,
    cell: CellDep,
    changes: dict[str, Any] = Body(..., examples=[{"Q": 4e-6, "R": 1e-4}, {"samples": 30}]),
) -> BlockOut:
    """Tune a filter: ``{"Q": .., "R": ..}`` for a Kalman filter, ``{"samples": ..}`` for a
    moving average. Takes effect at the next tick, keeps the estimate, and is saved."""
    cell.tune("filter", name, changes)
    with cell.runtime.lock:
        return BlockOut(**cell.find("filter", name).describe())
