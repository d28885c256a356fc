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
import sys
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


class _Mmsg:
    """Many datagrams per system call: Linux's ``recvmmsg(2)`` through ctypes, which the
    :mod:`socket` module does not offer.

    Every call the socket module makes releases the GIL. While another thread of the
    process computes (a designer in the background, the HTTP server), the receiving thread
    then waits for the GIL again after each datagram, up to the interpreter's switch
    interval (5 ms): a few thousand frames a second were enough to fall behind. The call
    here is made through :class:`ctypes.PyDLL`, which keeps the GIL: it never blocks
    (``MSG_DONTWAIT``) and copies up to :attr:`N` datagrams, with each one's kernel receive
    time (``SO_TIMESTAMPNS``), in a few microseconds per datagram.
    """

    N = 256
    SIZE = 4096  # python-can's own receive buffer

    def __init__(self, fd: int) -> None:
        import ctypes
        import ctypes.util

        class Iovec(ctypes.Structure):
            _fields_ = [("iov_base", ctypes.c_void_p), ("iov_len", ctypes.c_size_t)]

        class Msghdr(ctypes.Structure):
            _fields_ = [("msg_name", ctypes.c_void_p), ("msg_namelen", ctypes.c_uint32),
                        ("msg_iov", ctypes.c_void_p), ("msg_iovlen", ctypes.c_size_t),
                        ("msg_control", ctypes.c_void_p), ("msg_controllen", ctypes.c_size_t),
                        ("msg_flags", ctypes.c_int)]

        class Mmsghdr(ctypes.Structure):
            _fields_ = [("msg_hdr", Msghdr), ("msg_len", ctypes.c_uint)]

        libc = ctypes.PyDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        self._call = libc.recvmmsg  # AttributeError where the C library has none
        self._call.restype = ctypes.c_int
        self._call.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_uint, ctypes.c_int,
                               ctypes.c_void_p]
        self._errno = ctypes.get_errno
        n, size = self.N, self.SIZE
        self.control = socket.CMSG_SPACE(_TIMESPEC.size)
        self._data = ctypes.create_string_buffer(n * size)
        self._ctl = ctypes.create_string_buffer(n * self.control)
        self._iov = (Iovec * n)()
        self._hdrs = (Mmsghdr * n)()
        base, cbase = ctypes.addressof(self._data), ctypes.addressof(self._ctl)
        for i in range(n):
            self._iov[i].iov_base, self._iov[i].iov_len = base + i * size, size
            h = self._hdrs[i].msg_hdr
            h.msg_iov, h.msg_iovlen = ctypes.addressof(self._iov[i]), 1
            h.msg_control, h.msg_controllen = cbase + i * self.control, self.control
        self.fd = fd
        self._hdr_size = ctypes.sizeof(Mmsghdr)
        self._len_at = Mmsghdr.msg_len.offset
        self._ctl_len_at = Mmsghdr.msg_hdr.offset + Msghdr.msg_controllen.offset
        self._flags_at = Mmsghdr.msg_hdr.offset + Msghdr.msg_flags.offset
        self.data = memoryview(self._data).cast("B")
        self.ctl = memoryview(self._ctl).cast("B")
        self._hdr_view = memoryview(self._hdrs).cast("B")
        self._used = n  # entries whose control length the kernel may have changed
        self._size_t = struct.Struct("@N")
        self._uint = struct.Struct("@I")
        self._cmsg = struct.Struct("@Nii")

    def read(self, limit: int) -> list[tuple[memoryview, float | None]]:
        """Up to ``limit`` (at most :attr:`N`) datagrams already queued, each with its kernel
        receive time (``None`` when the kernel gave none); ``[]`` when none is."""
        hv, size_t, ctl_len = self._hdr_view, self._size_t, self.control
        hs, cl_at = self._hdr_size, self._ctl_len_at
        for i in range(self._used):  # the kernel rewrote the control lengths it filled
            size_t.pack_into(hv, i * hs + cl_at, ctl_len)
        n = self._call(self.fd, self._hdrs, min(limit, self.N), socket.MSG_DONTWAIT, None)
        if n < 0:
            err = self._errno()
            self._used = 0
            if err in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EINTR):
                return []
            raise OSError(err, os.strerror(err))
        self._used = n
        out = []
        uint, cmsg, timespec = self._uint.unpack_from, self._cmsg.unpack_from, _TIMESPEC.unpack_from
        data, ctl, size, len_at = self.data, self.ctl, self.SIZE, self._len_at
        head = self._cmsg.size
        for i in range(n):
            length = uint(hv, i * hs + len_at)[0]
            stamp = None
            if size_t.unpack_from(hv, i * hs + cl_at)[0] >= head + _TIMESPEC.size:
                _, level, kind = cmsg(ctl, i * ctl_len)
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    sec, nsec = timespec(ctl, i * ctl_len + head)
                    stamp = sec + nsec * 1e-9
            out.append((data[i * size:i * size + min(length, size)], stamp))
        return out


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
            self._many: _Mmsg | None = None
            if self._anc and sys.platform.startswith("linux"):
                try:
                    self._many = _Mmsg(sock.fileno())  # type: ignore[union-attr]
                except (AttributeError, OSError, ImportError) as exc:  # no recvmmsg here
                    log.debug("recvmmsg not available (%s): one datagram per call", exc)

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
        if self._many is not None:
            return self._read_many(limit, skipped)
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

    def _read_many(self, limit: int, skipped) -> list[can.Message]:
        many, unpackb, fd = self._many, self._unpackb, self._fd
        assert many is not None and self.sock is not None
        if self.sock.fileno() != many.fd:  # closed under us: its number may be another's now
            raise can.CanOperationError(f"the UDP socket of {self.bus.channel_info} is closed")
        out: list[can.Message] = []
        while len(out) < limit:
            try:
                got = many.read(limit - len(out))
            except OSError as exc:
                if out:
                    break  # the frames read before it go first; the next read raises again
                raise can.CanOperationError(f"failed to receive on the UDP socket: {exc}") from exc
            for data, stamp in got:
                try:
                    msg = frame_of(data, time.time() if stamp is None else stamp, unpackb)
                except Exception as exc:  # not a python-can frame: counted by the caller
                    err = can.CanOperationError("could not unpack received message")
                    err.__cause__ = exc
                    skipped(err)
                    continue
                if msg.is_fd and not fd:
                    continue
                out.append(msg)
            if len(got) < many.N:
                break  # the socket is empty
        return out


