"""The FastAPI application of a running cell."""

from collections.abc import Callable

from fastapi import APIRouter, FastAPI

from cell import __version__, registry
from cell.context import Cell

from . import errors
from .routes import channels, filters, health, page, scenario, scripts
from .routes.blocks import block_router

#: Routes a block family has beyond GET/PATCH, by family name.
FAMILY_ROUTES: dict[str, Callable[[APIRouter], None]] = {"filter": filters.add_routes}


def create_app(cell: Cell) -> FastAPI:
    """The app of ``cell``: one router per block family the cell has, plus the fixed ones."""
    app = FastAPI(
        title="testcell",
        version=__version__,
        description="Live values and tuning of an emulated engine test cell that speaks CAN.",
    )
    registry.load_plugins()
    app.state.cell = cell
    errors.install(app)
    app.include_router(health.router)
    app.include_router(channels.router)
    present = {b.family for b in cell.runtime.blocks.values()}
    for fam in registry.FAMILIES.values():
        if fam.name in present:
            router = block_router(fam)
            FAMILY_ROUTES.get(fam.name, lambda r: None)(router)
            app.include_router(router)
    app.include_router(scripts.router)
    app.include_router(scenario.router)
    app.include_router(page.router)
    return app
