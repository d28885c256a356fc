"""Serving the app with uvicorn so that open streams end when the server is asked to stop."""

from __future__ import annotations

import uvicorn
from fastapi import FastAPI


class Server(uvicorn.Server):
    """uvicorn's server, ending the app's streams (``/stream``, ``/stream/sse``) on SIGINT or
    SIGTERM: uvicorn waits for open responses before it stops, and an event stream never
    ends by itself."""

    def handle_exit(self, sig, frame) -> None:
        hub = getattr(self.config.app.state, "hub", None) if isinstance(self.config.app, FastAPI) else None
        if hub is not None:
            hub.close()
        super().handle_exit(sig, frame)


def serve(app: FastAPI, host: str, port: int, log_level: str) -> None:
    """Run ``app`` until SIGINT or SIGTERM (what ``uvicorn.run`` does, plus the above)."""
    Server(uvicorn.Config(app, host=host, port=port, log_level=log_level)).run()
