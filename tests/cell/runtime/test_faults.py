"""Fault isolation in the runtime: a block that raises (any type), returns a complex number or
a NaN, or fails on its crank-angle samples faults that block alone; the loop goes on, the
other blocks stay ``ok``, the fault is counted with its reason, and the block is reset and
retried with backoff in bus time (1, 2, 4 ... 30 s)."""

from __future__ import annotations

import math
import struct

import can
import numpy as np
import pytest
from tests.helpers.client import local_client

from cell.app.assemble import build_runtime
from cell.app.cell import Cell
from cell.core.settings import Settings
from cell.estimators.backpressure import native_filters
from cell.runtime import faults
from cell.runtime.blocks import Block
from cell.runtime.samples import find_sample_streams
from cell.runtime.scheduler import Runtime
from cell.sim import simulate
from service.main import create_app
from tests.helpers.frames import feed

AIRPATH = ("airpath-default", "airpath-augmented")


@pytest.fixture(scope="module")
def diesel_frames(db):
    """7 s of the large diesel at rated, every frame, in time order."""
    return list(simulate(db, "rated", duration=7.0))


def _diesel_runtime():
    rt, _ = build_runtime(Settings.build({"engine": "large-diesel"}, environ={}))
    return rt


def _zero_airpath_sens(db):
    sens = db.message("AIRPATH_SENS")
    zero = bytes(sens.length)  # every signal 0: inside its DBC range ("sensor unplugged")

    def corrupt(m):
        if m.arbitration_id != sens.frame_id:
            return m
        return can.Message(timestamp=m.timestamp, arbitration_id=m.arbitration_id, data=zero,
                           is_extended_id=False)
    return corrupt


def _exh_bp_r_raw_minimum(db):
    exh = db.message("EXH_BP")
    sig = exh.get_signal_by_name("EXH_BP_R")
    assert (sig.start, sig.length, sig.is_signed, sig.byte_order) == (32, 32, True, "little_endian")

    def corrupt(m):
        if m.arbitration_id != exh.frame_id:
            return m
        data = bytearray(m.data)
        data[4:8] = struct.pack("<i", -2 ** 31)  # raw minimum: -21 474 836.48 mmH2O
        return can.Message(timestamp=m.timestamp, arbitration_id=m.arbitration_id,
                           data=bytes(data), is_extended_id=False)
    return corrupt


def _downstream(rt, signals):
    """The channels computed, directly or through other blocks, from ``signals``."""
    reached = set(signals)
    while True:
        more = {o for b in rt.blocks.values() if reached.intersection(b.inputs) for o in b.outputs}
        if more <= reached:
            return reached
        reached |= more


@pytest.mark.parametrize("corruption, signals, faults_it", [
    (_zero_airpath_sens, ("DSL_P_IM", "N_T", "VGT_POS", "EGR_POS"), True),  # all in range
    (_exh_bp_r_raw_minimum, ("EXH_BP_R",), False),  # out of range: refused at the door
], ids=["AIRPATH_SENS all zero", "EXH_BP_R raw minimum"])
def test_half_a_second_of_bad_frames_faults_only_the_airpath_observer(db, diesel_frames, corruption,
                                                                       signals, faults_it):
    rt = _diesel_runtime()
    corrupt = corruption(rt.db)
    rt.ingest_many([m for m in diesel_frames if m.timestamp < 3.0])
    rt.advance(2.99)
    chans = rt.channels
    touched = _downstream(rt, signals)
    others = {out for name, b in rt.blocks.items() if name not in AIRPATH for out in b.outputs
              if chans[out].status == "ok" and out not in touched}
    # the left bank's filters and controller at least (with every script, for AIRPATH_SENS)
    assert {"EXH_BP_L_Kalman", "EXH_BP_L_MAF", "EXH_BP_L_Adaptive", "VALVE_DEMAND_L"} <= others
    assert len(others) > (50 if faults_it else 3)
    assert all(chans[o].status == "ok" for o in rt.blocks["airpath-default"].outputs)
    ticks = rt.ticks
    rt.ingest_many([corrupt(m) if m.timestamp < 3.5 else m
                    for m in diesel_frames if 3.0 <= m.timestamp < 3.5])
    rt.advance(3.5)  # on main: TypeError out of the air-path EKF, and the loop ends here
    assert rt.last_tick_time == pytest.approx(3.5) and rt.ticks - ticks >= 5
    chans = rt.channels
    for out in rt.blocks["airpath-default"].outputs:
        assert chans[out].status == "invalid" and chans[out].reason, (out, chans[out])
        if faults_it:  # on main: the TypeError that ended the loop; now the observer contract
            # refuses the unplugged sensor by name (a fault, had it reached the model, would do too)
            assert "DSL_P_IM" in chans[out].reason or "faulted" in chans[out].reason, chans[out].reason
    stayed = {o: chans[o].status for o in others}
    assert all(s == "ok" for s in stayed.values()), {o: s for o, s in stayed.items() if s != "ok"}
    if faults_it:
        f = rt.health()["block_faults"]["airpath-default"]
        assert f["last_reason"] and (f.get("refused", 0) + f.get("exception", 0)) >= 1
    # good frames again: the observer is retried after its backoff and publishes again
    rt.ingest_many([m for m in diesel_frames if 3.5 <= m.timestamp < 7.0])
    rt.advance(6.99)
    f = rt.health()["block_faults"].get("airpath-default", {"backing_off": False, "streak": 0})
    assert not f["backing_off"] and f["streak"] == 0
    assert all(rt.channels[o].status == "ok" for o in rt.blocks["airpath-default"].outputs)


