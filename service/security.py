"""Who may change the cell, and how much a request may carry.

- **Binding.** ``testcell up`` serves on 127.0.0.1 by default; any other address is refused
  unless a token is set (:func:`check_bind`), so a cell is never open to the network by
  accident.
- **Tokens.** With ``TESTCELL_TOKEN`` set, every state-changing request (``POST``, ``PUT``,
  ``PATCH``, ``DELETE``) must carry ``Authorization: Bearer <token>``; reads stay open unless
  ``TESTCELL_PROTECT_READS=1``. A refused request gets 401 before any route runs, so nothing
  changes. Tokens are compared in constant time (:func:`hmac.compare_digest`).
- **WebSocket commands.** A WebSocket route calls :func:`websocket_may_command` (a command
  carries the token as ``{"token": ...}``, or the handshake carried the bearer header) before
  acting on a command; :func:`websocket_may_connect` for the handshake when reads are
  protected.
- **Origin checks (on by default).** A request whose ``Host`` is not one of
  :attr:`Security.allowed_hosts` (the configured host, ``localhost``, ``127.0.0.1``, ``[::1]``
  and ``TESTCELL_ALLOWED_HOSTS``) gets 400 from Starlette's ``TrustedHostMiddleware``, so a
  DNS-rebound name cannot reach the cell. A state-changing request whose ``Origin`` is present
  and not the cell's own (``http://<Host>``) gets 403; it needs ``Content-Type:
  application/json`` or gets 415 (the exceptions: ``PUT /scripts/{name}`` may send its source
  as ``text/plain`` or ``curl --data-binary``'s default type; a ``DELETE`` without a body needs
  no type). A browser sends a cross-origin ``text/plain`` POST without a preflight: the origin
  check is what stops a web page from resetting a trip.
- **WebSocket tokens.** A WebSocket client presents the token as the subprotocol
  ``token.<TOKEN>`` (``Sec-WebSocket-Protocol``; the server echoes it back) or with the
  bearer header, never in the query string: uvicorn's access log records the query, so
  ``?token=`` is refused with close code 1008 and a reason saying where the token goes.
- **Bounded inputs.** A request body over :attr:`Security.max_body_bytes` gets 413, whether
  it declares its length or streams it; scripts have their own limit (``max_script_bytes``).

Everything is one pure ASGI middleware (:class:`SecurityMiddleware`), so routes added later
are covered without a line of their own.
"""

from __future__ import annotations

import hmac
import ipaddress
import json
import os
import socket
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from cell.core.errors import ConfigError

#: Methods that change state: they need the token once one is set.
WRITE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
#: Paths that never need a token (the page itself; it asks for the token in the browser).
OPEN_PATHS = frozenset({"/"})
#: Path prefixes that never need one either: the page's own script and style files (a
#: browser sends no Authorization header for a ``<script src>``).
OPEN_PREFIXES = ("/static/",)
#: Hosts every cell answers to, whatever it binds to.
LOCAL_HOSTS = ("localhost", "127.0.0.1", "[::1]")
#: Further host names (comma-separated) the cell answers to, e.g. behind a proxy.
ALLOWED_HOSTS_ENV = "TESTCELL_ALLOWED_HOSTS"
#: The one body type writes need ...
JSON_TYPE = "application/json"
#: ... and the other one a route may take: (method, path prefix) -> media types.
#: A script's source is text: ``text/plain``, or what ``curl --data-binary`` and other tools
#: send by default. A PUT is never a "simple" cross-origin request (a browser asks first),
#: and the origin check refuses a foreign page's anyway.
TEXT_BODIES = {("PUT", "/scripts/"): frozenset({"text/plain", "application/octet-stream",
                                                "application/x-www-form-urlencoded"})}
#: The subprotocol prefix a WebSocket client carries the token in: ``token.<TOKEN>``.
WS_TOKEN_PREFIX = "token."


