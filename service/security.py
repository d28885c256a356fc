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
- **Bounded inputs.** A request body over :attr:`Security.max_body_bytes` gets 413, whether
  it declares its length or streams it; scripts have their own limit (``max_script_bytes``).

Everything is one pure ASGI middleware (:class:`SecurityMiddleware`), so routes added later
are covered without a line of their own.
"""

from __future__ import annotations

import hmac
import ipaddress
import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from cell.core.errors import ConfigError

#: Methods that change state: they need the token once one is set.
WRITE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
#: Paths that never need a token (the page itself; it asks for the token in the browser).
OPEN_PATHS = frozenset({"/"})


@dataclass(frozen=True)
class Security:
    """The service's access rules and size limits (from :class:`cell.core.settings.Settings`)."""

    token: str | None = None
    protect_reads: bool = False
    max_body_bytes: int = 1024 * 1024
    max_script_bytes: int = 256 * 1024

    def __repr__(self) -> str:  # never print the token
        return (f"Security(token={'set' if self.token else None}, protect_reads="
                f"{self.protect_reads}, max_body_bytes={self.max_body_bytes}, "
                f"max_script_bytes={self.max_script_bytes})")

    @classmethod
    def from_settings(cls, settings: Any) -> Security:
        return cls(token=getattr(settings, "token", None) or None,
                   protect_reads=bool(getattr(settings, "protect_reads", False)),
                   max_body_bytes=int(getattr(settings, "max_body", cls.max_body_bytes)),
                   max_script_bytes=int(getattr(settings, "max_script", cls.max_script_bytes)))

    def needs_token(self, method: str, path: str) -> bool:
        if not self.token or path in OPEN_PATHS:
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


def websocket_may_connect(websocket: Any, security: Security) -> bool:
    """Whether a WebSocket handshake may be accepted (reads protected: it needs the token)."""
    if not security.token or not security.protect_reads:
        return True
    return security.authorized(_ws_headers(websocket)) or security.token_matches(
        websocket.query_params.get("token"))


def websocket_may_command(websocket: Any, security: Security, command: Mapping[str, Any]) -> bool:
    """Whether a command received on a WebSocket may act: with a token set, the command
    carries ``"token"`` or the handshake carried the bearer header. Compared in constant time."""
    if not security.token:
        return True
    token = command.get("token") if isinstance(command, Mapping) else None
    return security.authorized(_ws_headers(websocket)) or security.token_matches(
        token if isinstance(token, str) else None)


# -- the middleware -----------------------------------------------------------------------------
class BodyTooLarge(Exception):
    pass


class SecurityMiddleware:
    """401 for a request without the token where one is needed; 413 for a body over the limit."""

    def __init__(self, app: Any, security: Security) -> None:
        self.app = app
        self.security = security

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] == "websocket":
            if not websocket_may_connect(_WsScope(scope), self.security):
                await send({"type": "websocket.close", "code": 1008})
                return
            await self.app(scope, receive, send)
            return
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        sec = self.security
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        if sec.needs_token(scope["method"], scope["path"]) and not sec.authorized(headers):
            await _json(send, 401, {"detail": "this request needs the cell's token: "
                                              "'Authorization: Bearer <TESTCELL_TOKEN>'"},
                        [(b"www-authenticate", b"Bearer")])
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

        self.headers = {k.decode("latin-1"): v.decode("latin-1") for k, v in scope["headers"]}
        qs = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        self.query_params = {k: v[0] for k, v in qs.items()}


async def _json(send: Any, status: int, body: dict, extra: list | None = None) -> None:
    data = json.dumps(body).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(data)).encode()), *(extra or [])]})
    await send({"type": "http.response.body", "body": data})


__all__ = ["OPEN_PATHS", "WRITE_METHODS", "Security", "SecurityMiddleware", "bearer", "check_bind",
           "is_loopback", "websocket_may_command", "websocket_may_connect"]
