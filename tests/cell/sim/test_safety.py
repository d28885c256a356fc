"""The simulator as the engine controller and the valve actuators: it refuses forged commands,
falls to a safe state when the demand stops, resets a trip only in two steps once its cause
has cleared, and counts what it cannot decode. All on bus time, in lockstep: no wall clock."""

from __future__ import annotations

import os

import can
import pytest

from cell.bus.dbc import CellDatabase
from cell.core.errors import ConfigError
from cell.core.settings import Settings
from cell.experiments.backpressure import case_cell, rated_hold
from cell.plant import TRIPPED
from cell.plant.backpressure import (RESET_DONE, RESET_PENDING, RESET_REFUSED_BAD_FRAME,
                                     RESET_REFUSED_CAUSE, RESET_REFUSED_NO_REQUEST, RUNNING)
from cell.plant.diesel import EngineParams
from cell.plant.large_diesel import large_diesel
from cell.sim import ParentWatch, build
from cell.sim.lockstep import Lockstep
from cell.sim.simulator import SAFE_DEMAND_TIMEOUT, SAFE_NONE, SAFE_PARENT_LOST, Simulator

IDLE = EngineParams().idle_speed


def at_rated(initial_valve: float):
    """The engine at rated from t = 0, in steady state (no 80 s ramp to wait for)."""
    return large_diesel(rated_hold(EngineParams(), 60.0), 0, initial_valve=initial_valve)


@pytest.fixture(scope="module")
def db():
    return CellDatabase()  # counters of its own: no other test's frames in between


def status(sim: Simulator) -> dict[str, float]:
    """What the simulator's status frames say now (decoded from the frames it sends)."""
    out = {}
    for m in (sim.db.message("SIM_STATUS"), sim.db.message("SIM_E2E")):
        names = [s.name for s in m.signals]
        msg = sim.db.encode(m.name, {n: sim._own[n]() for n in names}, 0.0)
        out.update(sim.db.decode(msg)[1])
    return out


def steps(sim: Simulator, seconds: float, each=None) -> None:
    for _ in range(round(seconds / sim.dt)):
        if each is not None:
            each()
        sim.frames()
        sim.step()


def stamped(db: CellDatabase, sim: Simulator, values: dict[str, float],
            name: str = "VALVE_DEMAND") -> can.Message:
    return db.encode(name, values, sim.t0 + sim.t)


# -- the closed loop: the runtime's demand carries counter and CRC, the watchdog -------------
@pytest.fixture(scope="module")
def closed_loop(db):
    """The engine at rated under both PI loops (runtime in lockstep), 8 s; then the loops are
    switched off (the demand stops) for 3 s; then on again for 2 s. Records every step."""
    sim, rt, ctrls = case_cell("kalman", 0, 0.005, 0.013, 60.0, 680.0, EngineParams(), None,
                               db, None)
    for c in ctrls:
        rt.set_params(c.name, {"enable": True}, family="controller")
    banks = sim.plant.plant("exhaust")
    engine = sim.plant.plant("engine")
    rec = []
    off_at, on_at = 8.0, 11.0
    for _k, _ in Lockstep(sim, rt).steps(round(13.0 / sim.dt)):
        t = sim.t
        if abs(t - off_at) < 1e-9 or abs(t - on_at) < 1e-9:
            for c in ctrls:
                rt.set_params(c.name, {"enable": t >= on_at}, family="controller")
        rec.append((t, sim.safe_state, banks.valves["L"].demand, banks.valves["R"].demand,
                    rt.channels["VALVE_DEMAND_L"].value, engine.speed, dict(status(sim))))
    return rec, off_at, on_at


def test_the_runtimes_demand_is_valid_and_moves_the_valves(closed_loop):
    rec, off_at, _ = closed_loop
    before = [r for r in rec if 1.0 <= r[0] < off_at]
    assert all(r[1] == SAFE_NONE for r in before)
    assert before[-1][6]["E2E_DISCARDED"] == 0  # every frame of the runtime passed
    # the valve follows the PI demand (one exchange late at most)
    moved = [r for r in before if abs(r[2] - 100.0) > 1.0]
    assert moved and all(abs(r[2] - r[4]) < 2.0 for r in moved)


def test_demand_stops_valves_open_and_engine_idles_within_three_cycles(closed_loop):
    rec, off_at, on_at = closed_loop
    last_demand = off_at  # the loops go off after the exchange of off_at: its tick sent one
    safe = [r for r in rec if r[1] == SAFE_DEMAND_TIMEOUT]
    assert safe, "the watchdog never fired"
    t_safe = safe[0][0]
    assert last_demand + 0.3 < t_safe <= last_demand + 0.3 + 0.03  # 3 cycles + 3 steps
    assert safe[0][6]["SAFE_STATE"] == SAFE_DEMAND_TIMEOUT  # the status frame says so
    assert all(r[2] == 100.0 and r[3] == 100.0 for r in safe)  # both valves to fully open
    at_rated = [r[5] for r in rec if r[0] == pytest.approx(t_safe, abs=1e-6)][0]
    later = [r[5] for r in rec if r[0] == pytest.approx(on_at - 0.01, abs=1e-6)][0]
    assert at_rated > 1700 and later < at_rated - 500  # running down to idle
    assert later > IDLE - 1.0


