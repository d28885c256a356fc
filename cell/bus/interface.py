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
import errno
import logging
import math
import os
import select
import socket
import struct
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from cell.bus.drops import bus_socket
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


#: SO_TIMESTAMPNS (Linux): the kernel's receive time of each datagram, which python-can asks
#: for on its udp_multicast sockets and stamps its frames with
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_TIMESPEC = struct.Struct("@ll")


#: the fields of python-can's udp_multicast wire format (``pack_message``), in its order
WIRE_FIELDS = ("timestamp", "arbitration_id", "is_extended_id", "is_remote_frame",
               "is_error_frame", "channel", "dlc", "data", "is_fd", "bitrate_switch",
               "error_state_indicator")
_new_message = can.Message.__new__


def _classic_frame(fields: Any, stamp: float) -> can.Message | None:
    """The :class:`can.Message` of an unpacked datagram that is a plain classic data frame
    (python-can's fields, no flag set, an ID in range, ``dlc`` bytes of data, at most 8),
    stamped ``stamp``; ``None`` for anything else.

    It is the message ``can.Message(check=True, **fields)`` makes, with its attributes set
    directly: the checks of :meth:`can.Message._check` that such a frame can fail are made
    here, and ``__init__`` (a third of the cost of a frame's receive) is skipped. Every
    other datagram (a remote, error or FD frame, odd types, missing or extra fields) goes
    through python-can's constructor.
    """
    if type(fields) is not dict or len(fields) != 11:
        return None
    try:
        aid, ext, data, dlc = (fields["arbitration_id"], fields["is_extended_id"],
                               fields["data"], fields["dlc"])
        if (fields["is_remote_frame"] is not False or fields["is_error_frame"] is not False
                or fields["is_fd"] is not False or fields["bitrate_switch"] is not False
                or fields["error_state_indicator"] is not False or "timestamp" not in fields):
            return None
        channel = fields["channel"]
    except KeyError:
        return None
    if (type(aid) is not int or type(ext) is not bool or type(data) is not bytes
            or type(dlc) is not int or not 0 <= aid < (0x20000000 if ext else 0x800)
            or dlc != len(data) or dlc > 8 or not stamp >= 0.0 or stamp == math.inf):
        return None
    msg = _new_message(can.Message)
    msg.timestamp = stamp
    msg.arbitration_id = aid
    msg.is_extended_id = ext
    msg.is_remote_frame = False
    msg.is_error_frame = False
    msg.channel = channel
    msg.dlc = dlc
    msg.data = bytearray(data)
    msg.is_fd = False
    msg.is_rx = True
    msg.bitrate_switch = False
    msg.error_state_indicator = False
    return msg


def frame_of(data: bytes, stamp: float, unpackb=None) -> can.Message:
    """The :class:`can.Message` of one udp_multicast datagram, stamped ``stamp``: python-can's
    ``unpack_message(data, replace={"timestamp": stamp}, check=True)``, equal field for
    field (a plain classic data frame is built by :func:`_classic_frame`). Raises what that
    raises for a datagram that is not a frame."""
    if unpackb is None:
        import msgpack

        unpackb = msgpack.unpackb
    fields = unpackb(data, raw=False)
    msg = _classic_frame(fields, stamp)
    if msg is None:  # anything else: python-can's own constructor checks it
        fields.update(timestamp=stamp)
        msg = can.Message(check=True, **fields)
    return msg


