"""Frames the kernel dropped before the cell read them, where the platform reports it.

A udp_multicast bus is one UDP socket. When the process does not read it fast enough (a
stall, a burst) the kernel drops datagrams that do not fit its receive buffer and counts them
per socket; Linux shows the count in the last column (``drops``) of ``/proc/net/udp`` and
``/proc/net/udp6``, on the line of the socket's inode. That count is read here, so the
receive path itself is untouched (``SO_RXQ_OVFL`` would add a control message to every
datagram, which python-can's receive does not expect). Other buses (SocketCAN, virtual), and
platforms without ``/proc/net/udp``, report no count: :func:`kernel_drops` gives ``None``,
which ``/health`` shows as not available.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path
from typing import Any

#: Where Linux lists its UDP sockets.
PROC_UDP = (Path("/proc/net/udp"), Path("/proc/net/udp6"))


def bus_socket(bus: Any) -> socket.socket | None:
    """The UDP socket of a udp_multicast bus (a :class:`~cell.bus.interface.CellBus` or the
    python-can bus itself), else ``None``."""
    raw = getattr(bus, "bus", bus)
    sock = getattr(getattr(raw, "_multicast", None), "_socket", None)
    return sock if isinstance(sock, socket.socket) else None


def socket_drops(sock: socket.socket, tables: tuple[Path, ...] = PROC_UDP) -> int | None:
    """The kernel's drop count of ``sock`` (``None``: the platform does not report it)."""
    try:
        inode = os.fstat(sock.fileno()).st_ino
    except (OSError, ValueError):  # closed
        return None
    for table in tables:
        try:
            lines = table.read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) >= 13 and fields[9] == str(inode):
                try:
                    return int(fields[-1])
                except ValueError:
                    return None
    return None


def kernel_drops(bus: Any) -> int | None:
    """Datagrams the kernel dropped on ``bus``'s socket so far, or ``None`` if not reported."""
    sock = bus_socket(bus)
    return None if sock is None else socket_drops(sock)


__all__ = ["PROC_UDP", "bus_socket", "kernel_drops", "socket_drops"]
