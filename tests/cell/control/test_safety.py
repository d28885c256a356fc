"""The PI controllers' safe behaviour (issue 20, point 2; issue 24's feedback check): hold or go
safe while the feedback is bad, go safe without wind-up while the engine is tripped (so the
engine does not re-trip after a reset), and refuse a feedback channel there is not."""

import can
import pytest

from cell import sim as simmod
from cell.control.backpressure import PIController, controllers, running_code
from cell.core.errors import ParamError
from cell.core.settings import Settings
from cell.estimators.backpressure import native_filters
from cell.runtime import supervision
from cell.runtime.scheduler import Runtime
from cell.sim.lockstep import Lockstep

RUNNING, TRIPPED = 1, 2  # VAL_ 259 ENGINE_STATE


def status(db, t, state=RUNNING):
    return db.encode("ENGINE_STATUS", {"ENGINE_STATE": state, "TRIP_REASON": 0,
                                       "EXH_BP_LIMIT": 1200, "ENGINE_LOAD": 100}, t)


def feed(rt, db, t0, t1, bp=900.0, state=RUNNING, every=None):
    """Frames from ``t0`` to ``t1`` at 100 Hz: back-pressure ``bp`` (or ``every(t)``),
    valves at 50 %, the engine in ``state``."""
    k = 0
    while t0 + 0.01 * k < t1 - 1e-9:
        t = round(t0 + 0.01 * k, 6)
        y = every(t) if every else bp
        if isinstance(y, can.Message):
            rt.ingest(y)
        else:
            rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": y, "EXH_BP_R": y}, t))
        rt.ingest(db.encode("VALVE_POS", {"VALVE_POS_L": 50.0, "VALVE_POS_R": 50.0}, t))
        if k % 10 == 0:
            rt.ingest(status(db, t, state))
        k += 1
    rt.advance(t1 - 0.01)


def test_the_running_state_is_read_from_the_dbc(db):
    sig = db.message("ENGINE_STATUS").get_signal_by_name("ENGINE_STATE")
    assert running_code() == RUNNING and str(sig.choices[RUNNING]) == "RUNNING"
    assert PIController("R").running_state == RUNNING


def forged(db, t, raw):
    m = db.message("EXH_BP")
    return can.Message(timestamp=t, arbitration_id=m.frame_id, is_extended_id=False,
                       data=m.encode({"EXH_BP_L": 70000, "EXH_BP_R": raw}, scaling=False, strict=False))


def test_an_out_of_range_value_is_invalid_counted_and_does_not_move_the_pi_output(db):
    """The issue's forged 21,474,836 mmH2O moved the demand from 18 % to 73 %. Now the value
    is invalid, the filter skips it and the controller holds its output through it."""
    runs = {}
    for checked in (False, True):
        rt = Runtime(db, [*native_filters(), *controllers("kalman", enable=True)])
        if not checked:  # the failure first: no range check on EXH_BP_R
            from cell.runtime.plausibility import Limit
            rt.plausibility.override([Limit("EXH_BP_R")])
        demand = []
        rt.tick_listeners.append(lambda t, rt=rt, d=demand: d.append(
            (round(t, 2), rt.channels["VALVE_DEMAND_R"].value, rt.channels["VALVE_DEMAND_R"].status)))
        feed(rt, db, 0.0, 3.0, bp=600.0)  # below the setpoint: the loop is closing the valve
        feed(rt, db, 3.0, 3.2, every=lambda t: forged(db, t, 2**31 - 1) if t >= 3.05 else 600.0)
        runs[checked] = (rt, dict((t, (v, s)) for t, v, s in demand))
    before = runs[True][1][3.0][0]
    assert before < 99.0 and runs[False][1][3.0][0] == before
    assert runs[False][1][3.1][0] > before + 0.3  # unchecked: the forged value opens the valve
    rt, demand = runs[True]
    assert demand[3.1] == (before, "ok") and demand[3.2 - 0.1][0] == before
    assert rt.channel("EXH_BP_R").status == "invalid" and rt.health()["implausible"]["EXH_BP_R"] >= 1
    assert rt.blocks["PI_R"].state()["mode"].startswith("hold: input EXH_BP_R_Kalman is invalid")


def test_bad_feedback_holds_for_hold_s_then_goes_to_the_safe_output(db):
    rt = Runtime(db, [*native_filters(), *controllers("kalman", enable=True, hold_s=0.5)])
    feed(rt, db, 0.0, 3.0, bp=500.0)  # below the setpoint: the loop closes the valve
    pi = rt.blocks["PI_R"]
    assert pi.u < 99.0 and pi.state()["mode"] == "auto"
    seen = []
    rt.tick_listeners.append(lambda t: seen.append((round(t, 2), pi.u, pi.state()["mode"][:4],
                                                    pi.integral)))
    # EXH_BP stops (the sensor's frames are lost); ENGINE_STATUS goes on
    k = 0
    while 3.0 + 0.1 * k < 4.5:
        rt.ingest(status(db, 3.0 + 0.1 * k))
        rt.ingest(db.encode("VALVE_POS", {"VALVE_POS_L": 50.0, "VALVE_POS_R": 50.0}, 3.0 + 0.1 * k))
        k += 1
    rt.advance(4.5)
    last_auto = [(u, i) for _, u, m, i in seen if m == "auto"][-1]
    held = [(u, i) for _, u, m, i in seen if m == "hold"]
    assert held and all(h == last_auto for h in held)  # output held, integrator frozen
    safe = [(t, u) for t, u, m, _ in seen if m == "safe"]
    first_bad = min(t for t, _, m, _ in seen if m != "auto")
    assert safe and safe[0][0] == pytest.approx(first_bad + 0.5) and all(u == 100.0 for _, u in safe)
    frames = [db.decode(f)[1] for f in rt.take_outbox() if f.arbitration_id == 0x200]
    assert frames[-1]["VALVE_DEMAND_R"] == 100.0  # the safe demand goes on the bus
    # the feedback returns: the loop starts bumplessly from the safe output
    feed(rt, db, 4.5, 6.0, bp=500.0)
    assert pi.state()["mode"] == "auto" and 100.0 - 0.5 * 15 - 1e-9 <= pi.u < 100.0


