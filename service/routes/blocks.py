"""One router shape for every tunable block family (filters, controllers, observers, ...)."""

from typing import Any

from fastapi import APIRouter, Body

from cell.core.registry import BlockFamily

from ..deps import CellDep
from ..schemas import BlockOut, TunedOut


def block_router(fam: BlockFamily) -> APIRouter:
    """``GET /{section}``, ``GET /{section}/{name}`` and ``PATCH /{section}/{name}``."""
    family, prefix = fam.name, f"/{fam.section}"
    router = APIRouter(prefix=prefix, tags=[fam.section])

    @router.get("", response_model=list[BlockOut], name=f"list {family}s",
                description=f"Every {family} of the cell ({fam.description}).")
    def list_blocks(cell: CellDep) -> list[BlockOut]:
        return [BlockOut(**b) for b in cell.blocks(family)]

    @router.get("/{name}", response_model=BlockOut, name=f"get {family}")
    def get_block(name: str, cell: CellDep) -> BlockOut:
        return BlockOut(**cell.block(family, name))

    @router.patch("/{name}", response_model=TunedOut, name=f"tune {family}")
    def patch_block(name: str, cell: CellDep,
                    changes: dict[str, Any] = Body(..., examples=list(fam.examples))) -> TunedOut:
        """Change parameters; validated as a whole, effective at the next tick, saved. A
        controller switched off stays off when the tuning file cannot be written (200,
        with the failure in ``warnings`` and ``/health``)."""
        warnings: list[str] = []
        cell.tune(family, name, changes, warnings)
        return TunedOut(**cell.block(family, name), warnings=warnings)

    return router
