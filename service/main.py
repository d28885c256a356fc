"""The FastAPI application of a running cell."""

from collections.abc import Callable

from fastapi import APIRouter, FastAPI
from fastapi_offline import FastAPIOffline
from starlette.middleware.trustedhost import TrustedHostMiddleware

from cell import __version__
from cell.app import load as load_cell_parts
from cell.core import registry
from cell.app.cell import Cell

from . import errors
from .metrics import FrameRates, Metrics
from .routes import (channels, engine, families, filters, health, messages, metrics, observers,
                     page, scenario, scripts, simulator, stream)
from .schemas import ERROR_RESPONSES
from .security import Security, SecurityMiddleware
from .stream import StreamHub
from .routes.blocks import block_router

#: Routes a block family has beyond GET/PATCH, by family name.
FAMILY_ROUTES: dict[str, Callable[[APIRouter], None]] = {"filter": filters.add_routes,
                                                         "observer": observers.add_routes}
#: Where Swagger UI's and ReDoc's own files are served.
DOCS_ASSETS = "/static/docs"


def create_app(cell: Cell, security: Security | None = None) -> FastAPI:
    """The app of ``cell``: one router per block family the cell has, plus the fixed ones.

    ``security`` (default: from the cell's settings, else open with the default limits)
    decides who may change the cell and how large a request may be (:mod:`service.security`).
    """
    # /docs and /redoc from Swagger UI's and ReDoc's files shipped in the fastapi-offline
    # package (no CDN: a test-cell network often has no internet), under /static/ so that
    # they load without a token as the page's own files do
    app = FastAPIOffline(
        static_url=DOCS_ASSETS,
        title="testcell",
        version=__version__,
        description="Live values and tuning of an emulated engine test cell that speaks CAN.",
        responses=ERROR_RESPONSES,
    )
    load_cell_parts()
    app.state.cell = cell
    app.state.hub = StreamHub(cell)
    app.state.frame_rates = FrameRates(cell)
    app.state.metrics = Metrics(cell, app.state.frame_rates, app.state.hub)
    settings = cell.settings
    security = security or (Security.from_settings(settings) if settings else Security())
    app.state.security = security
    app.add_middleware(SecurityMiddleware, security=security)
    # outermost: a request for a host name that is not the cell's (DNS rebinding) gets 400
    app.add_middleware(TrustedHostMiddleware, allowed_hosts=list(security.allowed_hosts),
                       www_redirect=False)
    errors.install(app)
    app.include_router(health.router)
    app.include_router(channels.router)
    app.include_router(messages.router)
    app.include_router(families.router)
    present = {f["name"] for f in cell.families() if f["blocks"]}
    for fam in registry.FAMILIES.values():
        if fam.name in present:
            router = block_router(fam)
            FAMILY_ROUTES.get(fam.name, lambda r: None)(router)
            app.include_router(router)
    app.include_router(scripts.router)
    app.include_router(scenario.router)
    app.include_router(stream.router)
    app.include_router(metrics.router)
    app.include_router(simulator.router)
    app.include_router(engine.router)
    app.include_router(page.router)
    return app
