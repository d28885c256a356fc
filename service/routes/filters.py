"""``/filters``: the moving-average, Kalman and adaptive filters.

``PATCH`` takes ``{"Q": .., "R": ..}`` for a Kalman filter or ``{"samples": ..}`` for a moving
average; ``POST /filters/{name}/autotune`` estimates a Kalman filter's Q and R from its recent
input alone and applies them only when asked.
"""

from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field, StrictBool

from cell.analysis.autotune import apply_refusals, autotune
from cell.core.errors import ConfigError

from ..deps import CellDep


class AutotuneIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    minutes: Annotated[float, Field(gt=0, le=24 * 60, allow_inf_nan=False, strict=True,
                                    description="how much recent input to use")] = 5.0
    method: Literal["ml", "als"] = "ml"
    apply: StrictBool = False


def add_routes(router: APIRouter) -> None:
    """The filter family's own routes, added to its block router."""
    router.post("/{name}/autotune", name="autotune filter")(autotune_filter)


def autotune_filter(name: str, cell: CellDep, body: AutotuneIn | None = None) -> dict[str, Any]:
    """Estimate Q and R from the last ``minutes`` of the filter's input (no truth needed):
    maximum likelihood on the innovations, with a confidence interval. Applied (and saved)
    only with ``"apply": true``, and never when the tuner flags its own estimate (at the edge
    of the search range, too little data, ...): then 409, naming why, and nothing changes."""
    body = body or AutotuneIn()
    block = cell.block("filter", name)
    if block["kind"] != "kalman":
        raise HTTPException(422, detail=[{"loc": ["path", "name"], "type": "value_error",
                                          "msg": f"{name} is a {block['kind']} filter; only "
                                                 "Kalman filters have Q and R"}])
    y = [v for _, v, _ in cell.history(block["inputs"][0], body.minutes * 60.0)]
    rate = cell.period(block["rate"]) ** -1
    try:
        result = autotune(y, rate, body.method)
    except ConfigError as exc:
        raise HTTPException(422, detail=[{"loc": ["body", "minutes"], "type": "value_error",
                                          "msg": str(exc)}]) from None
    out = {**result.to_dict(), "filter": name, "samples_used": len(y), "applied": None}
    if body.apply:
        refused = apply_refusals(result)
        if refused:
            return JSONResponse(status_code=409, content={
                **out, "refused": refused,
                "detail": f"not applied to {name}: " + "; ".join(refused)})
        out["applied"] = cell.tune("filter", name, {"Q": result.Q, "R": result.R})
    return out
