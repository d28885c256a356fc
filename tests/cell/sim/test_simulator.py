"""The simulator on the DBC (cell/sim/simulator.py): what it sends and where received frames go."""

from __future__ import annotations

import can
import pytest

from cell.bus.dbc import CellDatabase, default_dbc_path
from cell.core.errors import ConfigError
from cell.sim.lockstep import Lockstep
from cell.plant import Composition, Plant, large_diesel
from cell.sim.simulator import Simulator

EXTRA = """VERSION ""

BS_:

BU_: SIM RUNTIME

BO_ 1536 RIG_STATE: 4 SIM
 SG_ RIG_LEVEL : 0|16@1+ (0.01,0) [0|600] "l" RUNTIME
 SG_ RIG_LEVEL_TRUE : 16|16@1+ (0.01,0) [0|600] "l" Vector__XXX

BO_ 1537 RIG_CMD: 2 RUNTIME
 SG_ RIG_FILL : 0|16@1+ (0.01,0) [0|600] "l/s" SIM

BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_ "GenMsgCycleTime" BO_ 1536 50;
BA_ "GenMsgCycleTime" BO_ 1537 100;
"""


class Tank(Plant):
    """A tank filled at the commanded rate: level' = fill (the independent reference)."""

    inputs = ("RIG_FILL",)
    outputs = ("RIG_LEVEL", "RIG_LEVEL_TRUE")

    def __init__(self, period: float = 0.01) -> None:
        super().__init__("tank", period)
        self.level = 0.0

    def step(self, t, u):
        self.level += u.get("RIG_FILL", 0.0) * self.period

    def output(self):
        return {"RIG_LEVEL": self.level, "RIG_LEVEL_TRUE": self.level}


@pytest.fixture
def db(tmp_path):
    extra = tmp_path / "rig.dbc"
    extra.write_text(EXTRA)
    return CellDatabase([default_dbc_path(), extra])


def test_another_engines_frames_in_the_dbc_are_left_alone(db):
    """A SIM message that no plant of this engine produces is not sent (and raises nothing)."""
    sim = Simulator(large_diesel("rated"), db)
    names = {m.name for m, _, _ in sim.schedule}
    assert "RIG_STATE" not in names and {"EXH_BP", "TRUTH_BP", "ENGINE_1"} <= names
    assert sim.frames()  # every message is due at t = 0


def test_frames_follow_the_dbc_cycle_time_and_received_commands_reach_their_plant(db):
    tank = Tank()
    sim = Simulator(Composition("rig", [tank]), db)
    assert [m.name for m, _, _ in sim.schedule] == ["RIG_STATE"]  # the cell's frames are not ours
    cmd = db.encode("RIG_CMD", {"RIG_FILL": 2.0})
    times = []
    for k, frames in Lockstep(sim).steps(100, frames=True):
        if k == 10:
            assert sim.receive(cmd)
        times += [m.timestamp for m in frames]
    assert times == pytest.approx([0.05 * i for i in range(20)])  # 50 ms cycle
    # filled at 2 l/s from the step after the command: 90 steps of 10 ms
    assert tank.level == pytest.approx(2.0 * 0.9)
    # frames addressed to others, or unknown, are not routed
    assert not sim.receive(db.encode("VALVE_DEMAND", {"VALVE_DEMAND_L": 1, "VALVE_DEMAND_R": 1}))
    assert not sim.receive(can.Message(arbitration_id=0x7FF, data=b"\x00"))


def test_a_sim_message_only_partly_produced_is_refused_naming_the_missing_signal(db):
    class HalfTank(Tank):
        outputs = ("RIG_LEVEL",)

        def output(self):
            return {"RIG_LEVEL": self.level}

    with pytest.raises(ConfigError, match="RIG_STATE carries RIG_LEVEL_TRUE, which no plant"):
        Simulator(Composition("rig", [HalfTank()]), db)
