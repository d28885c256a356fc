"""Opening the CAN bus the python-can way, with the cell's ``auto`` choice.

``--bus`` takes ``auto``, ``virtual``, ``udp_multicast``, ``socketcan`` or
``INTERFACE:CHANNEL`` (for example ``socketcan:can0``). Without ``--bus``, python-can's own
``CAN_INTERFACE``/``CAN_CHANNEL`` environment variables are honoured, then ``auto``.

Two cells on one machine are isolated by multicast group *and* port:
``udp_multicast:GROUP:PORT`` (default port :data:`MULTICAST_PORT`, python-can's). python-can
binds its socket to the port on every address, and Linux then delivers to it the datagrams
of *every* group joined on the machine with that port; the cell's sockets therefore also
turn off ``IP_MULTICAST_ALL``, so that they receive only their own group.
"""

from __future__ import annotations

import collections
import logging
import os
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from cell.core.errors import BusError

log = logging.getLogger(__name__)

#: Linux's IP_MULTICAST_ALL (not exported by every Python build)
IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)

MULTICAST_GROUP = "239.74.163.2"
MULTICAST_PORT = 43113  # python-can's udp_multicast default
VCAN = "vcan0"
VIRTUAL_CHANNEL = "testcell"

_DEFAULT_CHANNEL = {"udp_multicast": MULTICAST_GROUP, "socketcan": VCAN, "virtual": VIRTUAL_CHANNEL}


