"""Bus selection, echo dropping and the one-line errors of cell.bus.interface."""


import can
import pytest

from cell.bus import interface as cellbus
from cell.bus.interface import MULTICAST_GROUP, BusSpec, CellBus, open_bus, resolve
from tests.helpers.buses import NOT_ROUTED, private_bus, routed_over_loopback
from cell.core.errors import BusError


def test_resolve_auto_prefers_vcan0(monkeypatch):
    monkeypatch.setattr(cellbus, "have_socketcan", lambda name="vcan0": True)
    assert resolve("auto", env={}) == BusSpec("socketcan", "vcan0")
    monkeypatch.setattr(cellbus, "have_socketcan", lambda name="vcan0": False)
    assert resolve("auto", env={}) == BusSpec("udp_multicast", MULTICAST_GROUP)
    assert resolve(None, env={}) == BusSpec("udp_multicast", MULTICAST_GROUP)


def test_resolve_honours_python_can_environment():
    env = {"CAN_INTERFACE": "virtual", "CAN_CHANNEL": "bench"}
    assert resolve(None, env=env) == BusSpec("virtual", "bench")
    assert resolve("socketcan:can1", env=env) == BusSpec("socketcan", "can1")
    assert resolve("virtual", env={}) == BusSpec("virtual", "testcell")


def test_unknown_bus_names_the_choices():
    with pytest.raises(BusError, match="unknown bus 'carrier-pigeon'.*udp_multicast"):
        resolve("carrier-pigeon", env={})


def test_missing_socketcan_interface_names_the_fix():
    with pytest.raises(BusError, match="vcan7 does not exist: run scripts/setup-vcan.sh"):
        open_bus("socketcan:vcan7")


def test_permission_problem_is_one_line(monkeypatch):
    def refuse(**kwargs):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(can, "Bus", refuse)
    with pytest.raises(BusError, match="permission denied opening virtual:x.*--bus udp_multicast"):
        open_bus("virtual:x")


class FakeBus:
    """Stands in for udp_multicast: every send comes back to the sender."""

    def __init__(self):
        self.queue = []

    def send(self, msg):
        self.queue.append(msg)

    def recv(self, timeout=None):
        return self.queue.pop(0) if self.queue else None

    def shutdown(self):
        pass


def test_own_echoes_are_dropped_but_identical_foreign_frames_are_not():
    fake = FakeBus()
    b = CellBus(fake, BusSpec("udp_multicast", MULTICAST_GROUP))
    mine = can.Message(arbitration_id=0x300, data=b"\x01" * 8, is_extended_id=False)
    b.send(mine)
    assert b.recv(0) is None and b.echoes_dropped == 1
    # someone else sends the same bytes later: delivered, since our one echo was consumed
    fake.queue.append(can.Message(arbitration_id=0x300, data=b"\x01" * 8, is_extended_id=False))
    assert b.recv(0) is not None
    other = can.Message(arbitration_id=0x101, data=b"\x02" * 8, is_extended_id=False)
    fake.queue.append(other)
    assert b.recv(0).arbitration_id == 0x101


@pytest.mark.skipif(not routed_over_loopback(), reason=NOT_ROUTED)
def test_udp_multicast_between_two_buses_without_echo():
    a, b = open_bus(private_bus()), open_bus(private_bus())  # never the default group
    try:
        msg = can.Message(arbitration_id=0x200, data=b"\x10\x27\x10\x27", is_extended_id=False)
        a.send(msg)
        got = b.recv(2.0)
        assert got is not None and bytes(got.data) == bytes(msg.data)
        assert a.recv(0.3) is None, "the sender received its own echo"
    finally:
        a.shutdown()
        b.shutdown()


@pytest.mark.skipif(not cellbus.have_socketcan("vcan0"),
                    reason="no vcan0: this kernel has no SocketCAN here (scripts/setup-vcan.sh creates it "
                           "where the vcan module exists)")
def test_socketcan_vcan0_round_trip():
    a, b = open_bus("socketcan"), open_bus("socketcan")
    try:
        assert a.spec == BusSpec("socketcan", "vcan0")
        a.send(can.Message(arbitration_id=0x200, data=b"\x10\x27\x10\x27", is_extended_id=False))
        got = b.recv(2.0)
        assert got is not None and got.arbitration_id == 0x200
    finally:
        a.shutdown()
        b.shutdown()


# -- undecodable datagrams --------------------------------------------------------------------
def _garbage(n: int = 1) -> None:
    """``n`` datagrams of 21 bytes that are not msgpack, sent to this process's private group."""
    import socket

    from tests.helpers.buses import private_group

    group, port = private_group()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
        s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        for _ in range(n):
            s.sendto(b"\xc1" * 21, (group, port))  # 0xc1 is never used by msgpack


@pytest.mark.skipif(not routed_over_loopback(), reason=NOT_ROUTED)
def test_python_can_udp_multicast_raises_on_a_garbage_datagram():
    """The failure the wrapper exists for: python-can's own bus raises on 21 bytes of garbage."""
    from tests.helpers.buses import private_group

    group, port = private_group()
    raw = can.Bus(interface="udp_multicast", channel=group, port=port)
    try:
        _garbage()
        with pytest.raises(can.CanOperationError, match="unpack"):
            raw.recv(2.0)
    finally:
        raw.shutdown()


@pytest.mark.skipif(not routed_over_loopback(), reason=NOT_ROUTED)
def test_a_garbage_datagram_is_counted_and_skipped_on_a_real_bus():
    a, b = open_bus(private_bus()), open_bus(private_bus())
    try:
        _garbage(3)
        msg = can.Message(arbitration_id=0x211, data=b"\x01\x02\x03", is_extended_id=False)
        a.send(msg)
        got = b.recv(2.0)  # the garbage came first; the good frame is returned
        assert got is not None and got.arbitration_id == 0x211 and bytes(got.data) == b"\x01\x02\x03"
        assert b.undecodable == 3
        assert "could not unpack" in b.last_undecodable
        # garbage alone: the receive honours its timeout and answers None
        _garbage()
        assert b.recv(0.3) is None and b.undecodable == 4
    finally:
        a.shutdown()
        b.shutdown()


@pytest.mark.skipif(not routed_over_loopback(), reason=NOT_ROUTED)
def test_a_closed_socket_still_raises():
    b = open_bus(private_bus())
    b.bus._multicast._socket.close()  # the bus goes away under the receiver
    try:
        with pytest.raises((can.CanOperationError, OSError, ValueError)):
            b.recv(0.2)
        assert b.undecodable == 0
    finally:
        b.shutdown()


def test_only_receive_errors_not_caused_by_the_socket_are_undecodable():
    unpack = can.CanOperationError("could not unpack received message")
    unpack.__cause__ = ValueError("unpack(b) received extra data")
    lost = can.CanOperationError("Failed to wait for IP/UDP socket: [Errno 9] Bad file descriptor")
    lost.__cause__ = OSError(9, "Bad file descriptor")
    assert cellbus.is_undecodable(unpack)
    assert not cellbus.is_undecodable(lost)
    assert not cellbus.is_undecodable(OSError("down"))
    assert not cellbus.is_undecodable(can.CanTimeoutError())
