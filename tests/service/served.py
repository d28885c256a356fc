"""A real uvicorn server on a free port, in a thread of the test process (no multicast)."""

from __future__ import annotations

import contextlib
import signal
import socket
import threading
import time

import uvicorn

from service.serve import Server


@contextlib.contextmanager
def served(app, ws: str = "auto", sndbuf: int | None = None):
    """Serve ``app`` on 127.0.0.1 and a free port; yields the base URL (``http://127.0.0.1:PORT``).

    ``sndbuf`` caps the kernel's send buffer of every accepted connection (they inherit it
    from the listening socket), so a client that stops reading backs up into the server
    within a few kB rather than megabytes of kernel buffers.
    """
    config = uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning", ws=ws,
                            lifespan="off")
    server = Server(config)
    thread = threading.Thread(target=server.run, name="test-uvicorn", daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.02)
    sock = server.servers[0].sockets[0]
    if sndbuf:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, sndbuf)
    port = sock.getsockname()[1]
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.handle_exit(signal.SIGTERM, None)  # as SIGTERM does: streams end, then the server
        thread.join(10)
