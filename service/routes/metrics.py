"""``GET /metrics``: Prometheus text format (see :mod:`service.metrics`)."""

from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse

from .. import metrics

router = APIRouter(tags=["health"])


@router.get("/metrics", response_class=PlainTextResponse)
def get_metrics(request: Request) -> PlainTextResponse:
    """Frames/s and frames by ID, decode errors by kind, tick overruns, per-block step time
    and stream clients, in the Prometheus text exposition format."""
    app = request.app
    text = metrics.render(app.state.cell, app.state.frame_rates, app.state.hub)
    return PlainTextResponse(text, media_type=metrics.CONTENT_TYPE)
