"""Bus selection, echo dropping and the one-line errors of cell.bus.interface."""

import collections

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


def test_an_echo_read_seconds_late_is_still_dropped(monkeypatch):
    """A receiver behind its socket by more than the echo window (a backlog) while it goes
    on sending: its own frames come back late and must not count as received (the soak's
    "runtime counted more than the simulator sent")."""
    clock = [1000.0]
    monkeypatch.setattr(cellbus.time, "time", lambda: clock[0])
    monkeypatch.setattr(cellbus.time, "monotonic", lambda: clock[0])  # either clock: 4 s pass
    fake = FakeBus()
    b = CellBus(fake, BusSpec("udp_multicast", MULTICAST_GROUP))
    for k in range(40):  # 4 s of outputs at 10 Hz, none read yet
        b.send(can.Message(timestamp=clock[0], arbitration_id=0x300, data=bytes([k]) * 8,
                           is_extended_id=False))
        clock[0] += 0.1
    assert [m for _ in range(45) for m in b.recv_batch(0.0)] == []  # (one echo per zero-timeout
    assert b.echoes_dropped == 40  # receive on this fake bus) every echo recognised
    # a foreign frame stamped after the window lets the records of older sends go
    b.send(can.Message(timestamp=clock[0], arbitration_id=0x300, data=b"\xaa" * 8,
                       is_extended_id=False))
    fake.queue[:] = [can.Message(timestamp=clock[0] + 2.5, arbitration_id=0x101, data=b"\x02",
                                 is_extended_id=False)]
    assert len(b.recv_batch(0.0)) == 1 and b._sent == collections.deque()
    # and a frame nobody reads back is forgotten at the latest after ECHO_KEEP_S
    clock[0] += b.ECHO_KEEP_S + 1
    b.send(can.Message(timestamp=clock[0], arbitration_id=0x301, data=b"\x01", is_extended_id=False))
    assert len(b._sent) == 1 and set(b._pending_ids) == {0x301}


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


# -- the batch receive (CellBus.recv_batch, DatagramReader) -------------------------------------
SLOTS = [s for s in can.Message.__slots__ if s != "__weakref__"]


def _fields(msg: can.Message) -> dict:
    return {s: (bytes(getattr(msg, s)), type(getattr(msg, s))) if s == "data" else getattr(msg, s)
            for s in SLOTS}


def _frames() -> list[can.Message]:
    """Frames of every kind python-can's udp_multicast carries, valid or not."""
    out = [can.Message(arbitration_id=i, data=bytes(range(n)), is_extended_id=False)
           for i, n in ((0, 0), (0x7F, 1), (0x80, 2), (0x100, 8), (0x7FF, 5))]
    out += [can.Message(arbitration_id=0x1FFFFFFF, data=b"\xff" * 8, is_extended_id=True),
            can.Message(arbitration_id=0x18FEF100, data=b"\x01", is_extended_id=True),
            can.Message(arbitration_id=0x123, is_remote_frame=True, dlc=4, is_extended_id=False),
            can.Message(arbitration_id=0x0, is_error_frame=True, is_extended_id=False),
            can.Message(arbitration_id=0x321, data=bytes(64), is_fd=True, bitrate_switch=True,
                        is_extended_id=False),
            can.Message(arbitration_id=0x222, data=b"\x01\x02", channel="can7", is_extended_id=False)]
    # invalid ones python-can refuses on receive (check=True): the fast path must too
    out += [can.Message(arbitration_id=0x800, data=b"\x01", is_extended_id=False),
            can.Message(arbitration_id=0x20000000, data=b"\x01", is_extended_id=True),
            can.Message(arbitration_id=0x100, data=b"\x01\x02", dlc=3, is_extended_id=False),
            can.Message(arbitration_id=0x100, data=bytes(9), is_extended_id=False),
            can.Message(arbitration_id=0x100, data=b"\x01", bitrate_switch=True, is_extended_id=False),
            can.Message(arbitration_id=-1, data=b"\x01", is_extended_id=False)]
    return out


