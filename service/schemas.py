"""Response schemas of the HTTP API."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field


class ChannelOut(BaseModel):
    name: str
    value: float | None
    unit: str
    time: float | None
    status: Literal["ok", "stale", "invalid"]
    reason: str | None = None
    source: str


class HistoryPoint(BaseModel):
    time: float
    value: float | None
    status: Literal["ok", "stale", "invalid"]


class HistoryOut(BaseModel):
    name: str
    unit: str
    seconds: float
    points: list[HistoryPoint]


class TripOut(BaseModel):
    state: str
    reason: str
    since: float | None


class HealthOut(BaseModel):
    status: Literal["ok", "waiting", "degraded"]
    reasons: list[str]
    trip: TripOut | None
    bus: str
    frames: int
    frames_per_s: float
    decode_errors: dict[str, int]
    unknown_ids: dict[str, int]
    late_frames: int
    block_errors: dict[str, int]
    withheld: dict[str, int]
    implausible: dict[str, int] = Field(
        default_factory=dict, description="decoded bus values outside their signal's range or "
                                          "rate limit, by signal (they are invalid)")
    unsaved: list[str] = Field(
        default_factory=list, description="changes applied but not saved (a controller switched "
                                          "off while the tuning file could not be written)")
    tick_overruns: int = Field(0, description="ticks whose work took longer than the period of "
                                              "the fastest task in them (also in /metrics)")
    last_frame_time: float | None
    bus_time: float | None
    runtime_running: bool
    streams: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="per crank-angle sample stream consumed by a block: frames, samples, "
                    "reordered (put back in order), late (dropped), lost_frames, gaps and the "
                    "last gap")


class BlockOut(BaseModel):
    name: str
    kind: str
    family: str
    rate: str
    rates: list[str]
    inputs: list[str]
    outputs: list[str]
    params: dict[str, Any]
    state: dict[str, Any]


class TunedOut(BlockOut):
    """A block after a ``PATCH``, with what did not go as asked (applied but not saved)."""

    warnings: list[str] = []


class FamilyOut(BaseModel):
    """A block family: its resource ``/{section}``, what its blocks are, example PATCH
    bodies, and the names of the cell's blocks of that family (empty: no such resource)."""

    name: str = Field(description="the family, as blocks name it (``filter``, ``controller``, ...)")
    section: str = Field(description="its resource: GET /{section}, GET and PATCH /{section}/{name}")
    description: str
    examples: list[dict[str, Any]] = Field(description="parameter changes a PATCH may send")
    blocks: list[str] = Field(description="the cell's blocks of this family, in the order they run")


class ErrorOut(BaseModel):
    """An error: ``detail`` says what was wrong and where (other fields by route)."""

    model_config = ConfigDict(extra="allow")
    detail: Any


#: Error answers any route may give, documented once for the whole API.
ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    400: {"model": ErrorOut, "description": "Bad input (e.g. a script that does not compile)"},
    401: {"model": ErrorOut, "description": "The cell's token is needed (TESTCELL_TOKEN)"},
    404: {"model": ErrorOut, "description": "No such channel, block or script"},
    409: {"model": ErrorOut, "description": "Refused: conflicts with the cell's state"},
    413: {"model": ErrorOut, "description": "Request body or script over its limit"},
}
