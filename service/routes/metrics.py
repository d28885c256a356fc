"""``GET /metrics``: Prometheus text format (see :mod:`service.metrics`)."""

from fastapi import APIRouter, Request
from fastapi.responses import Response

from .. import metrics

router = APIRouter(tags=["health"])


@router.get("/metrics", response_class=Response,
            responses={200: {"content": {metrics.CONTENT_TYPE: {}},
                             "description": "the exposition text"}})
def get_metrics(request: Request) -> Response:
    """Frames/s and frames by ID, decode errors by kind, ticks and their duration histogram,
    overruns, per-block step time, errors, faults and backoff, lost frames, the live loop's
    stalls, lag and dropped stale outputs, frame-to-API latency and stream clients, in the
    Prometheus text exposition format."""
    return Response(request.app.state.metrics.render(), media_type=metrics.CONTENT_TYPE)