@dataclass(frozen=True)
class Security:
    """The service's access rules and size limits (from :class:`cell.core.settings.Settings`)."""

    token: str | None = None
    protect_reads: bool = False
    max_body_bytes: int = 1024 * 1024
    max_script_bytes: int = 256 * 1024
    allowed_hosts: tuple[str, ...] = LOCAL_HOSTS
    """``Host`` names (without port) the cell answers to; others get 400."""

    def __repr__(self) -> str:  # never print the token
        return (f"Security(token={'set' if self.token else None}, protect_reads="
                f"{self.protect_reads}, max_body_bytes={self.max_body_bytes}, "
                f"max_script_bytes={self.max_script_bytes})")

    @classmethod
    def from_settings(cls, settings: Any) -> Security:
        return cls(token=getattr(settings, "token", None) or None,
                   protect_reads=bool(getattr(settings, "protect_reads", False)),
                   max_body_bytes=int(getattr(settings, "max_body", cls.max_body_bytes)),
                   max_script_bytes=int(getattr(settings, "max_script", cls.max_script_bytes)),
                   allowed_hosts=allowed_hosts(getattr(settings, "host", None)))

    def needs_token(self, method: str, path: str) -> bool:
        if not self.token or path in OPEN_PATHS:
            return False
        if method.upper() == "GET" and path.startswith(OPEN_PREFIXES):
            return False
        return method.upper() in WRITE_METHODS or self.protect_reads

    def token_matches(self, presented: str | None) -> bool:
        """Constant-time comparison of a presented token with the cell's."""
        if not self.token or presented is None:
            return False
        return hmac.compare_digest(presented.encode("utf-8"), self.token.encode("utf-8"))

    def authorized(self, headers: Mapping[str, str]) -> bool:
        """True when ``headers`` carry ``Authorization: Bearer <the token>``."""
        return self.token_matches(bearer(headers.get("authorization")))


def allowed_hosts(host: str | None, env: Mapping[str, str] | None = None) -> tuple[str, ...]:
    """The ``Host`` names a cell serving on ``host`` answers to: ``host`` itself, the local
    names, this machine's names and addresses when ``host`` is a wildcard (``0.0.0.0``,
    ``::``), and those
    of ``TESTCELL_ALLOWED_HOSTS``."""
    env = os.environ if env is None else env
    names: list[str] = []
    if host:
        h = host.strip()
        names.append(f"[{h}]" if ":" in h and not h.startswith("[") else h)
        if h in ("0.0.0.0", "::", "[::]"):
            names += [socket.gethostname(), socket.getfqdn(), *_own_addresses()]
    names += LOCAL_HOSTS
    names += [n.strip() for n in env.get(ALLOWED_HOSTS_ENV, "").split(",") if n.strip()]
    return tuple(dict.fromkeys(n.lower() for n in names if n))


def _own_addresses() -> list[str]:
    """This machine's addresses as its name resolves (``[...]`` around IPv6 ones)."""
    try:
        infos = socket.getaddrinfo(socket.gethostname(), None)
    except OSError:
        return []
    return [f"[{i[4][0]}]" if i[0] == socket.AF_INET6 else i[4][0] for i in infos]


def media_type(value: str | None) -> str:
    """``application/json; charset=utf-8`` -> ``application/json`` (lower case); ``""`` if none."""
    return (value or "").split(";", 1)[0].strip().lower()


def own_origin(scope: Mapping[str, Any], headers: Mapping[str, str]) -> str:
    """The cell's own origin as a browser on its page names it: ``http://<Host>``."""
    scheme = {"ws": "http", "wss": "https"}.get(scope.get("scheme", "http"),
                                               scope.get("scheme", "http"))
    return f"{scheme}://{headers.get('host', '')}".lower()


