"""The PI back-pressure controller written as a .fdv script (issue: "can also be written as
a .fdv script"), against a plain PI written in the test, and onto the bus."""

from importlib.resources import files

import numpy as np
import pytest

from cell.estimators.backpressure import native_filters
from cell.scripts import load_script
from cell.runtime.scheduler import Runtime

TEXT = files("cell.scripts").joinpath("examples/pi_controller.fdv").read_text()


def reference_pi(measurements, kp=0.005, ki=0.013, dt=0.1, sp=680.0, rate=5.0):
    """Reverse-acting PI with conditional integration and a rate limit, written plainly."""
    integ, u, out = 100.0, 100.0, []
    for y in measurements:
        e = y - sp
        want = kp * e + integ + ki * e * dt
        if 0.0 <= want <= 100.0:
            integ = integ + ki * e * dt
        target = min(max(want, 0.0), 100.0)
        u = u + min(max(target - u, -rate * dt), rate * dt)
        out.append(u)
    return np.array(out)


def test_pi_script_matches_a_plain_pi_and_puts_demand_on_the_bus(db):
    block = load_script("pi_controller.fdv", TEXT)
    assert {"kp", "ki", "setpoint"} <= set(block.constants())
    rt = Runtime(db, [*native_filters(), block])
    seen = []
    rt.tick_listeners.append(lambda t: seen.append(
        (rt.channels["EXH_BP_R_Kalman"].value, rt.channels["VALVE_DEMAND_R"].value)))
    rng = np.random.default_rng(2)
    for i in range(3000):  # 30 s: pressure falls from 900 towards the setpoint and below
        level = 900.0 - 10.0 * i * 0.01
        y = level + rng.normal(0, 40)
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": y, "EXH_BP_R": y}, i * 0.01))
    rt.advance(29.99)
    kal, demand = np.array(seen).T
    np.testing.assert_allclose(demand, reference_pi(kal), atol=1e-9)
    assert demand.min() < 100.0  # the loop moved the valve...
    assert np.all(np.abs(np.diff(demand)) <= 0.5 + 1e-9)  # ...at most 5 %/s
    frames = [f for f in rt.take_outbox() if f.arbitration_id == db.message("VALVE_DEMAND").frame_id]
    assert len(frames) == len(seen)
    _, last = db.decode(frames[-1])
    assert last["VALVE_DEMAND_R"] == pytest.approx(demand[-1], abs=0.005)


def test_pi_script_and_native_controllers_cannot_both_drive_the_valve(db):
    from cell.control.backpressure import controllers
    from cell.core.errors import ConfigError

    rt = Runtime(db, [*native_filters(), *controllers("kalman")])
    with pytest.raises(ConfigError, match="VALVE_DEMAND_L.*PI_L"):
        rt.add_block(load_script("pi_controller.fdv", TEXT))