def test_a_tripped_engine_puts_the_output_at_safe_without_windup(db):
    rt = Runtime(db, [*native_filters(), *controllers("kalman", enable=True)])
    feed(rt, db, 0.0, 2.0, bp=700.0)
    feed(rt, db, 2.0, 8.0, bp=0.0, state=TRIPPED)  # the engine runs down: bp far below setpoint
    pi = rt.blocks["PI_R"]
    assert pi.u == 100.0 and pi.integral == 100.0 and pi.state()["mode"].startswith(
        "safe: ENGINE_STATE = 2")
    feed(rt, db, 8.0, 8.5, bp=300.0)  # reset: the loop restarts from fully open
    assert pi.state()["mode"] == "auto" and pi.u >= 100.0 - 0.5 * 5


def run_trip(db, interlock):
    """si-free large diesel in lockstep, both loops on: a set-point above the protection's
    limit drives the engine into a trip; 3 s later the operator resets it (as POST
    /engine/reset and its confirm do) with the set-point back at 680. Returns the trip and re-trip times,
    the demands during the trip and the integrator at the reset."""
    s = Settings.build({"engine": "large-diesel", "duty": "transient", "valve": 20.0},
                       environ={}).for_simulator()
    sim = simmod.build(s, db)
    rt = Runtime(db, [*native_filters(), *controllers("kalman", enable=True, setpoint=1400.0,
                                                       interlock=interlock)])
    trip = reset = retrip = challenge = None
    during = []
    integral = None
    for k, _ in Lockstep(sim, rt).steps(round(30.0 / sim.dt)):
        t = k * sim.dt
        state = rt.channels.get("ENGINE_STATE")
        tripped = state is not None and state.value == TRIPPED
        if tripped and trip is None:
            trip = t
        elif trip is not None and reset is None:
            during.append(rt.channels["VALVE_DEMAND_R"].value)
            if t >= trip + 3.0 and challenge is None:
                integral = rt.blocks["PI_R"].integral
                for b in "LR":
                    rt.set_params(f"PI_{b}", {"setpoint": 680.0})
                challenge = supervision.request_reset(rt)  # the two steps of a reset
            elif challenge is not None and t >= trip + 3.1 - 1e-9:
                supervision.confirm_reset(rt, challenge)
                reset = t
        elif reset is not None and t > reset + 0.3 and tripped and retrip is None:
            retrip = t
        if retrip is not None or (trip is None and t > 25.0):
            break
    return trip, reset, retrip, during, integral


@pytest.fixture(scope="module")
def trips(db):
    return {interlock: run_trip(db, interlock) for interlock in ("", "ENGINE_STATE")}


def test_without_the_interlock_the_loops_wind_the_valves_shut_and_the_engine_re_trips(trips):
    trip, reset, retrip, during, integral = trips[""]
    assert trip is not None and reset is not None
    assert min(during) < during[0] - 10.0 < 10.0  # the loop winds the valve shut
    assert retrip is not None and retrip - reset < 3.0  # the re-trip 0.57 s after reset


def test_with_the_interlock_the_valves_open_and_the_engine_does_not_re_trip(trips):
    trip, reset, retrip, during, integral = trips["ENGINE_STATE"]
    assert trip is not None and reset is not None and trip + 3.0 <= reset
    assert during[5:] == [100.0] * len(during[5:])  # safe within the first ticks of the trip
    assert integral == 100.0  # no wind-up: the integrator sits at the safe output
    assert retrip is None  # ran on to the end of the run with no second trip


# -- feedback channels (issue 24) ------------------------------------------------------------
def test_a_feedback_that_is_no_channel_is_refused_naming_the_channels_there_are(db):
    rt = Runtime(db, [*native_filters(), *controllers("kalman")])
    before = rt.blocks["PI_R"].params()
    with pytest.raises(ParamError) as err:
        rt.set_params("PI_R", {"feedback": "NOPE", "kp": 0.01}, family="controller")
    assert err.value.field == "feedback"
    msg = str(err.value)
    assert "'NOPE' is not a channel" in msg and "channels in mmH2O" in msg
    assert "EXH_BP_R_Kalman" in msg and "EXH_BP_R_MAF" in msg and "VALVE_POS_R," not in msg
    assert rt.blocks["PI_R"].params() == before


def test_a_feedback_of_another_unit_is_refused(db):
    rt = Runtime(db, controllers("kalman"))
    with pytest.raises(ParamError, match=r"ENGINE_SPEED is in rpm, PI_R needs mmH2O"):
        rt.set_params("PI_R", {"feedback": "ENGINE_SPEED"})
    with pytest.raises(ParamError, match=r"interlock: 'NOPE' is not a channel"):
        rt.set_params("PI_R", {"interlock": "NOPE"})
    assert rt.set_params("PI_R", {"feedback": "EXH_BP_R", "interlock": ""})["feedback"] == "EXH_BP_R"
