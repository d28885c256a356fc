"""One bank's controller off, the other's on (issue 24, point 3): both banks' demands share
the ``VALVE_DEMAND`` frame, so switching one PI off must not keep the whole frame off the bus,
or the simulator's demand watchdog takes both valves safe. On the simulator, in lockstep."""

import pytest

from cell.bus.dbc import CellDatabase
from cell.experiments.backpressure import case_cell
from cell.plant.diesel import EngineParams
from cell.sim.lockstep import Lockstep
from cell.sim.simulator import SAFE_NONE

OFF_AT, END = 25.0, 40.0


@pytest.fixture(scope="module")
def one_bank_off():
    """Both loops on at rated from t = 0 (valves fully open), PI_R switched off at OFF_AT."""
    db = CellDatabase()  # E2E counters of its own
    sim, rt, ctrls = case_cell("kalman", 0, 0.005, 0.013, END, 680.0, EngineParams(), None,
                               db, None)
    for c in ctrls:
        rt.set_params(c.name, {"enable": True}, family="controller")
    banks = sim.plant.plant("exhaust")
    rec = []
    for k, _ in Lockstep(sim, rt, stride=10).steps(round(END / sim.dt)):
        t = sim.t
        if abs(t - OFF_AT) < 1e-9:
            rt.set_params("PI_R", {"enable": False}, family="controller")
        if k % 10 == 0:
            rec.append((t, sim.safe_state, banks.valves["L"].demand, banks.valves["R"].demand,
                        banks.valves["R"].position, rt.channels["EXH_BP_L_TRUE"].value
                        if "EXH_BP_L_TRUE" in rt.channels else None,
                        rt.blocks["PI_R"].mode))
    return rec


def test_disabling_one_pi_keeps_the_other_banks_loop_and_no_watchdog(one_bank_off):
    rec = one_bank_off
    assert all(r[1] == SAFE_NONE for r in rec), "the demand watchdog fired"
    before = [r for r in rec if OFF_AT - 3.0 <= r[0] < OFF_AT]
    after = [r for r in rec if r[0] >= END - 5.0]
    # the left loop held 680 mmH2O before and goes on holding it after PI_R is off (truth)
    for part in (before, after):
        bp = [r[5] for r in part]
        assert abs(sum(bp) / len(bp) - 680.0) < 25.0, bp[-5:]
        assert all(r[2] < 90.0 for r in part)  # the left valve is controlled, not safe (100)


def test_the_disabled_banks_valve_gets_its_manual_output(one_bank_off):
    """Disabled, PI_R's output tracks its valve's position: the valve holds its opening."""
    rec = one_bank_off
    at_off = [r for r in rec if r[0] <= OFF_AT][-1]
    after = [r for r in rec if r[0] > OFF_AT + 1.0]
    assert after and all(r[6] == "manual" for r in after)
    assert all(abs(r[3] - at_off[4]) < 2.0 for r in after), (at_off, after[-1])
    assert at_off[4] < 90.0  # it was closed in to hold its setpoint: not the safe 100 %


def test_a_disabled_controller_with_a_bad_input_sends_its_safe_output_beside_the_other():
    """PI_R off and its feedback gone: the shared frame still goes out (PI_L is on), with
    the right valve at PI_R's safe output, 100 % open."""
    from cell.control.backpressure import controllers
    from cell.estimators.backpressure import native_filters
    from cell.runtime.plausibility import Limit
    from cell.runtime.scheduler import Runtime

    db = CellDatabase()
    ctrls = controllers("kalman", enable=False)
    rt = Runtime(db, [*native_filters(), *ctrls])
    rt.set_params("PI_L", {"enable": True, "setpoint": 800.0}, family="controller")
    rt.plausibility.override([Limit("EXH_BP_R", 0.0, 1000.0, None)])  # 1500: implausible
    t = 0.0
    while t < 2.0:
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 700.0, "EXH_BP_R": 700.0}, t) if t < 1.0
                  else db.encode("EXH_BP", {"EXH_BP_L": 700.0, "EXH_BP_R": 1500.0}, t))
        rt.ingest(db.encode("VALVE_POS", {"VALVE_POS_L": 40.0, "VALVE_POS_R": 40.0}, t))
        rt.ingest(db.encode("ENGINE_STATUS", {"ENGINE_STATE": 1, "TRIP_REASON": 0,
                                              "EXH_BP_LIMIT": 1200, "ENGINE_LOAD": 100}, t))
        t = round(t + 0.01, 6)
    demand = [db.decode(f)[1] for f in rt.take_outbox()
              if f.arbitration_id == db.message("VALVE_DEMAND").frame_id]
    assert demand, "PI_L's demand never went out"
    assert demand[5]["VALVE_DEMAND_R"] == pytest.approx(40.0, abs=0.1)  # tracking: holds
    assert demand[-1]["VALVE_DEMAND_R"] == pytest.approx(100.0)  # its input bad: safe
    assert demand[-1]["VALVE_DEMAND_L"] < 99.0 and rt.blocks["PI_L"].mode == "auto"
    assert rt.blocks["PI_R"].mode.startswith("manual, safe: input EXH_BP_R")