class CellBus:
    """A python-can bus that drops the echoes of its own frames and skips what it cannot decode.

    udp_multicast delivers every datagram to every member of the group, the sender
    included. Frames this bus sent are remembered until their echo comes back, which is
    then dropped. A sent frame is forgotten once the receive has read frames stamped
    :attr:`ECHO_WINDOW_S` after it was sent (its echo would have come before them), or at
    the latest :attr:`ECHO_KEEP_S` after it was sent: the window runs on the receive's own
    progress, not the wall clock, so a receiver seconds behind (a backlog, a stall) still
    recognises its own frames. (With a wall-clock window of 2 s, such a receiver took the
    echoes of its own outputs for received frames: the soak's "runtime counted more than
    the simulator sent".)

    A datagram or frame that cannot be decoded (:func:`is_undecodable`: anyone on the group
    can send 21 bytes of garbage) never raises out of :meth:`recv`: it is counted in
    :attr:`undecodable` (the last error in :attr:`last_undecodable`) and the receive goes on
    to the next frame within the same timeout. Loss of the bus still raises.
    """

    ECHO_WINDOW_S = 2.0
    #: the longest a sent frame is remembered when no frame stamped after it is read
    ECHO_KEEP_S = 120.0

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

    def _expire(self, before: float) -> None:
        """Forget the frames sent before wall time ``before`` (their echoes came or never will)."""
        while self._sent and self._sent[0][0] < before:
            _, key = self._sent.popleft()
            self._unpend(key)

    def _received_up_to(self, stamp: float) -> None:
        """The receive has read a frame stamped ``stamp`` (wall clock, the kernel's)."""
        if self._sent and self._sent[0][0] < stamp - self.ECHO_WINDOW_S:
            self._expire(stamp - self.ECHO_WINDOW_S)

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
            now = time.time()  # the clock the kernel stamps received datagrams with
            self._expire(now - self.ECHO_KEEP_S)
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
            if frames:
                self._received_up_to(frames[-1].timestamp)
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
            if self._sent:
                self._received_up_to(msg.timestamp)
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
