"""An in-process HTTP client of a cell's app, as a browser on this machine addresses it.

The service answers only to its own host names (``TrustedHostMiddleware``), so a client uses
``http://127.0.0.1``, not Starlette's ``testserver`` (which its ``websocket_connect`` uses
whatever the base URL: :class:`LocalClient` connects WebSockets to the same host).
"""

from __future__ import annotations

from typing import Any

from fastapi.testclient import TestClient

#: The base URL of every in-process client: a host the cell answers to.
LOCAL_URL = "http://127.0.0.1"


class LocalClient(TestClient):
    """A :class:`TestClient` whose WebSockets go to :data:`LOCAL_URL`'s host too."""

    def websocket_connect(self, url: str, *args: Any, **kwargs: Any) -> Any:
        if "://" not in url:
            url = LOCAL_URL.replace("http", "ws", 1) + url
        return super().websocket_connect(url, *args, **kwargs)


def local_client(app: Any, **kwargs: Any) -> LocalClient:
    """A client of ``app`` on :data:`LOCAL_URL`."""
    return LocalClient(app, base_url=LOCAL_URL, **kwargs)