def foreign_origin(scope: Mapping[str, Any], headers: Mapping[str, str]) -> str | None:
    """The request's ``Origin`` when it is present and not the cell's own, else ``None``."""
    origin = headers.get("origin")
    if origin is None:
        return None
    return None if origin.strip().lower().rstrip("/") == own_origin(scope, headers) else origin


def content_type_refusal(method: str, path: str, headers: Mapping[str, str]) -> str | None:
    """Why a write's body type is refused (415), or ``None`` when it is accepted."""
    method = method.upper()
    if method not in WRITE_METHODS:
        return None
    got = media_type(headers.get("content-type"))
    if got == JSON_TYPE:
        return None
    extra = next((types for (m, prefix), types in TEXT_BODIES.items()
                  if m == method and path.startswith(prefix)), frozenset())
    if got in extra or (extra and not got):  # a script's source sent with no type at all
        return None
    if method == "DELETE" and headers.get("content-length", "0") == "0" \
            and "transfer-encoding" not in headers:
        return None
    allowed = " or ".join([JSON_TYPE, *sorted(extra)])
    return (f"{method} {path} needs Content-Type: {allowed}; got "
            f"{repr(headers['content-type']) if 'content-type' in headers else 'none'}")


def bearer(value: str | None) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header value, else ``None``."""
    if not value:
        return None
    scheme, _, token = value.strip().partition(" ")
    return token.strip() if scheme.lower() == "bearer" and token.strip() else None


def is_loopback(host: str) -> bool:
    if host in ("localhost", "localhost.localdomain"):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_bind(host: str, token: str | None) -> None:
    """Refuse to serve beyond this machine without a token (:class:`ConfigError`)."""
    if not is_loopback(host) and not token:
        raise ConfigError(
            f"--host {host}: refusing to serve the cell beyond this machine without a token; "
            "set TESTCELL_TOKEN (every change then needs 'Authorization: Bearer <token>'), or "
            "serve on 127.0.0.1")


# -- WebSocket helpers (for the stream route) ---------------------------------------------------
def _ws_headers(websocket: Any) -> Mapping[str, str]:
    return {k.lower(): v for k, v in websocket.headers.items()}


def websocket_subprotocols(websocket: Any) -> list[str]:
    """The subprotocols a WebSocket client offered (``Sec-WebSocket-Protocol``), in order."""
    value = _ws_headers(websocket).get("sec-websocket-protocol", "")
    return [p.strip() for p in value.split(",") if p.strip()]


def websocket_token_protocol(websocket: Any) -> str | None:
    """The offered subprotocol that carries a token (``token.<TOKEN>``), to be echoed back
    when the connection is accepted; ``None`` when none was offered."""
    return next((p for p in websocket_subprotocols(websocket) if p.startswith(WS_TOKEN_PREFIX)),
                None)


def _ws_token(websocket: Any) -> str | None:
    proto = websocket_token_protocol(websocket)
    return proto[len(WS_TOKEN_PREFIX):] if proto is not None else None


def websocket_refusal(websocket: Any, security: Security) -> str | None:
    """Why a WebSocket handshake is refused (the close reason), or ``None`` to accept it:
    a token in the query string (logged by the server) when a token is set, a foreign
    ``Origin``, or, with reads protected, no valid token in a subprotocol or bearer header."""
    headers = _ws_headers(websocket)
    if security.token and "token" in websocket.query_params:
        return ("the token does not go in the query string (access logs record it): offer it "
                "as the subprotocol 'token.<TOKEN>' (Sec-WebSocket-Protocol)")
    origin = foreign_origin(getattr(websocket, "scope", {}), headers)
    if origin is not None:
        return f"origin {origin!r} is not this cell's"
    if not security.token or not security.protect_reads:
        return None
    if security.authorized(headers) or security.token_matches(_ws_token(websocket)):
        return None
    return "this stream needs the cell's token: offer the subprotocol 'token.<TOKEN>'"


def websocket_may_connect(websocket: Any, security: Security) -> bool:
    """Whether a WebSocket handshake may be accepted (:func:`websocket_refusal`)."""
    return websocket_refusal(websocket, security) is None


def websocket_may_command(websocket: Any, security: Security, command: Mapping[str, Any]) -> bool:
    """Whether a command received on a WebSocket may act: with a token set, the command
    carries ``"token"`` or the handshake carried the bearer header. Compared in constant time."""
    if not security.token:
        return True
    token = command.get("token") if isinstance(command, Mapping) else None
    return (security.authorized(_ws_headers(websocket))
            or security.token_matches(_ws_token(websocket))
            or security.token_matches(token if isinstance(token, str) else None))


# -- the middleware -----------------------------------------------------------------------------
class BodyTooLarge(Exception):
    pass


class SecurityMiddleware:
    """403 for a write from a foreign origin, 401 for a request without the token where one
    is needed, 415 for a write that is not JSON, 413 for a body over the limit; a refused
    WebSocket is accepted and closed at once with code 1008 and the reason."""

    def __init__(self, app: Any, security: Security) -> None:
        self.app = app
        self.security = security

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] == "websocket":
            refusal = websocket_refusal(_WsScope(scope), self.security)
            if refusal is not None:
                # accepted, then closed: a close before the accept reaches a browser as a bare
                # failed handshake, without the reason
                message = await receive()
                if message["type"] == "websocket.connect":
                    await send({"type": "websocket.accept"})
                    await send({"type": "websocket.close", "code": 1008, "reason": refusal[:120]})
                return
            await self.app(scope, receive, send)
            return
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        sec = self.security
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        writes = scope["method"].upper() in WRITE_METHODS
        origin = foreign_origin(scope, headers) if writes else None
        if origin is not None:
            await _json(send, 403, {"detail": f"{scope['method']} {scope['path']} from origin "
                                              f"{origin!r} refused: only this cell's own page "
                                              f"({own_origin(scope, headers)}) may change it"})
            return
        if sec.needs_token(scope["method"], scope["path"]) and not sec.authorized(headers):
            await _json(send, 401, {"detail": "this request needs the cell's token: "
                                              "'Authorization: Bearer <TESTCELL_TOKEN>'"},
                        [(b"www-authenticate", b"Bearer")])
            return
        refused_type = content_type_refusal(scope["method"], scope["path"], headers)
        if refused_type is not None:
            await _json(send, 415, {"detail": refused_type})
            return
        limit = sec.max_body_bytes
        length = headers.get("content-length")
        if length is not None and length.isdigit() and int(length) > limit:
            await _json(send, 413, {"detail": f"request body is {length} bytes; the limit is {limit}"})
            return
        seen = 0
        started = False

        async def limited_receive() -> dict:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise BodyTooLarge
            return message

        async def tracking_send(message: dict) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except BodyTooLarge:
            if not started:
                await _json(send, 413, {"detail": f"request body is over the limit of {limit} bytes"})


class _WsScope:
    """The little of a WebSocket the helpers read, from a raw ASGI scope."""

    def __init__(self, scope: dict) -> None:
        from urllib.parse import parse_qs

        self.scope = scope
        self.headers = {k.decode("latin-1"): v.decode("latin-1") for k, v in scope["headers"]}
        qs = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        self.query_params = {k: v[0] for k, v in qs.items()}


async def _json(send: Any, status: int, body: dict, extra: list | None = None) -> None:
    data = json.dumps(body).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(data)).encode()), *(extra or [])]})
    await send({"type": "http.response.body", "body": data})


__all__ = ["OPEN_PATHS", "WRITE_METHODS", "Security", "SecurityMiddleware", "allowed_hosts", "bearer",
           "check_bind", "content_type_refusal", "foreign_origin", "is_loopback", "media_type",
           "own_origin", "websocket_may_command", "websocket_may_connect", "websocket_refusal",
           "websocket_token_protocol"]
