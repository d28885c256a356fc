"""One contract test over every registered observer (issue 18, point 1).

The observers are found in ``registry.BLOCK_SETS`` after ``cell.app.load()`` by the
contract's marker (:func:`~cell.estimators.contract.follows_contract`), so an observer joins
this test when it moves onto the contract. Each observer is first run on the simulator's
frames of its own engine (a short recording per engine, shared by the module), so that its
estimate is a real one; then each case checks one clause of the contract: an input out of
its declared range or NaN is refused with the reason and changes nothing, a gap turns the
outputs stale and the observer resumes with a restart, a divergence resets it with the
reason shown in ``state()``, and a design survives a round trip through JSON.
"""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from cell import app
from cell.bus.dbc import load
from cell.core import registry
from cell.core.settings import Settings
from cell.estimators.contract import (
    DesignError,
    Estimate,
    InputRefused,
    confidence_channel,
    follows_contract,
    read_design,
    write_design,
)
from cell.estimators.core import Diverged
from cell.runtime.scheduler import Runtime
from cell.sim import build as build_sim
from cell.sim.lockstep import Lockstep

#: seconds of each engine's own frames an observer runs on before a case
RUN = 2.0


def _registered() -> list[tuple[str, str, str]]:
    """(block set, engine, observer name) of every registered observer on the contract."""
    app.load()
    found = []
    for bs in registry.BLOCK_SETS.values():
        engines = [e for e in registry.ENGINES if bs.applies_to(e)]
        if not engines:
            continue
        for block in bs.build(Settings.build({}, environ={})):
            if follows_contract(block):
                found.append((bs.name, engines[0], block.name))
    return found


OBSERVERS = _registered()


def test_every_observer_of_the_issue_is_on_the_contract():
    names = {name for _, _, name in OBSERVERS}
    assert {"airpath-default", "airpath-augmented", "airpath", "rod_inversion"} <= names


@pytest.fixture(scope="module")
def db():
    return load([*registry.DBC_FILES])


@pytest.fixture(scope="module")
def frames(db):
    """The frames of the first RUN seconds of each engine's default duty cycle."""
    cache: dict[str, list] = {}

    def get(engine: str) -> list:
        if engine not in cache:
            sim = build_sim(Settings.build({"engine": engine}, environ={}), db)
            cache[engine] = list(Lockstep(sim).frames(round(RUN / sim.dt)))
        return cache[engine]

    return get


def _build(bs_name: str, name: str):
    (block,) = [b for b in registry.BLOCK_SETS[bs_name].build(Settings.build({}, environ={}))
                if b.name == name]
    return block


def _running(db, frames, bs_name, engine, name):
    """The observer after RUN s of its engine's frames, its runtime, and the inputs and time
    of its next tick."""
    block = _build(bs_name, name)
    rt = Runtime(db, [block])
    got = frames(engine)
    rt.ingest_many(got)
    t_end = got[-1].timestamp
    rt.advance(t_end)
    period = block._rec.period or rt.rates.period(block.rate)
    inputs = {ch: rt.channels[ch].value for ch in block.inputs}
    assert all(v is not None for v in inputs.values()), inputs
    return block, rt, inputs, block._rec.t_step + period, period


def _snapshot(block):
    est = block.estimate()
    return None if est is None else (est.x.copy(), None if est.P is None else est.P.copy())


def _same(a, b):
    if a is None or b is None:
        return a is b
    return np.array_equal(a[0], b[0]) and (a[1] is b[1] is None or np.array_equal(a[1], b[1]))


CASES = [pytest.param(*o, id=o[2]) for o in OBSERVERS]


@pytest.mark.parametrize("bs_name,engine,name", CASES)
def test_the_observer_runs_and_publishes_its_confidence(db, frames, bs_name, engine, name):
    block, rt, inputs, t, period = _running(db, frames, bs_name, engine, name)
    conf = confidence_channel(name)
    assert conf in block.outputs
    ch = rt.channels[conf]
    assert ch.status == "ok" and 0.0 <= ch.value <= 1.0
    st = block.state()
    json.dumps(st, allow_nan=False)
    c = st["contract"]
    assert c["status"] == "ok" and c["reason"] is None
    assert set(c) >= {"x", "P", "innovations", "nis", "resets", "last_reset_reason", "gaps"}
    if c["x"] is not None:
        est = block.estimate()
        assert c["x"] == [v if math.isfinite(v) else None for v in est.x.tolist()]


