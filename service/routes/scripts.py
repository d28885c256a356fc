"""``/scripts``: the cell's PUMA-style (``.fdv``) and CyFlex-style (``.labels``/``.ravg``) scripts."""

import re
from typing import Any

from fastapi import APIRouter, HTTPException, Request, Response
from fastapi.responses import JSONResponse

from cell.app.cell import Cell
from cell.core.errors import ConfigError, ParamError
from cell.scripts import ScriptError
from cell.scripts.manager import ScriptManager

from ..deps import CellDep

router = APIRouter(prefix="/scripts", tags=["scripts"])
NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,99}\.(fdv|labels|ravg)$")


def _manager(cell: Cell) -> ScriptManager:
    mgr = cell.scripts
    if mgr is None:
        raise HTTPException(404, detail="this cell runs no scripts")
    return mgr


def _summary(d: dict[str, Any]) -> dict[str, Any]:
    return {k: d[k] for k in ("name", "dialect", "rates", "inputs", "outputs", "constants",
                               "errors", "shipped")}


@router.get("")
def list_scripts(cell: CellDep) -> list[dict[str, Any]]:
    """Every script: dialect, inputs, outputs, constants and current errors."""
    mgr = _manager(cell)
    return [_summary(mgr.describe(n)) for n in mgr.names()]


@router.get("/{name}")
def get_script(name: str, cell: CellDep) -> dict[str, Any]:
    """Source, dialect, outputs with their status, constants and errors."""
    return _manager(cell).describe(_manager(cell).block_name(name))


@router.put("/{name}", openapi_extra={"requestBody": {"content": {"text/plain": {}}, "required": True}})
async def put_script(name: str, request: Request, cell: CellDep) -> JSONResponse:
    """Create or replace a script from its text (the body). The dialect comes from the
    name's suffix. It compiles now and is swapped in at the next tick; outputs whose formulas
    did not change keep their state. A script that does not compile gets 400 with every
    error (file:line:column), and the running one stays. An input that no channel provides
    is named in ``warnings``."""
    mgr = _manager(cell)
    if not NAME.match(name):
        raise HTTPException(422, detail=[{"loc": ["path", "name"], "type": "value_error",
                                          "msg": "a script name is letters, digits, _ . - and "
                                                 "ends in .fdv, .labels or .ravg"}])
    raw = await request.body()
    limit = request.app.state.security.max_script_bytes
    if len(raw) > limit:
        raise HTTPException(413, detail=f"{name} is {len(raw)} bytes; the limit for a script is "
                                        f"{limit} bytes (TESTCELL_MAX_SCRIPT)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise HTTPException(400, detail=f"the script is not UTF-8 text: byte {exc.start}") from None
    existed = mgr.block_name(name) in mgr.names()
    try:
        block, kept = mgr.put(name, text)
    except ScriptError as exc:
        return JSONResponse(status_code=400, content={
            "detail": f"{name} does not compile; the running script is unchanged",
            "errors": [e.as_dict() for e in exc.errors]})
    except ConfigError as exc:
        return JSONResponse(status_code=409, content={"detail": str(exc)})
    body = mgr.describe(block.name) | {"kept_state": kept}
    body["warnings"] = [f"input {i} is not a channel of this cell (no DBC signal, no block "
                        f"output): the outputs that read it stay stale until a channel {i} exists"
                        for i in mgr.unknown_inputs(block.name)]
    return JSONResponse(status_code=200 if existed else 201, content=body)


@router.patch("/{name}")
def patch_script(name: str, cell: CellDep, body: dict[str, Any]) -> dict[str, Any]:
    """Change script constants without editing the text: ``{"constants": {"Q_EXH_BP_R": 4e-6}}``.
    Takes effect at the next tick and is saved."""
    mgr = _manager(cell)
    extra = set(body) - {"constants"}
    if extra or not isinstance(body.get("constants"), dict):
        field = sorted(extra)[0] if extra else "constants"
        raise ParamError(field, 'the body is {"constants": {NAME: number, ...}}')
    consts = mgr.set_constants(mgr.block_name(name), body["constants"])
    return {"name": mgr.block_name(name), "constants": consts}


@router.delete("/{name}", status_code=204)
def delete_script(name: str, cell: CellDep) -> Response:
    """Remove a script and its outputs (a removed shipped script stays removed)."""
    _manager(cell).delete(name)
    return Response(status_code=204)
