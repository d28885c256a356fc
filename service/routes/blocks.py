"""One router shape for every tunable block family: filters, controllers, observers."""

from typing import Any

from fastapi import APIRouter, Body

from ..deps import CellDep
from ..schemas import BlockOut


def block_router(family: str, prefix: str, examples: list[dict[str, Any]]) -> APIRouter:
    """``GET {prefix}``, ``GET {prefix}/{name}`` and ``PATCH {prefix}/{name}`` for ``family``."""
    router = APIRouter(prefix=prefix, tags=[prefix.strip("/")])

    @router.get("", response_model=list[BlockOut], name=f"list {family}s")
    def list_blocks(cell: CellDep) -> list[BlockOut]:
        rt = cell.runtime
        with rt.lock:
            return [BlockOut(**rt.block(n).describe()) for n in cell.names(family)]

    @router.get("/{name}", response_model=BlockOut, name=f"get {family}")
    def get_block(name: str, cell: CellDep) -> BlockOut:
        with cell.runtime.lock:
            return BlockOut(**cell.find(family, name).describe())

    @router.patch("/{name}", response_model=BlockOut, name=f"tune {family}")
    def patch_block(name: str, cell: CellDep,
                    changes: dict[str, Any] = Body(..., examples=examples)) -> BlockOut:
        """Change parameters; validated as a whole, effective at the next tick, saved."""
        cell.tune(family, name, changes)
        with cell.runtime.lock:
            return BlockOut(**cell.find(family, name).describe())

    return router
