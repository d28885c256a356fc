"""``/observers``: the family's own route beyond ``GET``/``PATCH``.

``PUT /observers/{name}/design`` loads a design live (the JSON a ``testcell design`` tool
writes, naming its observer): validated as a whole, 422 naming the field on a bad one, and
the previous design kept; 404 for an unknown observer.
"""

from typing import Any

from fastapi import APIRouter, Body, HTTPException

from cell.core.errors import ConfigError

from ..deps import CellDep
from ..schemas import BlockOut


def add_routes(router: APIRouter) -> None:
    """The observer family's own routes, added to its block router."""
    router.put("/{name}/design", response_model=BlockOut, name="load observer design")(put_design)


def put_design(name: str, cell: CellDep,
               design: dict[str, Any] = Body(..., examples=[{"observer": "twc", "identified": {
                   "lambda_lag": "composition", "tau_lambda": 0.12}}])) -> BlockOut:
    """Load a design into the observer; the estimate restarts from it at the next tick."""
    try:
        cell.load_design(name, design, source=f"PUT /observers/{name}/design")
    except ConfigError as exc:
        raise HTTPException(status_code=422, detail=str(exc)) from None
    return BlockOut(**cell.block("observer", name))