@pytest.mark.parametrize("bs_name,engine,name", CASES)
@pytest.mark.parametrize("bad", ["out-of-range", "nan"])
def test_bad_input_is_refused_with_the_reason_and_changes_nothing(db, frames, bs_name, engine,
                                                                   name, bad):
    block, rt, inputs, t, period = _running(db, frames, bs_name, engine, name)
    before, refused = _snapshot(block), dict(block.state()["contract"]["refused"])
    if block.ranges:
        ch, (lo, hi) = next(iter(block.ranges.items()))
        value = hi + abs(hi) + 1.0 if bad == "out-of-range" else math.nan
        words = f"{ch} = {value:g} outside its plausible range" if bad == "out-of-range" else f"{ch} is nan"
        with pytest.raises(InputRefused, match=words):
            block.step(t, inputs | {ch: value})
    elif block.streams and block.sample_ranges:
        ch = block.streams[0]
        lo, hi = block.sample_ranges[ch]
        value = hi + abs(hi) + 1.0 if bad == "out-of-range" else math.nan
        block.samples(ch, 0, np.full(6, value), t)
        words = f"samples of {ch} " + ("implausible" if bad == "out-of-range" else "not finite")
        with pytest.raises(InputRefused, match=words):
            block.step(t, inputs)
    else:
        pytest.fail(f"{name} declares no plausible range for any input or stream")
    assert _same(_snapshot(block), before)  # the estimate is kept
    c = block.state()["contract"]
    assert c["status"] == "invalid" and words.split(" ")[0] in c["reason"]
    assert sum(c["refused"].values()) == sum(refused.values()) + 1