class Flaky(Block):
    """Doubles EXH_BP_L; raises ``exc`` while ``failing``; remembers when it was stepped."""

    kind = family = "flaky"

    def __init__(self, exc: type[BaseException]):
        super().__init__("flaky", ["EXH_BP_L"], ["FLAKY_OUT"])
        self.exc, self.failing, self.tries, self.resets = exc, False, [], 0

    def _step(self, t, inputs):
        self.tries.append(round(t, 3))
        if self.failing:
            raise self.exc("cannot take this input")
        return {"FLAKY_OUT": 2.0 * inputs["EXH_BP_L"]}

    def reset(self):
        self.resets += 1


@pytest.mark.parametrize("exc", [TypeError, ValueError, RuntimeError, np.linalg.LinAlgError])
def test_a_raising_block_is_isolated_counted_backed_off_and_recovers(db, exc):
    flaky = Flaky(exc)
    rt = Runtime(db, [*native_filters(), flaky])
    cell = Cell(runtime=rt, bus="virtual:test")
    client = local_client(create_app(cell))
    feed(rt, db, 0.0, 1.0)
    assert rt.channels["FLAKY_OUT"].status == "ok"
    flaky.failing, flaky.tries = True, []
    feed(rt, db, 1.0, 5.05)  # MED ticks 1.0 .. 5.0
    # stepped at 1.0 (fault), again 1 s later (fault), then 2 s later (fault): backoff 1, 2, 4
    assert flaky.tries == [1.0, 2.0, 4.0]
    assert flaky.resets == 3
    out = rt.channels["FLAKY_OUT"]
    assert out.status == "invalid" and f"{exc.__name__}: cannot take this input" in out.reason
    assert "retry at bus time 8.000" in out.reason
    assert all(rt.channels[b.name].status == "ok" for b in native_filters())
    h = client.get("/health").json()
    f = h["block_faults"]["flaky"]
    assert (f["exception"], f["streak"], f["backoff_s"]) == (3, 3, 4.0)
    assert f["retry_at"] == 8.0 and f["backing_off"]
    assert f["last_reason"] == f"{exc.__name__}: cannot take this input" and f["resets"] == 3
    assert h["block_errors"]["flaky"] == 3
    assert h["status"] == "degraded" and any(r.startswith("block flaky faulted") for r in h["reasons"])
    metrics = client.get("/metrics").text
    assert 'testcell_block_faults_total{block="flaky",kind="exception"} 3.0' in metrics
    assert 'testcell_block_backoff_seconds{block="flaky"} 4.0' in metrics
    flaky.failing, flaky.tries = False, []
    feed(rt, db, 5.05, 8.25)
    assert flaky.tries == [8.0, 8.1, 8.2]  # retried when its backoff ended, then every tick
    assert rt.channels["FLAKY_OUT"].status == "ok"
    assert rt.channels["FLAKY_OUT"].value == pytest.approx(2 * 680.0)
    f = client.get("/health").json()["block_faults"]["flaky"]
    assert (f["streak"], f["backing_off"], f["exception"]) == (0, False, 3)


def test_the_backoff_doubles_from_one_second_up_to_thirty():
    assert [faults.backoff_after(n) for n in range(0, 9)] == [0, 1, 2, 4, 8, 16, 30, 30, 30]