def test_the_safe_state_ends_when_valid_demand_resumes(closed_loop):
    rec, _, on_at = closed_loop
    after = [r for r in rec if r[0] >= on_at + 0.2]
    assert after and all(r[1] == SAFE_NONE for r in after)
    assert after[-1][6]["SAFE_STATE"] == SAFE_NONE and after[-1][6]["E2E_DISCARDED"] == 0


def test_a_cell_that_never_sent_a_demand_is_not_put_in_the_safe_state(db):
    sim = Simulator(large_diesel("rated", 0, initial_valve=60.0), db)
    steps(sim, 2.0)
    assert sim.safe_state == SAFE_NONE and sim.plant.plant("exhaust").valves["L"].demand == 60.0


# -- forged frames ----------------------------------------------------------------------------
def test_600_forged_zero_demands_without_valid_e2e_do_not_close_the_valve(db):
    def attack(valid: bool) -> tuple[Simulator, float]:
        sim = Simulator(at_rated(100.0), db)
        sent = 0

        def forge():
            nonlocal sent
            if sent < 600:
                msg = stamped(db, sim, {"VALVE_DEMAND_L": 0.0, "VALVE_DEMAND_R": 0.0})
                if not valid:  # a forger without the data ID: a CRC that does not match
                    data = bytearray(msg.data)
                    data[db.e2e["VALVE_DEMAND"].crc_byte] ^= 0x5A
                    msg.data = data
                sim.receive(msg)
                sent += 1
        steps(sim, 6.0, forge)
        return sim, sim.plant.plant("exhaust").valves["L"].position

    # the attack of the issue, with frames that pass E2E: the valve closes
    trusted, pos = attack(valid=True)
    assert pos < 80.0
    forged, pos = attack(valid=False)
    assert pos == 100.0 and forged.plant.plant("exhaust").state == RUNNING
    assert forged.e2e.discarded == {("VALVE_DEMAND", "crc"): 600}
    assert status(forged)["E2E_CRC_ERRORS"] == 600 and forged.safe_state == SAFE_NONE


def test_wrong_crc_stale_counter_and_replay_move_nothing_and_are_counted(db):
    sim = Simulator(at_rated(100.0), db)
    banks = sim.plant.plant("exhaust")
    recorded = []

    def genuine(level):
        def send():
            if sim.k % 10 == 0:  # the demand's 100 ms cycle
                msg = stamped(db, sim, {"VALVE_DEMAND_L": level, "VALVE_DEMAND_R": level})
                recorded.append(msg)
                assert sim.receive(msg)
        return send
    steps(sim, 1.0, genuine(90.0))
    assert banks.valves["L"].demand == 90.0
    replay = list(recorded)
    # a wrong CRC: one bit of the payload flipped (of the next counter's frame)
    last = sim.e2e.last["VALVE_DEMAND"]
    bad = stamped(db, sim, {"VALVE_DEMAND_L": 10.0, "VALVE_DEMAND_R": 10.0,
                            "VALVE_DEMAND_CTR": (last + 1) % 15})
    data = bytearray(bad.data)
    data[1] ^= 0x04
    sim.receive(can.Message(timestamp=bad.timestamp, arbitration_id=0x200, data=bytes(data),
                            is_extended_id=False))
    # a stale counter: the last one accepted, with a valid CRC
    sim.receive(stamped(db, sim, {"VALVE_DEMAND_L": 10.0, "VALVE_DEMAND_R": 10.0,
                                  "VALVE_DEMAND_CTR": last}))
    assert banks.valves["L"].demand == 90.0
    steps(sim, 1.0, genuine(90.0))
    # a replay of the recorded sequence, as recorded (old time stamps)
    for msg in replay:
        sim.receive(msg)
    assert banks.valves["L"].demand == 90.0
    d = sim.e2e.discarded
    assert d[("VALVE_DEMAND", "crc")] == 1 and d[("VALVE_DEMAND", "repeated")] == 1
    assert d[("VALVE_DEMAND", "too_old")] == len(replay)
    s = status(sim)
    assert (s["E2E_CRC_ERRORS"], s["E2E_REPEATED"], s["E2E_TOO_OLD"]) == (1, 1, len(replay))
    assert s["E2E_DISCARDED"] == 2 + len(replay)