def test_a_datagram_becomes_the_frame_python_can_makes_of_it():
    """frame_of against python-can's own unpack_message (check=True): the same frame field
    for field, or an error where python-can raises one."""
    import msgpack
    from can.interfaces.udp_multicast.utils import pack_message, unpack_message

    datagrams = [pack_message(m) for m in _frames()]
    good = pack_message(_frames()[3])
    datagrams += [b"\xc1" * 21, msgpack.packb(5), msgpack.packb([1, 2]),
                  msgpack.packb({**msgpack.unpackb(good), "extra": 1}),
                  msgpack.packb({k: v for k, v in msgpack.unpackb(good).items() if k != "dlc"}),
                  msgpack.packb({**msgpack.unpackb(good), "arbitration_id": "0x100"}),
                  msgpack.packb({**msgpack.unpackb(good), "is_extended_id": 1})]
    agreed = refused = 0
    for data in datagrams:
        try:
            want = unpack_message(data, replace={"timestamp": 5.25}, check=True)
        except Exception as exc:  # python-can refuses it: so does the cell's receive
            with pytest.raises(type(exc)):
                cellbus.frame_of(data, 5.25)
            refused += 1
            continue
        assert _fields(cellbus.frame_of(data, 5.25)) == _fields(want), want
        agreed += 1
    assert agreed == 13 and refused == 11  # a missing dlc and an int flag are frames to both


@pytest.mark.skipif(not routed_over_loopback(), reason=NOT_ROUTED)
def test_the_batch_receive_reads_what_python_can_reads_and_counts_the_garbage():
    """Sent by python-can, read by the batch receive and, on the same group, by python-can's
    own recv: the same frames, stamped alike; the garbage counted; the own echo dropped."""
    import time

    tx, rx, peer = open_bus(private_bus()), open_bus(private_bus()), open_bus(private_bus())
    frames = _frames()[:11]  # the valid ones
    try:
        assert rx._reader() is not None and peer._reader() is not None  # read directly
        for i, m in enumerate(frames):
            if i == 4:
                _garbage(2)
            tx.send(m)
        rx.send(can.Message(arbitration_id=0x555, data=b"\x05", is_extended_id=False))  # own
        got: list[can.Message] = []
        deadline = time.monotonic() + 5
        while len(got) < len(frames) and time.monotonic() < deadline:
            got += rx.recv_batch(0.5, limit=4)  # a limit below the queue: several batches
        assert rx.recv_batch(0.2) == []  # nothing more: the echo was dropped
        theirs = [peer.recv(1.0) for _ in range(len(frames) + 1)]  # python-can, frame by frame
    finally:
        tx.shutdown()
        rx.shutdown()
        peer.shutdown()
    assert [_fields(m) | {"timestamp": 0} for m in got] == \
        [_fields(m) | {"timestamp": 0} for m in theirs[:-1]]
    assert theirs[-1].arbitration_id == 0x555  # the other bus does get rx's frame
    assert all(abs(a.timestamp - b.timestamp) < 0.05 for a, b in zip(got, theirs))
    assert abs(got[0].timestamp - time.time()) < 30  # the kernel's receive time
    assert rx.undecodable == 2 and peer.undecodable == 2 and "could not unpack" in rx.last_undecodable
    assert rx.echoes_dropped == 1


@pytest.mark.skipif(not routed_over_loopback(), reason=NOT_ROUTED)
def test_the_batch_receive_raises_when_the_socket_is_gone():
    b = open_bus(private_bus())
    b.bus._multicast._socket.close()  # the bus goes away under the receiver
    try:
        with pytest.raises(can.CanOperationError):
            b.recv_batch(0.2)
        assert b.undecodable == 0
    finally:
        b.shutdown()


def test_the_batch_receive_of_another_bus_goes_frame_by_frame():
    fake = FakeBus()
    b = CellBus(fake, BusSpec("virtual", "x"))
    sent = [can.Message(arbitration_id=0x100 + i, data=b"\x01", is_extended_id=False) for i in range(5)]
    fake.queue.extend(sent)
    assert b.recv_batch(0.0, limit=3) == sent[:3] and b.recv_batch(0.0) == sent[3:]
    assert b.recv_batch(0.0) == []
