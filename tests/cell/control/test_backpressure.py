"""PI back-pressure controller (seed 004, Figure 10): math against a hand-written reference,
anti-windup, rate limit, bumpless transfer, validation and its frames on the bus."""

import itertools
import math

import pytest

from cell.control.backpressure import PIController, controllers
from cell.core.errors import ParamError
from cell.runtime.scheduler import Runtime

R = 680.0
RUNNING = 1.0  # ENGINE_STATE (DBC VAL_ 259)


def reference_pi(ys, kp, ki, dt, u0):
    """Textbook reverse-acting PI, no limits: e = y - r, I starts at u0 - kp e0 (bumpless)."""
    out, integral = [], None
    for y in ys:
        e = y - R
        if integral is None:
            integral = u0 - kp * e
        else:
            integral += ki * e * dt
        out.append(kp * e + integral)
    return out


def drive(pi, ys, dt=0.1, pos=None):
    out = []
    for i, y in enumerate(ys):
        inputs = {pi.feedback: y}
        if pi.track:
            inputs[pi.track] = pos if pos is not None else 50.0
        if pi.interlock:
            inputs[pi.interlock] = RUNNING  # the engine runs
        out.append(pi.step(i * dt, inputs)[pi.output])
    return out


def test_p_and_i_terms_match_the_reference():
    ys = [600.0, 650.0, 700.0, 720.0, 690.0, 640.0, 680.0, 710.0]
    pi = PIController("R", "EXH_BP_R_Kalman", kp=0.02, ki=0.05, rate_limit=0.0, enable=True,
                      track="", manual=50.0)
    got = drive(pi, ys)
    assert got == pytest.approx(reference_pi(ys, 0.02, 0.05, 0.1, 50.0), abs=1e-12)
    # sign: above the setpoint opens the valve
    assert got[3] > got[2]


def test_anti_windup_holds_the_integrator_at_the_limit():
    pi = PIController("R", "x", kp=0.0, ki=0.1, rate_limit=0.0, out_max=60.0, enable=True,
                      track="", manual=55.0)
    drive(pi, [R + 100.0] * 50)  # pushes up for 5 s: unlimited it would reach 55 + 50
    assert pi.u == 60.0
    assert pi.integral == pytest.approx(60.0, abs=1.0)  # held near the limit, not 105
    # the moment the error reverses, the output leaves the limit (no wind-down delay)
    u = pi.step(5.0, {"x": R - 100.0, "ENGINE_STATE": RUNNING})[pi.output]
    assert u < 60.0


def test_backcalculation_also_bounds_the_integrator():
    pi = PIController("R", "x", kp=0.0, ki=0.1, rate_limit=0.0, out_max=60.0, enable=True,
                      track="", manual=55.0, antiwindup="backcalc", kt=5.0)
    drive(pi, [R + 100.0] * 100)
    assert pi.u == 60.0 and pi.integral < 63.0


def test_rate_limit_bounds_each_step():
    pi = PIController("R", "x", kp=1.0, ki=0.0, rate_limit=5.0, enable=True, track="",
                      manual=100.0)
    out = drive(pi, [R] + [R - 400.0] * 19)  # the error steps after the (bumpless) start
    steps = [a - b for a, b in itertools.pairwise(out)]
    assert max(steps) == pytest.approx(0.5)  # 5 %/s at 10 Hz
    assert out[-1] == pytest.approx(100.0 - 19 * 0.5)


def test_disabled_tracks_the_valve_and_enabling_is_bumpless():
    pi = PIController("R", "x", kp=0.05, ki=0.01)
    assert not pi.enable and pi.inputs == ["x", "VALVE_POS_R", "ENGINE_STATE"]
    assert drive(pi, [300.0] * 3, pos=100.0)[-1] == 100.0  # open loop: follows the valve
    pi.set_params({"enable": True})
    first = pi.step(0.3, {"x": 300.0, "VALVE_POS_R": 100.0, "ENGINE_STATE": RUNNING})[pi.output]
    assert first == 100.0  # no bump although kp * e = -19 %
    second = pi.step(0.4, {"x": 300.0, "VALVE_POS_R": 100.0, "ENGINE_STATE": RUNNING})[pi.output]
    assert second == pytest.approx(100.0 + 0.01 * (300.0 - R) * 0.1)


@pytest.mark.parametrize(
    "changes, field",
    [
        ({"kp": math.nan}, "kp"),
        ({"kp": -0.1}, "kp"),
        ({"ki": "fast"}, "ki"),
        ({"feedback": ""}, "feedback"),
        ({"feedback": 3}, "feedback"),
        ({"feedback": "EXH BP"}, "feedback"),
        ({"antiwindup": "magic"}, "antiwindup"),
        ({"enable": 1}, "enable"),
        ({"out_min": 80.0, "out_max": 20.0}, "out_min"),
        ({"out_max": 5.0, "kp": 0.1}, "out_max"),  # against the current out_min 10
        ({"kp": 0.1, "bogus": 1.0}, "bogus"),
        ({}, "body"),
    ],
)
def test_bad_values_name_the_field_and_change_nothing(changes, field):
    pi = PIController("L", out_min=10.0)
    before = pi.params()
    with pytest.raises(ParamError) as err:
        pi.set_params(changes)
    assert err.value.field == field
    assert pi.params() == before


def test_changing_feedback_changes_inputs():
    pi = PIController("L")
    assert pi.inputs[0] == "EXH_BP_L_Kalman"
    pi.set_params({"feedback": "EXH_BP_L_MAF", "kp": 0.02})
    assert pi.inputs == ["EXH_BP_L_MAF", "VALVE_POS_L", "ENGINE_STATE"] and pi.kp == 0.02
    pi.set_params({"track": "", "interlock": ""})
    assert pi.inputs == ["EXH_BP_L_MAF"]


def test_factory_and_demand_on_the_bus(db):
    blocks = controllers("raw", enable=True, track="", manual=70.0)
    assert [(b.name, b.inputs, b.outputs) for b in blocks] == [
        ("PI_L", ["EXH_BP_L", "ENGINE_STATE"], ["VALVE_DEMAND_L"]),
        ("PI_R", ["EXH_BP_R", "ENGINE_STATE"], ["VALVE_DEMAND_R"]),
    ]
    assert blocks[0].family == "controller" and blocks[0].kind == "pi"
    rt = Runtime(db, blocks)
    rt.ingest(db.encode("ENGINE_STATUS", {"ENGINE_STATE": RUNNING, "TRIP_REASON": 0.0,
                                          "EXH_BP_LIMIT": 1500.0, "ENGINE_LOAD": 100.0}, 0.0))
    for i in range(11):
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 500.0, "EXH_BP_R": 800.0}, i * 0.01))
    rt.advance(0.1)
    frames = [db.decode(m) for m in rt.take_outbox()]
    assert frames and all(msg.name == "VALVE_DEMAND" for msg, _ in frames)
    _, last = frames[-1]
    assert last["VALVE_DEMAND_L"] < 70.0 < last["VALVE_DEMAND_R"]  # low closes, high opens
