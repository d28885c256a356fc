"""A second sender of a simulator message: its frames arrive faster than the DBC's cycle, and
the runtime counts them as conflicts of that message, in ``/health`` (degraded, named)."""

import can
import pytest

from cell import sim as simmod
from cell.core.settings import Settings
from cell.runtime import senders, supervision
from cell.runtime.scheduler import Runtime
from cell.sim.lockstep import Lockstep

SECONDS = 4.0


def _forger(db, every_s=0.1, start_s=1.0, offset_s=0.05):
    """A wire that adds a forged ENGINE_STATUS (engine running) every ``every_s`` from
    ``start_s`` on, between the simulator's own (which it sends every 100 ms)."""
    state = {"next": None}
    sent = []

    def wire(frames: list[can.Message]) -> list[can.Message]:
        if not frames:
            return frames
        t = frames[0].timestamp
        if state["next"] is None:
            state["next"] = t + start_s + offset_s
        out = list(frames)
        while t >= state["next"]:
            values = {sig.name: 0 for sig in db.message("ENGINE_STATUS").signals}
            msg = db.encode("ENGINE_STATUS", {**values, "ENGINE_STATE": 1}, state["next"])
            out.append(msg)
            sent.append(msg)
            state["next"] += every_s
        return out

    return wire, sent


def _run(db, wire=None):
    s = Settings.build({"engine": "large-diesel", "duty": "rated", "duration": SECONDS},
                       environ={}).for_simulator()
    rt = Runtime(db)
    Lockstep(simmod.build(s, db), rt, wire=wire).run(SECONDS)
    return rt


@pytest.fixture(scope="module")
def honest(db):
    return _run(db)


@pytest.fixture(scope="module")
def forged(db):
    wire, sent = _forger(db)
    return _run(db, wire), sent


def test_the_simulator_alone_has_no_conflict(honest):
    h = honest.health()
    assert honest.senders.windows >= 3
    assert h["conflicts"] == {}
    assert not any("second sender" in r for r in supervision.assess(honest)["reasons"])
    assert honest.senders.pace == pytest.approx(1.0, rel=0.15)  # one frame per cycle


def test_a_forged_second_sender_of_engine_status_is_counted_and_named(forged):
    rt, sent = forged
    h = rt.health()
    assert set(h["conflicts"]) == {"ENGINE_STATUS"}, h["conflicts"]
    # the simulator's own frames are not counted, the forger's are (those in full windows)
    assert 0.6 * len(sent) <= h["conflicts"]["ENGINE_STATUS"] <= len(sent)
    health = supervision.assess(rt)
    assert health["status"] == "degraded"
    reason = next(r for r in health["reasons"] if "second sender" in r)
    assert "ENGINE_STATUS" in reason and "2.0 frames per cycle" in reason


def _synthetic(db, scale, forged, seconds=3.0):
    """Frames of four simulator messages at their DBC cycles, on a bus whose clock runs
    ``scale`` times faster (``--speed`` with frames stamped on receipt)."""
    rt = Runtime(db)
    cycles = {"EXH_BP": 0.01, "ENGINE_1": 0.02, "VALVE_POS": 0.02, "ENGINE_STATUS": 0.1}
    for name, cycle in cycles.items():
        assert db.message(name).cycle_time == round(cycle * 1000)
        assert "SIM" in db.message(name).senders
    frames = []
    for name, cycle in cycles.items():
        msg = db.message(name)
        zero = {s.name: max(0.0, s.minimum or 0.0) for s in msg.signals}
        k = 0
        while k * cycle < seconds:
            frames.append(db.encode(name, zero, k * cycle / scale))
            if forged and name == "ENGINE_STATUS":
                frames.append(db.encode(name, zero, (k + 0.5) * cycle / scale))
            k += 1
    frames.sort(key=lambda m: m.timestamp)
    rt.ingest_many(frames)
    rt.advance(seconds / scale)
    return rt


@pytest.mark.parametrize("scale", [1.0, 20.0])
def test_the_pace_follows_the_speed_and_only_the_doubled_message_conflicts(db, scale):
    seconds = 3.0 * scale  # three windows of bus time whatever the speed
    honest = _synthetic(db, scale, forged=False, seconds=seconds)
    assert honest.health()["conflicts"] == {}
    assert honest.senders.pace == pytest.approx(scale, rel=0.1)
    forged = _synthetic(db, scale, forged=True, seconds=seconds)
    conflicts = forged.health()["conflicts"]
    assert list(conflicts) == ["ENGINE_STATUS"]
    # one extra frame per cycle, over the windows closed so far (the first starts at the first tick)
    windows = forged.senders.windows
    assert conflicts["ENGINE_STATUS"] == pytest.approx(windows * senders.WINDOW_S * scale / 0.1,
                                                       rel=0.1)


def test_conflicts_are_no_longer_named_once_the_forger_stops(db):
    from cell.runtime.health import HealthCounters

    w = senders.SenderWatch(db.messages, HealthCounters())
    w.last["ENGINE_STATUS"] = (2.0, 10.0)
    w.conflicts["ENGINE_STATUS"] = 10
    assert w.active(10.5) == {"ENGINE_STATUS": 2.0}
    assert w.active(10.0 + (senders.HOLD_WINDOWS + 2) * senders.WINDOW_S) == {}
