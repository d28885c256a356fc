"""Scenario commands (cell/bus/scenario.py): generic over the DBC, from the CLI and over HTTP."""

from __future__ import annotations

import uuid
from pathlib import Path

import pytest
from tests.helpers.client import local_client

from cell.app import cli
from cell.bus.interface import open_bus
from cell.app.cell import Cell
from cell.bus.dbc import load
from cell.core.errors import ConfigError, ParamError
from cell.runtime.scheduler import Runtime
from cell.bus.scenario import parse_assignments, scenario_frames, scenario_keys
from service.main import create_app

RIG = Path(__file__).resolve().parents[2] / "data" / "dbc" / "scenario.dbc"


@pytest.fixture(scope="module")
def db():
    return load([RIG])


def _payload(db, msg):
    """A command frame's values but its E2E counter and CRC, whose CRC is checked."""
    message, values = db.decode(msg)
    spec = db.e2e[message.name]
    assert msg.data[spec.crc_byte] == spec.crc_of(bytes(msg.data))
    return {k: values[k] for k in db.payload_signals(message)}


def test_keys_are_the_signals_scenario_sends_to_sim(db):
    keys = scenario_keys(db)
    assert {"osc", "rig_level", "rig_gain", "rig_mode"} <= set(keys)
    assert "rig_valve" not in keys  # sent by RUNTIME, not a scenario
    assert keys["osc"].message.name == "SCENARIO_TWC" and keys["osc"].initial == 1.0
    assert keys["rig_gain"].initial == pytest.approx(2.5)  # GenSigStartValue 25 x 0.1
    assert keys["rig_level"].initial == 0.0  # no start value: 0


def test_a_command_sets_the_given_keys_and_the_start_value_of_the_others(db):
    frames = scenario_frames(db, {"RIG_LEVEL": "42.5", "rig_mode": "fast"}, 7.0)
    assert len(frames) == 1 and frames[0].timestamp == 7.0
    message, values = db.decode(frames[0])
    assert message.name == "RIG_SCENARIO"
    assert values == {"RIG_LEVEL": 42.5, "RIG_GAIN": 2.5, "RIG_MODE": 2.0}
    two = scenario_frames(db, {"osc": 0.6, "rig_gain": 3})
    assert sorted(db.decode(f)[0].name for f in two) == ["RIG_SCENARIO", "SCENARIO_TWC"]
    assert _payload(db, two[0]) == {"OSC": 0.6}


@pytest.mark.parametrize("values,field,needle", [
    ({"osk": 0.5}, "osk", "is not a scenario key; known: engine_reset_confirm, engine_reset_req, "
     "fuel_offset_cyl_1, fuel_offset_cyl_2, fuel_offset_cyl_3, fuel_offset_cyl_4, osc, rig_gain, "
     "rig_level, rig_mode"),
    ({"osc": 2.5}, "osc", "must be within [0.05, 2] (the DBC range of OSC in SCENARIO_TWC), got 2.5"),
    ({"osc": 0.01}, "osc", "must be within [0.05, 2]"),
    ({"rig_level": -1}, "rig_level", "must be within [0, 100] %"),
    ({"osc": "half"}, "osc", "must be a number, got 'half'"),
    ({"rig_mode": "turbo"}, "rig_mode", "or one of OFF, SLOW, FAST"),
    ({"osc": float("nan")}, "osc", "must be finite"),
    ({"osc": True}, "osc", "must be a number, got bool"),
    ({}, "body", "names no scenario key; known: engine_reset_confirm, engine_reset_req, fuel_offset_cyl_1"),
])
def test_bad_commands_are_refused_by_name(db, values, field, needle):
    with pytest.raises(ParamError) as err:
        scenario_frames(db, values)
    assert err.value.field == field and needle in err.value.message


def test_assignments_parse_and_malformed_ones_are_named():
    assert parse_assignments(["osc=0.5", " RIG_MODE = slow"]) == {"osc": "0.5", "rig_mode": "slow"}
    for items, needle in ((["osc"], "argument 1 'osc': expected KEY=VALUE"),
                          (["osc=1", "=2"], "argument 2 '=2'"),
                          (["osc=1", "OSC=2"], "OSC is given twice")):
        with pytest.raises(ConfigError, match=needle):
            parse_assignments(items)


def test_the_cli_sends_the_frame_on_the_bus(db, capsys):
    channel = f"virtual:scn-{uuid.uuid4().hex[:8]}"
    peer = open_bus(channel)
    try:
        assert cli.main(["scenario", "osc=0.5", "--bus", channel]) == 0
        msg = peer.recv(timeout=1.0)
    finally:
        peer.shutdown()
    assert _payload(db, msg) == {"OSC": 0.5}
    assert "sent SCENARIO_TWC (0x220)" in capsys.readouterr().out


def test_the_cli_refuses_an_unknown_key_or_a_value_out_of_range(capsys):
    channel = f"virtual:scn-{uuid.uuid4().hex[:8]}"
    peer = open_bus(channel)
    try:
        assert cli.main(["scenario", "osk=0.5", "--bus", channel]) == 2
        assert ("osk: is not a scenario key; known: engine_reset_confirm, engine_reset_req, "
                "fuel_offset_cyl_1") in capsys.readouterr().err
        assert cli.main(["scenario", "osc=9", "--bus", channel]) == 2
        assert "osc: must be within [0.05, 2]" in capsys.readouterr().err
        assert peer.recv(timeout=0.2) is None  # nothing was sent
    finally:
        peer.shutdown()
    assert cli.main(["scenario", "--list"]) == 0
    assert "osc" in capsys.readouterr().out


def test_post_scenario_queues_the_frame_and_refuses_bad_bodies(db):
    rt = Runtime(db)
    client = local_client(create_app(Cell(runtime=rt, bus="virtual:test")))
    keys = {k["key"]: k for k in client.get("/scenario").json()}
    assert keys["osc"]["minimum"] == 0.05 and keys["osc"]["initial"] == 1.0
    r = client.post("/scenario", json={"rig_level": 120})
    assert r.status_code == 422
    assert r.json()["detail"][0]["loc"] == ["body", "rig_level"]
    assert "within [0, 100]" in r.json()["detail"][0]["msg"]
    r = client.post("/scenario", json={"nope": 1})
    assert r.status_code == 422 and "osc, rig_gain" in r.json()["detail"][0]["msg"]
    assert rt.outbox == []  # nothing queued by a refused command
    r = client.post("/scenario", json={"osc": 0.5})
    assert r.status_code == 200
    assert r.json()["sent"] == [{"message": "SCENARIO_TWC", "frame_id": 0x220, "signals": {"OSC": 0.5}}]
    assert len(rt.outbox) == 1 and _payload(db, rt.outbox[0]) == {"OSC": 0.5}
