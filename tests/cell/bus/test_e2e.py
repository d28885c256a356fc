"""E2E protection of the commands to the simulator: the CRC, the encoder's counters, the
receiver's checks, and the DBC's declaration of it (cell/bus/e2e.py)."""

from __future__ import annotations

import random

import pytest

from cell.bus import e2e
from cell.bus.dbc import CellDatabase, load
from cell.core.errors import ConfigError


def crc8_bitwise(data: bytes, init: int, xor_out: int, poly: int = 0x1D) -> int:
    """The CRC-8 of ``data`` bit by bit (MSB first, no reflection)."""
    crc = init
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ xor_out


def crc_calculate_crc8(data: bytes, start: int, first_call: bool) -> int:
    """AUTOSAR ``Crc_CalculateCRC8`` as its specification words it: the initial value 0xFF on
    a first call, else ``start XOR 0xFF``; the result XORed with 0xFF."""
    init = 0xFF if first_call else start ^ 0xFF
    return crc8_bitwise(data, init, 0xFF)


def e2e_p01_crc(data_id: int, payload: bytes) -> int:
    """E2E profile 1's CRC (data-ID mode both) as its protect function chains it."""
    crc = crc_calculate_crc8(bytes([data_id & 0xFF]), 0xFF, False)
    crc = crc_calculate_crc8(bytes([data_id >> 8]), crc, False)
    crc = crc_calculate_crc8(payload, crc, False)
    return crc ^ 0xFF


def test_the_crc_is_sae_j1850_with_the_autosar_check_value():
    assert crc8_bitwise(b"123456789", 0xFF, 0xFF) == 0x4B  # the published check value
    assert e2e.crc8_sae_j1850(b"123456789") == 0x4B
    rng = random.Random(1)
    for n in (0, 1, 3, 8, 31):
        data = bytes(rng.randrange(256) for _ in range(n))
        assert e2e.crc8_sae_j1850(data) == crc8_bitwise(data, 0xFF, 0xFF)


def test_the_e2e_crc_is_profile_1s_chain_over_data_id_and_payload():
    rng = random.Random(2)
    for _ in range(50):
        data_id = rng.randrange(65536)
        payload = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 8)))
        assert e2e.e2e_crc(data_id, payload) == e2e_p01_crc(data_id, payload)
    # the chain is the plain division with start 0 and no final XOR
    assert e2e.e2e_crc(0x1234, b"\x01\x02") == crc8_bitwise(b"\x34\x12\x01\x02", 0, 0)


def test_every_command_to_the_simulator_is_protected():
    db = load()
    to_sim = {m.name for m in db.messages
              if any("SIM" in (s.receivers or []) for s in m.signals) and "SIM" not in m.senders}
    assert to_sim == {"VALVE_DEMAND", "ENGINE_CMD", "SCENARIO_TWC", "FUEL_OFFSET_CMD"}
    assert set(db.e2e) == to_sim
    assert len({s.data_id for s in db.e2e.values()}) == len(to_sim)  # one data ID each
    assert db.e2e["VALVE_DEMAND"].max_delta == 1 and db.e2e["ENGINE_CMD"].max_delta == 0


def test_encode_fills_the_counter_and_the_crc():
    db = CellDatabase()  # counters of its own
    spec = db.e2e["VALVE_DEMAND"]
    counters = []
    for i in range(17):
        msg = db.encode("VALVE_DEMAND", {"VALVE_DEMAND_L": 40.0, "VALVE_DEMAND_R": 50.0 + i})
        values = db.decode(msg)[1]
        counters.append(int(values["VALVE_DEMAND_CTR"]))
        data = bytes(msg.data)
        payload = data[:spec.crc_byte] + data[spec.crc_byte + 1:]
        assert data[spec.crc_byte] == e2e_p01_crc(spec.data_id, payload)
        assert values["VALVE_DEMAND_R"] == pytest.approx(50.0 + i)
    assert counters == [*range(15), 0, 1]  # 0..14, then round again
    # a counter or a CRC given explicitly is kept (a test forging a frame)
    forged = db.encode("VALVE_DEMAND", {"VALVE_DEMAND_L": 0.0, "VALVE_DEMAND_R": 0.0,
                                        "VALVE_DEMAND_CTR": 9, "VALVE_DEMAND_CRC": 0x55})
    assert db.decode(forged)[1]["VALVE_DEMAND_CTR"] == 9 and forged.data[spec.crc_byte] == 0x55
    # the runtime finds the message from its payload signals alone
    assert [m.name for m in db.messages_carrying({"VALVE_DEMAND_L", "VALVE_DEMAND_R"})] == \
        ["VALVE_DEMAND"]


