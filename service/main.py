"""The FastAPI application of a running cell."""

from fastapi import FastAPI

from cell import __version__
from cell.context import Cell

from . import errors
from .routes import channels, controllers, filters, health, page, scripts


def create_app(cell: Cell) -> FastAPI:
    app = FastAPI(
        title="testcell",
        version=__version__,
        description="Live values and tuning of an emulated engine test cell that speaks CAN.",
    )
    app.state.cell = cell
    errors.install(app)
    for router in (health.router, channels.router, filters.router, controllers.router,
                   scripts.router, page.router):
        app.include_router(router)
    return app
