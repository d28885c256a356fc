"""The cyclic runtime: bus-time ticks, sampling, staleness, decode errors and bus outputs."""

import can
import pytest

from cell.runtime.blocks import Block
from cell.core.errors import ConfigError
from cell.estimators.backpressure import MovingAverage, ScalarKalman, native_filters
from cell.runtime.scheduler import Rates, Runtime


def bp(db, t, left, right=None):
    return db.encode("EXH_BP", {"EXH_BP_L": left, "EXH_BP_R": left if right is None else right}, t)


class Recorder(Block):
    """Records what it is given at each tick (an independent observer of the scheduler)."""

    kind = "recorder"

    def __init__(self, source, rate="MED"):
        super().__init__(f"rec_{rate}", [source], [f"rec_{rate}"], rate)
        self.source = source
        self.seen = []

    def _step(self, t, inputs):
        self.seen.append((round(t, 6), inputs[self.source]))
        return {self.name: inputs[self.source]}


def test_input_at_tick_is_latest_frame_at_or_before_tick(db):
    rec = Recorder("EXH_BP_L")
    rt = Runtime(db, [rec])
    # frames at 0.00, 0.05, 0.10 (exactly on the tick), 0.13, 0.20, 0.21
    for t, v in [(0.0, 1.0), (0.05, 2.0), (0.10, 3.0), (0.13, 4.0), (0.20, 5.0), (0.21, 6.0)]:
        rt.ingest(bp(db, t, v))
    rt.advance(0.25)
    assert rec.seen == [(0.0, 1.0), (0.1, 3.0), (0.2, 5.0)]


def test_rates_tick_on_their_own_grids(db):
    recs = [Recorder("EXH_BP_L", r) for r in ("FAS", "MED", "SLO")]
    rt = Runtime(db, recs)
    for i in range(0, 201):
        rt.ingest(bp(db, i * 0.01, float(i)))
    rt.advance(2.0)
    fas, med, slo = ([t for t, _ in r.seen] for r in recs)
    assert fas == [round(i * 0.02, 6) for i in range(101)]
    assert med == [round(i * 0.1, 6) for i in range(21)]
    assert slo == [0.0, 1.0, 2.0]
    assert Runtime(db, rates=Rates.parse("FAS=100,MED=20")).rates == Rates(FAS=100, MED=20, SLO=1)


@pytest.mark.parametrize("spec", ["0", "MED=abc", "FOO=3", "nan", "MED=1e9", "-10"])
def test_bad_cycle_option_is_named(spec):
    with pytest.raises(ConfigError, match="--cycle"):
        Rates.parse(spec)


def test_stale_within_three_ticks_and_filters_hold_state(db):
    rt = Runtime(db, native_filters())
    t = 0.0
    while t < 10.0:
        rt.ingest(bp(db, t, 680.0 + (t * 7 % 3)))
        t = round(t + 0.01, 6)
    last = t - 0.01
    kal = rt.blocks["EXH_BP_R_Kalman"]
    statuses, states = [], []
    for k in range(1, 6):
        rt.advance(last + 0.1 * k)
        statuses.append(rt.channels["EXH_BP_R_Kalman"].status)
        states.append((kal.x, kal.n))
    assert "stale" in statuses[:3], statuses
    assert statuses[-1] == "stale"
    assert rt.channels["EXH_BP_R"].status_at(rt.now)[0] == "stale"
    first_stale = statuses.index("stale")
    held = states[first_stale - 1] if first_stale else states[0]
    assert all(s == held for s in states[first_stale:]), "filter integrated a stale input"
    x = kal.x
    # frames return: the filter resumes from the held state
    rt.ingest(bp(db, last + 1.0, 700.0))
    rt.advance(last + 1.05)
    assert rt.channels["EXH_BP_R_Kalman"].status == "ok"
    assert kal.x == pytest.approx(x + kal.K * (700.0 - x), abs=1e-9)


def test_undecodable_frames_are_counted_and_ignored(db):
    rt = Runtime(db, native_filters())
    rt.ingest(bp(db, 0.0, 500.0))
    rt.ingest(can.Message(timestamp=0.01, arbitration_id=0x7AB, data=b"\x00" * 8, is_extended_id=False))
    rt.ingest(can.Message(timestamp=0.02, arbitration_id=0x101, data=b"\x01\x02\x03", is_extended_id=False))
    rt.ingest(can.Message(timestamp=0.03, arbitration_id=0x101, data=b"\x00" * 12,
                          is_extended_id=False, is_fd=True))
    h = rt.health()
    assert h["decode_errors"] == {"unknown_id": 1, "bad_length": 2, "decode_error": 0,
                                  "remote_frame": 0, "error_frame": 0}
    assert h["unknown_ids"] == {"0x7AB": 1}
    assert h["frames"] == 4
    assert rt.channels["EXH_BP_L"].value == 500.0


def test_outputs_go_on_the_bus_as_dbc_frames(db):
    rt = Runtime(db, native_filters())
    for i in range(50):
        rt.ingest(bp(db, i * 0.01, 600.0 + i, 700.0 - i))
    rt.advance(0.5)
    frames = rt.take_outbox()
    ids = {f.arbitration_id for f in frames}
    assert ids == {db.message("BP_FILT_L").frame_id, db.message("BP_FILT_R").frame_id}
    last_r = [f for f in frames if f.arbitration_id == db.message("BP_FILT_R").frame_id][-1]
    _, values = db.decode(last_r)
    assert last_r.timestamp == pytest.approx(0.5)
    assert values["EXH_BP_R_Kalman"] == pytest.approx(rt.channels["EXH_BP_R_Kalman"].value, abs=0.005)
    assert values["EXH_BP_R_MAF"] == pytest.approx(rt.channels["EXH_BP_R_MAF"].value, abs=0.005)


def test_one_producer_per_channel(db):
    rt = Runtime(db, [ScalarKalman("EXH_BP_R_Kalman", "EXH_BP_R")])
    other = MovingAverage("EXH_BP_R_Kalman_2", "EXH_BP_R")
    other.outputs = ["EXH_BP_R_Kalman"]
    with pytest.raises(ConfigError, match="EXH_BP_R_Kalman_2.*EXH_BP_R_Kalman already"):
        rt.add_block(other)
    with pytest.raises(ConfigError, match="bus input"):
        rt.add_block(MovingAverage("EXH_BP_L", "EXH_BP_R"))


def test_a_failing_block_marks_only_its_outputs_invalid(db):
    class Divider(Block):
        kind = "divider"

        def _step(self, t, inputs):
            return {"ratio": 1.0 / (inputs["EXH_BP_L"] - 500.0)}

    rt = Runtime(db, [Divider("div", ["EXH_BP_L"], ["ratio"]), *native_filters()])
    rt.ingest(bp(db, 0.0, 500.0))
    rt.advance(0.0)
    assert rt.channels["ratio"].status == "invalid"
    assert "ZeroDivisionError" in rt.channels["ratio"].reason
    assert rt.channels["EXH_BP_L_Kalman"].status == "ok"
    assert rt.health()["block_errors"] == {"div": 1}
    rt.ingest(bp(db, 0.05, 501.0))
    rt.advance(0.1)
    assert rt.channels["ratio"].status == "ok" and rt.channels["ratio"].value == pytest.approx(1.0)
