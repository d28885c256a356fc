"""Turning the cell's errors into HTTP answers that name what was wrong."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from cell.core.errors import ConfigError, ParamError, UnknownBlockError


def install(app: FastAPI) -> None:
    @app.exception_handler(UnknownBlockError)
    async def _unknown(request: Request, exc: UnknownBlockError) -> JSONResponse:
        return JSONResponse(status_code=404, content={"detail": str(exc)})

    @app.exception_handler(ParamError)
    async def _param(request: Request, exc: ParamError) -> JSONResponse:
        return JSONResponse(
            status_code=422,
            content={"detail": [{"loc": ["body", exc.field], "msg": exc.message,
                                 "type": "value_error"}]},
        )

    @app.exception_handler(ConfigError)
    async def _config(request: Request, exc: ConfigError) -> JSONResponse:
        return JSONResponse(status_code=500, content={"detail": str(exc)})