def test_a_frame_the_simulator_cannot_decode_is_counted_and_skipped(db):
    sim = Simulator(large_diesel("rated", 0), db)
    assert not sim.receive(can.Message(arbitration_id=0x200, data=b"\x01\x02",
                                       is_extended_id=False))
    assert not sim.receive(can.Message(arbitration_id=0x7FF, data=b"\x00"))  # not ours: ignored
    assert sim.undecodable == 1 and status(sim)["SIM_UNDECODABLE"] == 1


# -- the two-step reset -------------------------------------------------------------------------
def reset_frame(db, sim, request=0, confirm=0):
    return stamped(db, sim, {"ENGINE_RESET_REQ": request, "ENGINE_RESET_CONFIRM": confirm},
                   "ENGINE_CMD")


def test_a_trip_clears_only_by_request_then_confirm_once_its_cause_cleared(db):
    sim = Simulator(at_rated(5.0), db)
    banks = sim.plant.plant("exhaust")
    while banks.state != TRIPPED and sim.t < 5.0:
        steps(sim, 0.01)
    assert banks.state == TRIPPED
    # while the back-pressure is still above the limit less the margin: refused
    assert not banks.cause_cleared()
    sim.receive(reset_frame(db, sim, request=11))
    steps(sim, 0.1)
    assert banks.reset_state == RESET_PENDING
    sim.receive(reset_frame(db, sim, confirm=11))
    steps(sim, 0.1)
    assert banks.state == TRIPPED and banks.reset_state == RESET_REFUSED_CAUSE
    steps(sim, 15.0)  # the engine runs down: the cause clears
    assert banks.cause_cleared()
    # one forged frame, with any value, never resets
    for frame in (reset_frame(db, sim, confirm=42), reset_frame(db, sim, request=42, confirm=42)):
        sim.receive(frame)
        steps(sim, 0.1)
        assert banks.state == TRIPPED
    assert banks.reset_state == RESET_REFUSED_BAD_FRAME
    # a confirm of another value, or later than the window: refused
    sim.receive(reset_frame(db, sim, request=7))
    steps(sim, 0.5)
    sim.receive(reset_frame(db, sim, confirm=8))
    steps(sim, 0.1)
    assert banks.state == TRIPPED and banks.reset_state == RESET_REFUSED_NO_REQUEST
    sim.receive(reset_frame(db, sim, request=9))
    steps(sim, 2.1)
    sim.receive(reset_frame(db, sim, confirm=9))
    steps(sim, 0.1)
    assert banks.state == TRIPPED and banks.reset_state == RESET_REFUSED_NO_REQUEST
    # the two steps within the window, the cause cleared: reset
    sim.receive(reset_frame(db, sim, request=1234))
    steps(sim, 1.0)
    assert banks.state == TRIPPED
    sim.receive(reset_frame(db, sim, confirm=1234))
    steps(sim, 0.01)
    assert banks.state == RUNNING and banks.reset_state == RESET_DONE
    assert sim.plant.signals["RESET_STATE"] == RESET_DONE


def test_the_watchdog_timeout_is_configurable_and_refuses_nonsense(db):
    sim = Simulator(at_rated(60.0), db, demand_timeout_cycles=5)
    banks = sim.plant.plant("exhaust")

    def demand():
        if sim.k % 10 == 0 and sim.t < 1.0 - 1e-9:
            assert sim.receive(stamped(db, sim, {"VALVE_DEMAND_L": 70.0, "VALVE_DEMAND_R": 70.0}))
    last = 0.9  # the last demand
    safe_at = None
    for _ in range(200):
        demand()
        sim.frames()
        sim.step()
        if safe_at is None and sim.safe_state == SAFE_DEMAND_TIMEOUT:
            safe_at = sim.t
    assert last + 0.5 < safe_at <= last + 0.5 + 0.02 and banks.valves["L"].demand == 100.0
    for bad in (0, -1, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="--demand-timeout-cycles must be a number > 0"):
            Simulator(at_rated(60.0), db, demand_timeout_cycles=bad)
    with pytest.raises(ConfigError, match="--demand-timeout-cycles"):
        Settings.build({"demand_timeout_cycles": 0.0}, environ={}).check()
    built = build(Settings.build({"demand_timeout_cycles": 7.0}, environ={}), db)
    assert built.watched["VALVE_DEMAND"][0] == pytest.approx(0.7)


def test_the_parent_watch_sees_a_parent_that_is_not_ours_any_more():
    assert not ParentWatch().lost()  # pytest's parent is alive
    assert ParentWatch(parent_pid=os.getpid()).lost()  # we are not our own parent
    sim = Simulator(at_rated(60.0), CellDatabase())
    sim.parent_lost()
    assert sim.safe_state == SAFE_PARENT_LOST and sim.plant.plant("exhaust").safe
    sim.watchdog()
    assert sim.safe_state == SAFE_PARENT_LOST  # for good