@pytest.mark.parametrize("bs_name,engine,name", CASES)
def test_a_gap_turns_the_outputs_stale_and_the_observer_resumes_with_a_restart(
        db, frames, bs_name, engine, name):
    block, rt, inputs, t, period = _running(db, frames, bs_name, engine, name)
    gaps = block.state()["contract"]["gaps"]
    ch = next(iter(block.ranges), None)
    for k in range(block.gap_ticks + 1):  # a stream observer may have had samples since its tick
        bad = inputs | ({ch: math.nan} if ch else {})  # a stream observer: ticks without samples
        try:
            block.step(t + k * period, bad)
        except InputRefused as exc:
            last = str(exc)
        else:
            last = None
    assert last is not None and last.startswith("stale: no valid input for")
    assert block.state()["contract"]["status"] == "stale"
    # good input again: the observer restarts and publishes
    t_back = t + (block.gap_ticks + 2) * period
    if block.streams:  # feed the stream again, from the engine's frames
        got = frames(engine)
        shift = t_back - got[0].timestamp
        for m in got[: len(got) // 4]:
            m = copy.copy(m)
            m.timestamp += shift
            rt.ingest(m)
        rt.advance(got[len(got) // 4].timestamp + shift)
    else:
        out = block.step(t_back, inputs)
        assert set(out) <= set(block.outputs) and confidence_channel(name) in out
    c = block.state()["contract"]
    # a stream observer with an input channel too (afr_inversion: ENGINE_SPEED) can be ticked
    # by the runtime once on a valid speed before its samples come back, and resume twice
    assert c["status"] == "ok" and (c["gaps"] == gaps + 1 or (block.streams and c["gaps"] > gaps))
    assert c["last_reset_reason"].startswith("resumed after a gap")


@pytest.mark.parametrize("bs_name,engine,name", CASES)
@pytest.mark.parametrize("how", ["model-error", "non-finite", "beyond-bounds"])
def test_divergence_resets_with_the_reason_in_state(db, frames, bs_name, engine, name, how,
                                                     monkeypatch):
    block, rt, inputs, t, period = _running(db, frames, bs_name, engine, name)
    resets = block.state()["contract"]["resets"]
    est = block.estimate()
    if how == "beyond-bounds" and block.state_bounds is None:
        pytest.skip(f"{name} declares no state bounds (its state is a bank of Fourier coefficients)")
    if block.streams:  # a stream observer steps on its samples: feed it one frame first
        rt.ingest_many(frames(engine)[-200:])
    if how == "model-error":
        def broken(t, inputs):
            raise TypeError("'<' not supported between instances of 'complex' and 'float'")
        monkeypatch.setattr(block, "_observe", broken)
        words = "TypeError in the model"
    else:
        x = np.array(est.x if est is not None else [0.0], dtype=float)
        if how == "non-finite":
            x = x * math.nan
            words = "non-finite state"
        else:
            x = np.where(np.isfinite(block.state_bounds[: len(x), 1]),
                         block.state_bounds[: len(x), 1] * 10 + 1e10, 1e10)
            words = "beyond its bounds"
        monkeypatch.setattr(block, "estimate", lambda: Estimate(x, None if est is None else est.P))
    with pytest.raises(Diverged, match=words):
        block.step(t, inputs)
    monkeypatch.undo()
    c = block.state()["contract"]
    assert c["resets"] == resets + 1 and words in c["last_reset_reason"]
    assert c["status"] == "diverged" and words in c["reason"]
    json.dumps(block.state(), allow_nan=False)


@pytest.mark.parametrize("bs_name,engine,name", CASES)
def test_a_design_round_trips_and_a_bad_one_keeps_the_previous(db, frames, bs_name, engine, name,
                                                                tmp_path):
    block, rt, inputs, t, period = _running(db, frames, bs_name, engine, name)
    design = block.design()
    assert design["observer"] == name
    path = write_design(design, tmp_path / f"{name}.json")
    loaded = read_design(path)
    assert loaded == json.loads(json.dumps(design))
    # a fresh observer of the same name takes the design and gives the same one back ...
    fresh = _build(bs_name, name)
    fresh.load_design(loaded, source=str(path))
    assert json.loads(json.dumps(fresh.design())) == loaded
    # ... and, fed the same input, both give the same outputs
    a, b = _build(bs_name, name), _build(bs_name, name)
    a.load_design(loaded)
    b.load_design(json.loads(json.dumps(loaded)))
    if not block.streams:
        outs = [x.step(t + k * period, inputs) for x in (a, b) for k in range(3)]
        assert outs[:3] == outs[3:]
    # a design for another observer, or with a bad field, is refused and nothing changes
    with pytest.raises(DesignError, match="names observer 'someone-else'"):
        fresh.load_design(loaded | {"observer": "someone-else"})
    if fresh.PARAMS:
        key = next(iter(fresh.PARAMS))
        with pytest.raises(DesignError, match=f"params.{key}"):
            fresh.load_design(loaded | {"params": {key: "not a number"}})
    with pytest.raises(DesignError, match="observer"):
        fresh.load_design({k: v for k, v in loaded.items() if k != "observer"})
    assert json.loads(json.dumps(fresh.design())) == loaded


# -- the designs that hold more than parameters ----------------------------------------------
def test_the_augmented_observer_takes_a_new_aq_live_and_refuses_one_the_pbh_test_refuses():
    from cell.estimators.diesel_airpath import SHIPPED_DESIGN, augmented_observer, load_design

    Aq = load_design(SHIPPED_DESIGN)
    obs = augmented_observer(Aq)
    u = {"FUEL_RATE": 200.0, "ENGINE_SPEED": 1500.0, "VGT_POS": 50.0, "EGR_POS": 20.0,
         "EXH_BP_L": 600.0, "EXH_BP_R": 600.0, "DSL_P_IM": 180.0, "N_T": 40000.0}
    ref = augmented_observer(Aq)
    other = np.array(Aq)
    other[:, 0] = [0.8, 0.6, 0.0]  # still seen by P_IM: passes Theorem 2
    obs.load_design(obs.design() | {"Aq": other.tolist()})
    assert obs.design()["Aq"] == other.tolist()
    assert all(math.isfinite(v) for v in obs.step(0.0, u).values())
    z, uu = np.r_[180.0, 200.0, 40.0, np.ones(Aq.shape[1])], np.array(list(u.values())[:6])
    f_new = obs.model.f(0.0, z, uu, obs.model.params)
    f_ref = ref.model.f(0.0, z, uu, ref.model.params)
    assert not np.allclose(f_new, f_ref)  # the model follows the new A_q (eq. 3: f(x - A_q q))
    bad = np.array(other)
    bad[:, 0] = [0.0, 1.0, 0.0]  # only P_EM, which no run-time sensor sees
    with pytest.raises(DesignError, match="column 1"):
        obs.load_design(obs.design() | {"Aq": bad.tolist()})
    with pytest.raises(DesignError, match="dim q"):
        obs.load_design(obs.design() | {"Aq": np.c_[other, other].tolist()})
    assert obs.design()["Aq"] == other.tolist()  # the previous design stays


def test_a_gain_table_written_by_design_airpath_is_a_design_of_the_airpath_observer(tmp_path):
    from cell.estimators.si_airpath import AirPathObserver, GainTable

    table = GainTable.load()
    path = table.save(tmp_path / "gains.json")
    data = read_design(path)
    assert data["observer"] == "airpath" and data["table"]["points"]
    obs = AirPathObserver()
    obs.load_design(data, source=str(path))
    assert len(obs.table.points) == len(table.points)
    assert GainTable.load(path).to_json() == table.to_json()
    broken = json.loads(json.dumps(data))
    broken["table"]["points"] = [{"speed": 1.0}]
    before = obs.table
    with pytest.raises(DesignError, match="malformed gain table"):
        obs.load_design(broken, source="broken.json")
    with pytest.raises(DesignError, match="names observer 'twc'"):
        GainTable.from_json(data | {"observer": "twc"}, "x.json")
    assert obs.table is before
