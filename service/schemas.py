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


class LoopOut(BaseModel):
    """The live loop: running, its problem now, restarts, stalls, lag, dropped stale outputs
    and the kernel's drop count of the bus socket (``None``: not reported by this bus)."""

    running: bool
    problem: str | None
    restarts: int
    last_error: str | None
    stalls: int = Field(description="passes of the loop that came more than stall_limit_s late")
    last_stall_s: float | None
    last_stall_end: float | None = Field(description="wall clock (Unix time) the last stall ended")
    lag_s: float | None = Field(description="seconds the runtime's bus time is behind the wall "
                                            "clock's estimate of it")
    dropped_stale: int = Field(description="output frames not sent for being more than one cycle "
                                           "older than the bus time (after a stall)")
    kernel_drops: int | None = Field(description="datagrams the kernel dropped on the bus socket; "
                                                 "null: not available on this bus or platform")
    stall_limit_s: float


class HealthOut(BaseModel):
    status: Literal["ok", "waiting", "degraded", "failed"]
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
    tick_overruns_per_min: int = Field(0, description="tick overruns over the last minute of bus time")
    block_faults: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="per block that has faulted: faults by kind (refused, exception, nonfinite), "
                    "the last reason, kind and bus time, the streak of exceptions, whether it is "
                    "backing off, its retry time and backoff, and its resets")
    frames_lost: dict[str, Any] = Field(
        default_factory=dict,
        description="missed cycles of cyclic messages (in all, over the last minute, by message) "
                    "and outages (gaps over 1 s) by message")
    listener_errors: dict[str, int] = Field(default_factory=dict)
    encode_errors: dict[str, int] = Field(default_factory=dict)
    loop: LoopOut | None = Field(None, description="the live loop (null: an offline cell)")
    limits: dict[str, float] = Field(default_factory=dict,
                                     description="thresholds past which the status is degraded")
    simulator: dict[str, Any] | None = Field(
        None, description="testcell up's simulator process: running, pid, restarts, the last "
                          "exit (exit_code, signal) and what up does then (on_sim_exit)")
    conflicts: dict[str, int] = Field(
        default_factory=dict,
        description="frames of a simulator message beyond its cycle rate (a second sender on "
                    "the bus), by message; /health is degraded and names it while it lasts")
    undecodable: int = Field(0, description="datagrams or frames received that could not be "
                                            "decoded (not a CAN frame at all), skipped")
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
    403: {"model": ErrorOut, "description": "A change from a foreign Origin (another site's page)"},
    404: {"model": ErrorOut, "description": "No such channel, block or script"},
    409: {"model": ErrorOut, "description": "Refused: conflicts with the cell's state"},
    413: {"model": ErrorOut, "description": "Request body or script over its limit"},
    415: {"model": ErrorOut, "description": "A change whose Content-Type is not application/json "
                                            "(a script's source may be text/plain)"},
}
