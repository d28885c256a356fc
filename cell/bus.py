"""Opening the CAN bus the python-can way, with the cell's ``auto`` choice.

``--bus`` takes ``auto``, ``virtual``, ``udp_multicast``, ``socketcan`` or
``INTERFACE:CHANNEL`` (for example ``socketcan:can0``). Without ``--bus``, python-can's own
``CAN_INTERFACE``/``CAN_CHANNEL`` environment variables are honoured, then ``auto``.
"""

from __future__ import annotations

import collections
import os
import time
from dataclasses import dataclass
from pathlib import Path

import can

from .errors import BusError

MULTICAST_GROUP = "239.74.163.2"
VCAN = "vcan0"
VIRTUAL_CHANNEL = "testcell"

_DEFAULT_CHANNEL = {"udp_multicast": MULTICAST_GROUP, "socketcan": VCAN, "virtual": VIRTUAL_CHANNEL}


@dataclass(frozen=True)
class BusSpec:
    """Which python-can interface and channel to open."""

    interface: str
    channel: str

    def __str__(self) -> str:
        return f"{self.interface}:{self.channel}"


def have_socketcan(name: str = VCAN) -> bool:
    """True when the network interface ``name`` exists (SocketCAN is usable)."""
    return Path("/sys/class/net", name).exists()


def resolve(spec: str | None = None, env: dict[str, str] | None = None) -> BusSpec:
    """Turn a ``--bus`` value (or the environment) into an interface and channel."""
    env = os.environ if env is None else env
    if not spec:
        if env.get("CAN_INTERFACE"):
            iface = env["CAN_INTERFACE"]
            return BusSpec(iface, env.get("CAN_CHANNEL") or _DEFAULT_CHANNEL.get(iface, ""))
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
    return BusSpec(iface, channel)


class CellBus:
    """A python-can bus that drops the echoes of its own frames.

    udp_multicast delivers every datagram to every member of the group, the sender
    included. Frames this bus sent are remembered for a short while and dropped when they
    come back.
    """

    ECHO_WINDOW_S = 2.0

    def __init__(self, bus: can.BusABC, spec: BusSpec) -> None:
        self.bus = bus
        self.spec = spec
        self._drop_echoes = spec.interface == "udp_multicast"
        self._sent: collections.deque[tuple[float, tuple]] = collections.deque()
        self._pending: collections.Counter = collections.Counter()
        self.echoes_dropped = 0

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
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            msg = self.bus.recv(remaining)
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

    def __enter__(self) -> CellBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()


def open_bus(spec: str | BusSpec | None = None, **kwargs) -> CellBus:
    """Open the bus, turning every failure into one :class:`BusError` line that names the fix."""
    resolved = spec if isinstance(spec, BusSpec) else resolve(spec)
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
        kwargs.setdefault("receive_own_messages", False)
    if resolved.interface == "virtual":
        kwargs.setdefault("receive_own_messages", False)
    try:
        bus = can.Bus(interface=resolved.interface, channel=resolved.channel, **kwargs)
    except PermissionError as exc:
        raise BusError(
            f"permission denied opening {resolved}: {exc.strerror or exc}; run with the "
            f"rights the interface needs, or use --bus udp_multicast"
        ) from exc
    except (OSError, can.CanError, ImportError, ValueError) as exc:
        raise BusError(f"cannot open CAN bus {resolved}: {exc}") from exc
    return CellBus(bus, resolved)
