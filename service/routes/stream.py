"""``WS /stream`` and ``GET /stream/sse``: channel values at every MED tick, pushed.

WebSocket protocol (JSON text messages)
---------------------------------------
Connect to ``/stream`` (optionally ``/stream?channels=EXH_BP_*,ENGINE_SPEED``; with reads
protected, offer the token as the subprotocol ``token.<TOKEN>``, which is echoed back; a
``?token=`` in the URL is refused, see :mod:`service.security`), then send::

    {"subscribe": ["EXH_BP_R", "EXH_BP_*_Kalman"]}     add names or glob patterns
    {"unsubscribe": ["EXH_BP_*_Kalman"]}               remove patterns given before

The server answers a subscription with ``{"type": "subscribed", "patterns": [...],
"channels": [{"name", "unit", "source"}...], "unmatched": [...]}`` and a ``snapshot`` of the
current values, then sends one message per MED tick::

    {"type": "data", "seq": 812, "time": 81.2,
     "values": {"EXH_BP_R": [681.3, "ok", 81.19]}, "dropped": 0}

``values`` maps each subscribed channel to ``[value, status, time]``: status is ``ok``,
``stale`` or ``invalid``, time is the bus time of the value (a stale channel keeps its last
value and time). ``seq`` counts ticks; a client too slow to keep up skips the oldest ticks
and gets the newest: ``dropped`` is how many it has missed so far, and each new skip is
also told with ``{"type": "dropped", "count": n, "total": N}``. A bad request gets
``{"type": "error", "message": ...}`` and the connection stays open.

Server-Sent Events
------------------
``GET /stream/sse?channels=EXH_BP_*`` streams the same ``subscribed`` and ``data``
messages as SSE events (``event: data``, ``id: <seq>``); ``count=N`` ends the stream after
N data events (``curl -N 'http://127.0.0.1:8000/stream/sse?channels=EXH_BP_R&count=5'``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import StreamingResponse

from .. import stream as _stream
from ..security import websocket_token_protocol
from ..stream import Client, StreamHub, SubscriptionError, TooManyClients, match, parse_patterns

router = APIRouter(tags=["stream"])

#: seconds without ticks after which an SSE stream sends a keep-alive comment
KEEPALIVE_S = 15.0


def _hub(app: Any) -> StreamHub:
    return app.state.hub


def _subscribed(hub: StreamHub, client: Client) -> dict[str, Any]:
    names = client.names(hub.cell.channel_names())
    unmatched = [p for p in client.patterns if not match((p,), names)]
    chans = hub.describe(names)
    return {"type": "subscribed", "patterns": list(client.patterns), "channels": chans,
            "unmatched": unmatched}


def _snapshot(hub: StreamHub, client: Client) -> dict[str, Any]:
    now, values = hub.current(client.names(hub.cell.channel_names()))
    return {"type": "snapshot", "time": now, "values": values}


@router.websocket("/stream")
async def stream(ws: WebSocket) -> None:
    hub = _hub(ws.app)
    # a browser drops a connection whose offered subprotocol is not echoed back
    await ws.accept(subprotocol=websocket_token_protocol(ws))
    try:
        client = hub.join(())
    except TooManyClients as exc:
        await ws.send_json({"type": "error", "message": str(exc)})
        await ws.close(1013, "too many subscribers")
        return
    try:
        query = ws.query_params.get("channels")
        await ws.send_json({"type": "hello", "time": hub.cell.now, "backlog": client.backlog})
        if query is not None:
            try:
                client.patterns = parse_patterns(query, "channels")
            except SubscriptionError as exc:
                await ws.send_json({"type": "error", "message": str(exc)})
            else:
                await ws.send_json(_subscribed(hub, client))
                await ws.send_json(_snapshot(hub, client))
        writer = asyncio.create_task(_writer(ws, client))
        try:
            await _reader(ws, hub, client)
        finally:
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await writer
    except WebSocketDisconnect:
        pass
    finally:
        hub.leave(client)


async def _reader(ws: WebSocket, hub: StreamHub, client: Client) -> None:
    while True:
        text = await ws.receive_text()
        try:
            req = json.loads(text)
        except ValueError as exc:
            await ws.send_json({"type": "error", "message": f"not JSON: {exc}"})
            continue
        if not isinstance(req, dict) or not req or set(req) - {"subscribe", "unsubscribe"}:
            keys = sorted(set(req) - {"subscribe", "unsubscribe"}) if isinstance(req, dict) else []
            await ws.send_json({"type": "error", "message":
                                (f"unknown key {keys[0]!r}; " if keys else "") +
                                'send {"subscribe": [names or patterns]} or {"unsubscribe": [...]}'})
            continue
        try:
            patterns = list(client.patterns)
            if "subscribe" in req:
                patterns += parse_patterns(req["subscribe"], "subscribe")
            if "unsubscribe" in req:
                gone = parse_patterns(req["unsubscribe"], "unsubscribe")
                unknown = [p for p in gone if p not in patterns]
                if unknown:
                    raise SubscriptionError(f"unsubscribe: {unknown[0]!r} was not subscribed; "
                                            f"subscribed: {', '.join(patterns) or 'nothing'}")
                patterns = [p for p in patterns if p not in gone]
            if len(set(patterns)) > 200:
                raise SubscriptionError("subscribe: at most 200 names or patterns in all")
        except SubscriptionError as exc:
            await ws.send_json({"type": "error", "message": str(exc)})
            continue
        client.patterns = tuple(dict.fromkeys(patterns))
        await ws.send_json(_subscribed(hub, client))
        await ws.send_json(_snapshot(hub, client))


async def _writer(ws: WebSocket, client: Client) -> None:
    while True:
        await client.event.wait()
        client.event.clear()
        if client.hub.closed:
            await ws.close(1001, "the cell is shutting down")
            return
        before = client.dropped
        records = client.take()
        if not client.patterns:
            continue
        if client.dropped > before:
            await ws.send_json({"type": "dropped", "count": client.dropped - before,
                                "total": client.dropped})
        for rec in records:
            await ws.send_text(client.message(rec))
            client.sent += 1
            ws.app.state.metrics.served("stream", rec.newest.get(client.patterns))


@router.get("/stream/sse", name="stream as server-sent events", response_class=StreamingResponse,
            responses={200: {"content": {"text/event-stream": {}},
                             "description": "subscribed, snapshot, data and dropped events"}})
async def stream_sse(
    request: Request,
    channels: Annotated[str, Query(description="comma-separated channel names or glob patterns, "
                                               "e.g. EXH_BP_*,ENGINE_SPEED")],
    count: Annotated[int | None, Query(ge=1, le=1_000_000,
                                       description="end after this many data events")] = None,
) -> StreamingResponse:
    """The channels' values at every MED tick, as Server-Sent Events (``text/event-stream``)."""
    hub = _hub(request.app)
    try:
        patterns = parse_patterns(channels, "channels")
    except SubscriptionError as exc:
        raise HTTPException(422, detail=[{"loc": ["query", "channels"], "type": "value_error",
                                          "msg": str(exc)}]) from None
    if len(hub.clients) >= _stream.MAX_CLIENTS:
        raise HTTPException(503, detail=f"the cell already streams to {len(hub.clients)} subscribers "
                                        f"(at most {_stream.MAX_CLIENTS}); try again later")
    return StreamingResponse(_sse(request, hub, patterns, count), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


async def _sse(request: Request, hub: StreamHub, patterns: tuple[str, ...],
               count: int | None) -> AsyncIterator[str]:
    # joined here, not in the route: a client gone before the first byte never joins
    try:
        client = hub.join(patterns, kind="sse")
    except TooManyClients as exc:  # filled up since the route looked
        yield f"event: error\ndata: {json.dumps({'type': 'error', 'message': str(exc)})}\n\n"
        return
    try:
        yield f"event: subscribed\ndata: {json.dumps(_subscribed(hub, client))}\n\n"
        yield f"event: snapshot\ndata: {json.dumps(_snapshot(hub, client))}\n\n"
        sent = 0
        while (count is None or sent < count) and not hub.closed:
            try:
                await asyncio.wait_for(client.event.wait(), KEEPALIVE_S)
            except TimeoutError:
                if await request.is_disconnected():
                    return
                yield ": keep-alive\n\n"
                continue
            client.event.clear()
            if hub.closed:
                return
            before = client.dropped
            records = client.take()
            if client.dropped > before:
                told = {"type": "dropped", "count": client.dropped - before, "total": client.dropped}
                yield f"event: dropped\ndata: {json.dumps(told)}\n\n"
            for rec in records:
                yield f"event: data\nid: {rec.seq}\ndata: {client.message(rec)}\n\n"
                sent += 1
                request.app.state.metrics.served("stream", rec.newest.get(client.patterns))
                if count is not None and sent >= count:
                    return
    finally:
        hub.leave(client)