def _frame(db, counter, crc=None, left=10.0):
    values = {"VALVE_DEMAND_L": left, "VALVE_DEMAND_R": left, "VALVE_DEMAND_CTR": counter}
    if crc is not None:
        values["VALVE_DEMAND_CRC"] = crc
    return bytes(db.encode("VALVE_DEMAND", values).data)


def test_the_receiver_discards_bad_crc_repeats_jumps_and_old_frames():
    db = CellDatabase()
    spec = db.e2e["VALVE_DEMAND"]
    rx = e2e.Receiver()
    good = _frame(db, 3)
    assert rx.check(spec, good, 3, 0.0) is None  # the first frame is accepted
    bad = bytearray(_frame(db, 4))
    bad[0] ^= 0x01  # one payload bit flipped
    assert rx.check(spec, bytes(bad), 4, 0.0) == "crc"
    assert rx.check(spec, good, 3, 0.0) == "repeated"
    assert rx.check(spec, _frame(db, 4), 4, 0.15) == "too_old"  # over one 100 ms cycle
    assert rx.check(spec, _frame(db, 4), 4, 0.05) is None
    assert rx.check(spec, _frame(db, 6), 6, 0.0) == "skipped"  # 4 -> 6: one lost, MaxDelta 1
    assert rx.check(spec, _frame(db, 7), 7, 0.0) is None  # followed from the new sequence
    assert rx.check(spec, _frame(db, 0), 0, 0.0) == "skipped"  # 7 -> 0 is 8 steps on
    assert rx.check(spec, _frame(db, 1, crc=0x00 if _frame(db, 1)[4] else 0x01), 1, 0.0) == "crc"
    assert rx.by_reason() == {"crc": 2, "repeated": 1, "skipped": 2, "too_old": 1}
    assert rx.discarded[("VALVE_DEMAND", "skipped")] == 2
    # an operator command (max delta 0): any new counter, never a repeated one
    cmd = db.e2e["ENGINE_CMD"]
    frame = bytes(db.encode("ENGINE_CMD", {"ENGINE_RESET_REQ": 5, "ENGINE_RESET_CONFIRM": 0,
                                           "ENGINE_CMD_CTR": 2}).data)
    jump = bytes(db.encode("ENGINE_CMD", {"ENGINE_RESET_REQ": 5, "ENGINE_RESET_CONFIRM": 0,
                                          "ENGINE_CMD_CTR": 11}).data)
    assert rx.check(cmd, frame, 2, 0.0) is None
    assert rx.check(cmd, jump, 11, 0.0) is None
    assert rx.check(cmd, jump, 11, 0.0) == "repeated"


def test_a_protected_message_without_its_counter_or_crc_is_refused_naming_it(tmp_path):
    text = (load().path.read_text()
            .replace(" SG_ VALVE_DEMAND_CTR : 40|4@1+ (1,0) [0|14] \"\" SIM\n", ""))
    bad = tmp_path / "bad.dbc"
    bad.write_text(text)
    with pytest.raises(ConfigError, match=r"bad.dbc: E2E message VALVE_DEMAND needs an "
                                          r"unsigned 4-bit signal VALVE_DEMAND_CTR"):
        CellDatabase([bad])
    text = load().path.read_text().replace("VALVE_DEMAND_CRC : 32|8", "VALVE_DEMAND_CRC : 33|7")
    bad.write_text(text)
    with pytest.raises(ConfigError, match="VALVE_DEMAND_CRC on a whole byte"):
        CellDatabase([bad])
