"""Response schemas of the HTTP API."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field


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


class HealthOut(BaseModel):
    status: Literal["ok", "waiting"]
    bus: str
    frames: int
    frames_per_s: float
    decode_errors: dict[str, int]
    late_frames: int
    block_errors: dict[str, int]
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