class Returns(Block):
    """Returns whatever ``value`` is (a complex number, a NaN) for its output."""

    kind = family = "returns"

    def __init__(self, name, value, output=None):
        super().__init__(name, ["EXH_BP_L"], [f"{name.upper()}_OUT"])
        self.value, self.output = value, output or f"{name.upper()}_OUT"

    def _step(self, t, inputs):
        return {self.output: self.value}


def test_a_complex_or_undeclared_output_faults_the_block_and_a_nan_counts_as_a_fault(db):
    cplx = Returns("cplx", (-1.0) ** 0.5)  # what a power of a negative base gives
    other = Returns("other", 1.0, output="EXH_BP_R")  # writes a bus input it does not own
    nan = Returns("nan", math.nan)
    rt = Runtime(db, [*native_filters(), cplx, other, nan])
    feed(rt, db, 0.0, 0.35)
    chans = rt.channels
    assert chans["CPLX_OUT"].status == "invalid" and "TypeError" in chans["CPLX_OUT"].reason
    assert chans["OTHER_OUT"].status == "invalid" and "KeyError" in chans["OTHER_OUT"].reason
    assert chans["EXH_BP_R"].value == pytest.approx(680.0)  # untouched
    assert chans["NAN_OUT"].status == "invalid"
    fs = rt.health()["block_faults"]
    assert fs["cplx"]["exception"] == 1 and fs["cplx"]["backing_off"]
    assert fs["nan"]["nonfinite"] == 4 and not fs["nan"]["backing_off"]  # stepped every tick
    assert rt.health()["withheld"] == {"NAN_OUT": 4}
    assert all(chans[b.name].status == "ok" for b in native_filters())


def test_an_arithmetic_refusal_keeps_the_block_running_at_the_next_tick(db):
    class Refuses(Block):
        kind = family = "refuses"

        def __init__(self):
            super().__init__("refuses", ["EXH_BP_L"], ["REF_OUT"])
            self.tries = []

        def _step(self, t, inputs):
            self.tries.append(round(t, 3))
            raise ArithmeticError("input implausible; estimate kept")

    block = Refuses()
    rt = Runtime(db, [block])
    feed(rt, db, 0.0, 0.45)
    assert block.tries == [0.0, 0.1, 0.2, 0.3, 0.4]  # no backoff: the block's own protocol
    f = rt.health()["block_faults"]["refuses"]
    assert f["refused"] == 5 and f["exception"] == 0 and not f["backing_off"]
    assert rt.channels["REF_OUT"].reason == "ArithmeticError: input implausible; estimate kept"


class Samples(Block):
    """Takes N_CRANK samples; raises TypeError on a sample <= 0 when ``picky``."""

    kind = family = "samples"

    def __init__(self, name, picky):
        super().__init__(name, [], [f"{name.upper()}_N"], "MED")
        self.streams = ("N_CRANK",)
        self.picky, self.seen = picky, []

    def _samples(self, stream, index, values, t):
        if self.picky and values[0] <= 0:
            raise TypeError("complex sample")
        self.seen.append(index)

    def _step(self, t, inputs):
        return {self.outputs[0]: float(len(self.seen))}


def test_a_sample_consumer_that_raises_faults_alone_and_the_stream_goes_on(db):
    picky, easy = Samples("picky", True), Samples("easy", False)
    rt = Runtime(db, [picky, easy])
    la = find_sample_streams(db.messages)["N_CRANK"]
    frames = [db.encode(la.message, la.frame_values(i, np.full(4, 0.0 if i == 4 else 1500.0)),
                        0.001 * (k + 1)) for k, i in enumerate([0, 4, 8, 12])]
    rt.ingest_many(frames)
    assert easy.seen == [0, 4, 8, 12]
    assert picky.seen == [0]  # faulted at 4, backing off for 1 s of bus time: 8 and 12 wait
    f = rt.health()["block_faults"]["picky"]
    assert f["exception"] == 1 and f["last_reason"] == "TypeError: complex sample" and f["backing_off"]
    assert "easy" not in rt.health()["block_faults"]


def test_a_tick_listener_that_raises_is_counted_and_the_ticks_go_on(db):
    rt = Runtime(db, native_filters())
    seen = []

    def broken(t):
        raise RuntimeError("listener defect")

    rt.tick_listeners.extend([broken, seen.append])
    feed(rt, db, 0.0, 0.55)
    assert seen == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4, 0.5])
    assert rt.health()["listener_errors"] == {broken.__qualname__: 6}