@dataclass(frozen=True)
class BusSpec:
    """Which python-can interface and channel to open."""

    interface: str
    channel: str
    port: int | None = None
    """udp_multicast only: the UDP port (``None``: python-can's default)."""

    def __str__(self) -> str:
        if self.port is not None:
            group = f"[{self.channel}]" if ":" in self.channel else self.channel
            return f"{self.interface}:{group}:{self.port}"
        return f"{self.interface}:{self.channel}"

    def bus_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of ``can.Bus`` beyond the interface and channel."""
        return {"port": self.port} if self.port is not None else {}


def _split_port(spec: str, channel: str) -> tuple[str, int | None]:
    """``GROUP:PORT`` or ``[IPV6]:PORT`` -> (group, port); a bare group -> (group, None)."""
    group, port = channel, None
    if channel.startswith("["):
        group, _, rest = channel[1:].partition("]")
        if rest:
            if not rest.startswith(":"):
                raise BusError(f"--bus {spec!r}: write an IPv6 group with a port as [GROUP]:PORT")
            port = rest[1:]
    elif channel.count(":") == 1:
        group, port = channel.split(":")
    if port is None:
        return group, None
    try:
        value = int(port)
    except ValueError:
        raise BusError(f"--bus {spec!r}: port {port!r} is not a number") from None
    if not 1024 <= value <= 65535:
        raise BusError(f"--bus {spec!r}: port must be 1024..65535, got {value}")
    return group, value


def have_socketcan(name: str = VCAN) -> bool:
    """True when the network interface ``name`` exists (SocketCAN is usable)."""
    return Path("/sys/class/net", name).exists()


def resolve(spec: str | None = None, env: dict[str, str] | None = None) -> BusSpec:
    """Turn a ``--bus`` value (or the environment) into an interface and channel."""
    env = os.environ if env is None else env
    if not spec:
        if env.get("CAN_INTERFACE"):
            iface = env["CAN_INTERFACE"]
            spec = f"{iface}:{env.get('CAN_CHANNEL') or _DEFAULT_CHANNEL.get(iface, '')}"
        else:
            spec = "auto"
    iface, _, channel = spec.partition(":")
    iface = iface.strip()
    if iface == "auto":
        if have_socketcan(VCAN):
            return BusSpec("socketcan", VCAN)
        return BusSpec("udp_multicast", MULTICAST_GROUP)
    if iface not in can.interfaces.VALID_INTERFACES:
        known = ", ".join(["auto", *sorted(can.interfaces.VALID_INTERFACES)])
        raise BusError(f"unknown bus {iface!r} in --bus {spec!r}; choose one of: {known}")
    channel = channel or env.get("CAN_CHANNEL") or _DEFAULT_CHANNEL.get(iface, "")
    if iface == "udp_multicast":
        group, port = _split_port(spec, channel)
        return BusSpec(iface, group, port)
    return BusSpec(iface, channel)


def is_undecodable(exc: BaseException) -> bool:
    """Whether a receive error is about one datagram or frame, not about the bus.

    python-can's udp_multicast bus raises :class:`can.CanOperationError` when a datagram is
    not a msgpack-packed frame ("could not unpack received message", raised from the
    decoder's error) or its ancillary data is odd; the socket itself is fine and the next
    datagram may be good. A bus that went away (socket closed, interface down) raises it
    *from* an :class:`OSError` (or an :class:`OSError` itself): that is bus loss.
    """
    if not isinstance(exc, can.CanOperationError) or isinstance(exc, can.CanTimeoutError):
        return False
    cause = exc.__cause__
    return not isinstance(cause, OSError)


class CellBus:
    """A python-can bus that drops the echoes of its own frames and skips what it cannot decode.

    udp_multicast delivers every datagram to every member of the group, the sender
    included. Frames this bus sent are remembered for a short while and dropped when they
    come back.

    A datagram or frame that cannot be decoded (:func:`is_undecodable`: anyone on the group
    can send 21 bytes of garbage) never raises out of :meth:`recv`: it is counted in
    :attr:`undecodable` (the last error in :attr:`last_undecodable`) and the receive goes on
    to the next frame within the same timeout. Loss of the bus still raises.
    """

    ECHO_WINDOW_S = 2.0

    def __init__(self, bus: can.BusABC, spec: BusSpec, kwargs: dict[str, Any] | None = None) -> None:
        self.bus = bus
        self.spec = spec
        self.kwargs = dict(kwargs or {})  # how the bus was opened, for reopen()
        self._drop_echoes = spec.interface == "udp_multicast"
        self._sent: collections.deque[tuple[float, tuple]] = collections.deque()
        self._pending: collections.Counter = collections.Counter()
        self.echoes_dropped = 0
        #: datagrams or frames received that could not be decoded, skipped
        self.undecodable = 0
        #: the last of those errors, as text (``None``: none yet)
        self.last_undecodable: str | None = None

    @staticmethod
    def _key(msg: can.Message) -> tuple:
        return (msg.arbitration_id, bool(msg.is_extended_id), bytes(msg.data))

    def _expire(self, now: float) -> None:
        while self._sent and now - self._sent[0][0] > self.ECHO_WINDOW_S:
            _, key = self._sent.popleft()
            self._pending[key] -= 1
            if self._pending[key] <= 0:
                del self._pending[key]

    def _forget(self, key: tuple) -> None:
        """Remove the oldest record of a sent frame whose echo just came back."""
        for i, (_, sent) in enumerate(self._sent):
            if sent == key:
                del self._sent[i]
                break
        self._pending[key] -= 1
        if self._pending[key] <= 0:
            del self._pending[key]

    def send(self, msg: can.Message) -> None:
        if self._drop_echoes:
            now = time.monotonic()
            self._expire(now)
            key = self._key(msg)
            self._sent.append((now, key))
            self._pending[key] += 1
        try:
            self.bus.send(msg)
        except can.CanError as exc:
            raise BusError(f"cannot send on {self.spec}: {exc}") from exc

    def recv(self, timeout: float | None = None) -> can.Message | None:
        deadline = None if timeout is None else time.monotonic() + timeout
        skipped = 0
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                msg = self.bus.recv(remaining)
            except can.CanOperationError as exc:
                if not is_undecodable(exc):
                    raise
                self.undecodable += 1
                skipped += 1
                cause = exc.__cause__
                self.last_undecodable = f"{exc}: {cause}" if cause is not None else str(exc)
                if self.undecodable in (1, 10, 100) or self.undecodable % 10_000 == 0:
                    log.warning("skipped %d undecodable datagram(s) on %s; last: %s",
                                self.undecodable, self.spec, self.last_undecodable)
                # what is already queued is still read after the deadline (a zero timeout
                # drains the socket), but a flood of garbage cannot hold the caller for ever
                if deadline is not None and time.monotonic() >= deadline and skipped >= 64:
                    return None
                continue
            if msg is None or not self._drop_echoes:
                return msg
            key = self._key(msg)
            if self._pending.get(key, 0) > 0:
                self._forget(key)
                self.echoes_dropped += 1
                if deadline is not None and time.monotonic() >= deadline:
                    return None
                continue
            return msg

    def shutdown(self) -> None:
        self.bus.shutdown()

    def reopen(self) -> None:
        """Open the same bus again after it went away (the old one is closed, quietly).

        Raises :class:`BusError` when it cannot be opened yet; the caller retries.
        """
        try:
            self.bus.shutdown()
        except Exception:  # already gone: nothing to close
            pass
        self.bus = _open_raw(self.spec, dict(self.kwargs))
        self._sent.clear()
        self._pending.clear()

    def __enter__(self) -> CellBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()


#: Receive buffer asked for on udp_multicast (the kernel caps it at net.core.rmem_max unless
#: the process may force it): at 50 000 frames/s the default ~200 kB holds a few ms.
RECEIVE_BUFFER = 8 * 1024 * 1024


def _only_own_group(bus: can.BusABC) -> None:
    """Turn off IP_MULTICAST_ALL on a udp_multicast bus's socket (see the module notes) and
    enlarge its receive buffer, so that a burst is not dropped by the kernel."""
    sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
    if sock is None:
        return
    force = getattr(socket, "SO_RCVBUFFORCE", None)
    for opt in ((force,) if force is not None else ()) + (socket.SO_RCVBUF,):
        try:
            sock.setsockopt(socket.SOL_SOCKET, opt, RECEIVE_BUFFER)
            break
        except OSError:
            continue
    if sock.family != socket.AF_INET:
        return
    try:
        sock.setsockopt(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)
    except OSError as exc:  # not Linux: isolation by port only
        log.debug("IP_MULTICAST_ALL not available: %s", exc)


def open_bus(spec: str | BusSpec | None = None, **kwargs) -> CellBus:
    """Open the bus, turning every failure into one :class:`BusError` line that names the fix."""
    resolved = spec if isinstance(spec, BusSpec) else resolve(spec)
    kwargs = {**resolved.bus_kwargs(), **kwargs}
    if resolved.interface == "udp_multicast":
        kwargs.setdefault("receive_own_messages", False)
    if resolved.interface == "virtual":
        kwargs.setdefault("receive_own_messages", False)
    return CellBus(_open_raw(resolved, kwargs), resolved, kwargs)


def _open_raw(resolved: BusSpec, kwargs: dict[str, Any]) -> can.BusABC:
    if resolved.interface == "socketcan" and not have_socketcan(resolved.channel):
        raise BusError(
            f"CAN interface {resolved.channel} does not exist: run scripts/setup-vcan.sh "
            f"(needs root and the vcan kernel module), or use --bus udp_multicast"
        )
    if resolved.interface == "udp_multicast":
        try:
            import msgpack  # noqa: F401
        except ImportError:
            raise BusError("the udp_multicast bus needs msgpack: pip install msgpack") from None
    try:
        bus = can.Bus(interface=resolved.interface, channel=resolved.channel, **kwargs)
    except PermissionError as exc:
        raise BusError(
            f"permission denied opening {resolved}: {exc.strerror or exc}; run with the "
            f"rights the interface needs, or use --bus udp_multicast"
        ) from exc
    except (OSError, can.CanError, ImportError, ValueError) as exc:
        raise BusError(f"cannot open CAN bus {resolved}: {exc}") from exc
    if resolved.interface == "udp_multicast":
        _only_own_group(bus)
    return bus
