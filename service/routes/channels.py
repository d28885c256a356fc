import math
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request

from ..deps import CellDep
from ..schemas import ChannelOut, HistoryOut, HistoryPoint

router = APIRouter(prefix="/channels", tags=["channels"])


def _clean(v: Any) -> Any:
    return v if not (isinstance(v, float) and not math.isfinite(v)) else None


def _out(snap: dict[str, Any]) -> ChannelOut:
    return ChannelOut(**{**snap, "value": _clean(snap["value"])})


def _served(request: Request, snaps: list[dict[str, Any]]) -> None:
    """Observe the answer's frame-to-API latency: the age of its newest value."""
    newest = max((s["time"] for s in snaps if s["time"] is not None), default=None)
    request.app.state.metrics.served("channels", newest)


@router.get("", response_model=list[ChannelOut])
def list_channels(cell: CellDep, request: Request) -> list[ChannelOut]:
    """Every channel: bus signals and block outputs, with value, unit, bus time and status
    (every one ``stale``, with the reason, while the live loop is stopped or stalled)."""
    snaps = cell.snapshot()
    out = [_out(s) for s in snaps]
    _served(request, snaps)
    return out


@router.get("/{name}", response_model=ChannelOut)
def get_channel(name: str, cell: CellDep, request: Request) -> ChannelOut:
    snap = cell.channel(name)
    _served(request, [snap])
    return _out(snap)


@router.get("/{name}/history", response_model=HistoryOut)
def channel_history(
    name: str,
    cell: CellDep,
    seconds: Annotated[float, Query(gt=0, le=86_400, allow_inf_nan=False,
                                    description="how far back, in seconds of bus time")] = 60.0,
) -> HistoryOut:
    """The channel's values at each MED tick over the last ``seconds`` (bounded ring buffer)."""
    points = cell.history(name, seconds)
    return HistoryOut(
        name=name,
        unit=cell.channel(name)["unit"],
        seconds=seconds,
        points=[HistoryPoint(time=t, value=_clean(v), status=s) for t, v, s in points],
    )