class DatagramReader:
    """The frames of a python-can udp_multicast bus, read in batches straight from its socket.

    python-can's ``recv`` costs one ``select``, one ``recvmsg``, a msgpack unpack and a
    :class:`can.Message` per frame, behind two layers of calls: about 13 µs a frame, most
    of the 22 µs that 45 000 frames/s leave. Here one ``select`` waits for the first
    datagram of a batch, the rest are read without waiting (``MSG_DONTWAIT``) until the
    socket is empty or the batch full, and each is unpacked with msgpack into the
    :class:`can.Message` python-can would have made (its wire format, ``check=True``,
    stamped with the kernel's receive time). Anything that is not such a message is passed
    to ``skipped`` as the :class:`can.CanOperationError` python-can would have raised.

    Only a python-can :class:`~can.interfaces.udp_multicast.UdpMulticastBus` without
    software filters is read this way (:attr:`usable`); any other bus goes through its
    own ``recv``.
    """

    MAX_DATAGRAM = 4096

    def __init__(self, bus: can.BusABC, sock: socket.socket | None) -> None:
        self.bus = bus
        self.sock = sock
        self.usable = (sock is not None and hasattr(socket, "MSG_DONTWAIT")
                       and not getattr(bus, "filters", None))
        self._anc = 0
        self._fd = getattr(bus, "protocol", can.CanProtocol.CAN_FD) is can.CanProtocol.CAN_FD
        if self.usable:
            try:
                import msgpack
            except ImportError:
                self.usable = False
                return
            self._unpackb = msgpack.unpackb
            try:
                stamped = sock.getsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS)  # type: ignore[union-attr]
                if not stamped:
                    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)  # type: ignore[union-attr]
                self._anc = socket.CMSG_SPACE(_TIMESPEC.size)
            except OSError:  # no kernel stamps here: the wall clock at reading
                self._anc = 0

    @classmethod
    def of(cls, bus: can.BusABC) -> DatagramReader:
        from can.interfaces.udp_multicast import UdpMulticastBus

        return cls(bus, bus_socket(bus) if isinstance(bus, UdpMulticastBus) else None)

    def read(self, timeout: float | None, limit: int, skipped) -> list[can.Message]:
        """Up to ``limit`` frames; waits up to ``timeout`` s for the first (0: no wait)."""
        sock = self.sock
        assert sock is not None
        if timeout is None or timeout > 0:
            try:
                ready, _, _ = select.select([sock], [], [], timeout)
            except (OSError, ValueError) as exc:  # closed, or the interface went away
                raise can.CanOperationError(f"failed to wait for the UDP socket: {exc}") from exc
            if not ready:
                return []
        out: list[can.Message] = []
        recvmsg, anc, flags = sock.recvmsg, self._anc, socket.MSG_DONTWAIT
        unpackb, timespec, fd = self._unpackb, _TIMESPEC.unpack, self._fd
        for _ in range(limit):  # at most ``limit`` datagrams, good or bad, per call
            try:
                data, ancdata, _, _ = recvmsg(self.MAX_DATAGRAM, anc, flags)
            except BlockingIOError:
                break  # the socket is empty
            except OSError as exc:
                if exc.errno == errno.EINTR:
                    continue
                if out:
                    break  # the frames read before it go first; the next read raises again
                raise can.CanOperationError(f"failed to receive on the UDP socket: {exc}") from exc
            if ancdata and ancdata[0][1] == SO_TIMESTAMPNS:
                sec, nsec = timespec(ancdata[0][2])
                stamp = sec + nsec * 1e-9
            else:
                stamp = time.time()
            try:
                msg = frame_of(data, stamp, unpackb)
            except Exception as exc:  # not a python-can frame: counted by the caller
                err = can.CanOperationError("could not unpack received message")
                err.__cause__ = exc
                skipped(err)
                continue
            if msg.is_fd and not fd:
                continue  # python-can drops an FD frame on a bus opened without FD
            out.append(msg)
        return out


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
        #: arbitration IDs among the frames sent and not yet echoed, with their counts
        self._pending_ids: collections.Counter = collections.Counter()
        self._datagrams: DatagramReader | None = None
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
            self._unpend(key)

    def _unpend(self, key: tuple) -> None:
        self._pending[key] -= 1
        if self._pending[key] <= 0:
            del self._pending[key]
        self._pending_ids[key[0]] -= 1
        if self._pending_ids[key[0]] <= 0:
            del self._pending_ids[key[0]]

    def _forget(self, key: tuple) -> None:
        """Remove the oldest record of a sent frame whose echo just came back."""
        for i, (_, sent) in enumerate(self._sent):
            if sent == key:
                del self._sent[i]
                break
        self._unpend(key)

    def send(self, msg: can.Message) -> None:
        if self._drop_echoes:
            now = time.monotonic()
            self._expire(now)
            key = self._key(msg)
            self._sent.append((now, key))
            self._pending[key] += 1
            self._pending_ids[key[0]] += 1
        try:
            self.bus.send(msg)
        except can.CanError as exc:
            raise BusError(f"cannot send on {self.spec}: {exc}") from exc

    def _is_echo(self, msg: can.Message) -> bool:
        """Whether ``msg`` is the echo of a frame this bus sent (and forget that frame)."""
        if msg.arbitration_id not in self._pending_ids:
            return False  # the common case, without building the frame's key
        key = self._key(msg)
        if self._pending.get(key, 0) > 0:
            self._forget(key)
            self.echoes_dropped += 1
            return True
        return False

    def _skipped(self, exc: BaseException) -> None:
        """Count one undecodable datagram or frame (logged at the 1st, 10th, 100th, ...)."""
        self.undecodable += 1
        cause = exc.__cause__
        self.last_undecodable = f"{exc}: {cause}" if cause is not None else str(exc)
        if self.undecodable in (1, 10, 100) or self.undecodable % 10_000 == 0:
            log.warning("skipped %d undecodable datagram(s) on %s; last: %s",
                        self.undecodable, self.spec, self.last_undecodable)

    def recv_batch(self, timeout: float | None, limit: int = 256) -> list[can.Message]:
        """The frames already received, at most ``limit``, waiting up to ``timeout`` seconds
        for the first (``[]``: none came).

        On udp_multicast this reads the socket directly (:class:`DatagramReader`: one
        ``select`` per batch, then non-blocking reads until the socket is empty), which
        costs a third of python-can's per-frame ``recv``; the frames are the same
        (:func:`can.interfaces.udp_multicast.utils.unpack_message`'s fields, stamped with
        their receive time). Echoes of this bus's own frames are dropped and undecodable
        datagrams counted and skipped, as :meth:`recv` does; bus loss raises.
        """
        reader = self._reader()
        if reader is None:
            out: list[can.Message] = []
            msg = self.recv(timeout)
            while msg is not None:
                out.append(msg)
                if len(out) >= limit:
                    break
                msg = self.recv(0.0)
            return out
        frames = reader.read(timeout, limit, self._skipped)
        if self._pending_ids and frames:
            frames = [m for m in frames if not self._is_echo(m)]
        return frames

    def _reader(self) -> DatagramReader | None:
        reader = self._datagrams
        if reader is None or reader.bus is not self.bus:
            reader = self._datagrams = DatagramReader.of(self.bus)
        return reader if reader.usable else None

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
                self._skipped(exc)
                skipped += 1
                # what is already queued is still read after the deadline (a zero timeout
                # drains the socket), but a flood of garbage cannot hold the caller for ever
                if deadline is not None and time.monotonic() >= deadline and skipped >= 64:
                    return None
                continue
            if msg is None or not self._drop_echoes:
                return msg
            if self._is_echo(msg):
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
        self._pending_ids.clear()
        self._datagrams = None

    def __enter__(self) -> CellBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()


#: Receive buffer asked for on udp_multicast (the kernel caps it at net.core.rmem_max unless
#: the process may force it, with CAP_NET_ADMIN): at 50 000 frames/s the default ~200 kB
#: holds a few ms. The kernel doubles what is asked and charges ~800 bytes per queued frame:
#: an rmem_max of 4 MB holds ~10 000 frames (0.2 s at 45 000 frames/s), 32 MB forced
#: ~80 000. Memory is taken only while frames are queued.
RECEIVE_BUFFER = 32 * 1024 * 1024


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
