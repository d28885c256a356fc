"""The simulator process (cell/sim.py): live on a virtual bus, offline into a log, and its CLI."""

from __future__ import annotations

import argparse
import math
import threading
import uuid
from collections import defaultdict

import can
import pytest

from cell import sim
from cell.bus.interface import open_bus
from cell.bus.dbc import load
from cell.core.errors import ConfigError
from cell.core.settings import Settings

DB = load()
#: the SIM messages the default engine (large-diesel) sends; other engines' frames are skipped
SIM_MESSAGES = {m.name: m for m, _, _ in sim.build(Settings.build({}, environ={}), DB).schedule}


def frames_in(duration: float) -> int:
    """Frames of every SIM message at its DBC cycle time over ``duration`` s (t = 0 included)."""
    return sum(math.ceil(duration / (m.cycle_time / 1000) - 1e-9) for m in SIM_MESSAGES.values())


@pytest.fixture
def channel() -> str:
    return f"virtual:testcell-sim-{uuid.uuid4().hex[:8]}"


def settings(**given) -> Settings:
    return Settings.build(given, environ={})


def demand_frame(left: float, right: float) -> can.Message:
    return DB.encode("VALVE_DEMAND", {"VALVE_DEMAND_L": left, "VALVE_DEMAND_R": right})


def test_run_sends_frames_and_obeys_valve_demand(channel):
    sim_bus = open_bus(channel)
    peer = open_bus(channel)
    try:
        # queued before the plant's first step: noise the simulator must ignore, then a demand
        peer.send(can.Message(arbitration_id=0x7FF, data=b"\x01", is_extended_id=False))
        peer.send(can.Message(arbitration_id=0x200, data=b"\x01\x02", is_extended_id=False))
        peer.send(demand_frame(100.0, 40.0))
        plant = sim.run(sim_bus, settings(duty="rated", seed=0, speed=20, duration=1.0), db=DB)
    finally:
        sim_bus.shutdown()
    received = []
    while (msg := peer.recv(timeout=0.2)) is not None:
        received.append(msg)
    peer.shutdown()

    assert len(received) == frames_in(1.0)
    by_name = defaultdict(list)
    for msg in received:
        message, values = DB.decode(msg)
        by_name[message.name].append((msg.timestamp, values))
    assert set(by_name) == set(SIM_MESSAGES)
    truth = [v for _, v in by_name["TRUTH_ENGINE"]]
    left = [v["VALVE_POS_L_TRUE"] for v in truth]
    right = [v["VALVE_POS_R_TRUE"] for v in truth]
    assert left[0] == pytest.approx(40.0)
    assert left[-1] > left[0] + 3.0  # 5 %/s towards 100 for ~1 s
    assert right == pytest.approx([40.0] * len(right))  # demand 40 is inside the dead-band
    assert plant.plant("exhaust").valves["L"].demand == pytest.approx(100.0)
    # paced: one simulated second at speed 20 takes at least ~1/20 s of wall time
    stamps = [m.timestamp for m in received]
    assert max(stamps) - min(stamps) >= 0.9 * (1.0 - 0.01) / 20


def test_run_stops_on_the_stop_event(channel):
    sim_bus = open_bus(channel)
    stop = threading.Event()
    result = {}

    def target():
        result["plant"] = sim.run(sim_bus, settings(duty="transient", seed=1, speed=10),
                                  stop_event=stop, db=DB)

    thread = threading.Thread(target=target)
    thread.start()
    try:
        stop.wait(0.3)
        stop.set()
        thread.join(timeout=5)
        assert not thread.is_alive()
    finally:
        sim_bus.shutdown()
    assert result["plant"].t > 0


def test_run_logs_start_and_trip(channel, caplog):
    sim_bus = open_bus(channel)
    try:
        with caplog.at_level("INFO", logger="cell.sim"):
            plant = sim.run(sim_bus, settings(speed=50, duration=0.5, bp_limit=5.0), db=DB)
    finally:
        sim_bus.shutdown()
    assert plant["ENGINE_STATE"] == 2  # idle back-pressure (~8 mmH2O) is above a 5 mmH2O limit
    text = caplog.text
    assert "sim started" in text and "tripped" in text


def test_write_log_round_trips_through_python_can(tmp_path):
    path = tmp_path / "rated.log"
    n = sim.write_log(path, "rated", seed=2, duration=2.0, t0=10.0, progress=False)
    assert n == frames_in(2.0)
    frames = list(can.LogReader(str(path)))
    assert len(frames) == n
    assert frames[0].timestamp == pytest.approx(10.0)
    assert frames[-1].timestamp < 12.0
    names = {DB.decode(m)[0].name for m in frames}
    assert names == set(SIM_MESSAGES)
    # the log is the lockstep source written out: same frames as simulate()
    from cell.sim import simulate

    expected = [bytes(m.data) for m in simulate(DB, "rated", 2, 2.0, t0=10.0)]
    assert [bytes(m.data) for m in frames] == expected


def test_write_log_refuses_an_unknown_format(tmp_path):
    with pytest.raises(ConfigError, match="--out"):
        sim.write_log(tmp_path / "x.nope", "rated", 0, 1.0, progress=False)


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    sim.add_arguments(parser)
    return parser.parse_args(argv)


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["--speed", "0"], "--speed"),
        (["--speed", "-2"], "--speed"),
        (["--valve", "120"], "--valve"),
        (["--valve", "-1"], "--valve"),
        (["--duration", "-5"], "--duration"),
        (["--duty", "sprint"], "--duty"),
        (["--bp-limit", "-3"], "--bp-limit"),
    ],
)
def test_bad_arguments_raise_config_error_naming_the_option(argv, option):
    with pytest.raises(ConfigError, match=option):
        sim.main(parse(argv))


def test_main_writes_a_log(tmp_path):
    out = tmp_path / "t.log"
    args = parse(["--duty", "transient", "--duration", "1", "--out", str(out), "--valve", "100"])
    assert sim.main(args) == 0
    assert len(list(can.LogReader(str(out)))) == frames_in(1.0)


def test_main_runs_on_a_bus(channel):
    peer = open_bus(channel)
    try:
        args = parse(["--bus", channel, "--speed", "50", "--duration", "0.5", "--seed", "4"])
        assert sim.main(args) == 0
        count = 0
        while peer.recv(timeout=0.2) is not None:
            count += 1
    finally:
        peer.shutdown()
    assert count == frames_in(0.5)
