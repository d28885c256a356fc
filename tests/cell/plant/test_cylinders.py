"""The crank-resolved plant (seed 001): per-cylinder fuel and IMEP, the exhaust and UEGO,
the crankshaft and transmission rod, its 6 deg sample frames, and its options."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.signal import lsim

from cell.bus.dbc import CellDatabase, dbc_dir
from cell.core.errors import ConfigError
from cell.sim.lockstep import Lockstep
from cell.plant.composition import Composition
from cell.plant.base import Plant
from cell.plant.cylinders import CylinderParams, Cylinders, cylinder_lambdas, parse_imbalance
from cell.plant.si_turbo import si_turbo
from cell.bus.scenario import scenario_frames
from cell.core.settings import Settings
from cell.sim import build
from cell.sim.simulator import Simulator
from cell.runtime.samples import find_sample_streams

RPM = 1500.0
TORQUE = 120.0


class SteadyEngine(Plant):
    """A stand-in engine: speed, torque and λ held (and ENGINE_1's other signals)."""

    outputs = ("ENGINE_SPEED", "ENGINE_TORQUE", "LAMBDA_ENGINE_TRUE", "FUEL_RATE", "ENGINE_POWER")

    def __init__(self, rpm: float = RPM):
        super().__init__("engine", 0.01)
        self.rpm = rpm

    def step(self, t, u):
        pass

    def output(self):
        return {"ENGINE_SPEED": self.rpm, "ENGINE_TORQUE": TORQUE, "LAMBDA_ENGINE_TRUE": 1.0,
                "FUEL_RATE": 5.0, "ENGINE_POWER": TORQUE * self.rpm * math.pi / 30e3}


@pytest.fixture(scope="module")
def db():
    # the cell's own frames and the crank frames (si-turbo's engine frames need its plants)
    return CellDatabase([dbc_dir() / "testcell.dbc", dbc_dir() / "crank.dbc"])


def _run(db, offsets=(0.25, 0, 0, 0), seconds=2.0):
    comp = Composition("t", [SteadyEngine(), Cylinders(imbalance=offsets)])
    sim = Simulator(comp, db)
    frames = list(Lockstep(sim).frames(round(seconds / sim.dt)))
    layouts = {db.message(la.message).frame_id: la for la in find_sample_streams(db.messages).values()}
    streams: dict[str, list] = {}
    for f in frames:
        la = layouts.get(f.arbitration_id)
        if la is not None:
            i, v = la.unpack(db.decode(f)[1])
            streams.setdefault(la.name, []).append((f.timestamp, i, v))
    return comp, frames, streams


@pytest.fixture(scope="module")
def run(db):
    return _run(db)


def test_parse_imbalance():
    assert parse_imbalance("1:+0.25") == (0.25, 0.0, 0.0, 0.0)
    assert parse_imbalance(" 1:+0.25, 4:-0.25 ") == (0.25, 0.0, 0.0, -0.25)
    assert parse_imbalance(None) == (0.0,) * 4


@pytest.mark.parametrize("spec,needle", [
    ("1=0.2", "item '1=0.2' is not CYLINDER:OFFSET"),
    ("x:0.2", "cylinder 'x' is not a number"),
    ("5:0.2", "cylinder 5 is not one of 1..4"),
    ("2:lots", "offset 'lots' of cylinder 2 is not a number"),
    ("2:0.6", "offset of cylinder 2 must be in -0.5..+0.5"),
])
def test_parse_imbalance_names_the_bad_item(spec, needle):
    with pytest.raises(ConfigError, match=needle.replace("+", r"\+").replace(".", r"\.")):
        parse_imbalance(spec)


def test_the_lambda_control_keeps_the_mean_fuel():
    lam = cylinder_lambdas(1.02, (0.25, 0.0, -0.1, 0.05))
    # fuel per cylinder is air / lambda with equal air: its mean is the engine's
    assert np.mean(1.0 / lam) == pytest.approx(1.0 / 1.02)
    assert lam[0] < 1.02 < lam[2]


def test_per_cylinder_truth(run):
    comp, _, _ = run
    s = comp.signals
    afr = np.array([s[f"AFR_CYL_{i}_TRUE"] for i in range(1, 5)])
    imep = np.array([s[f"IMEP_CYL_{i}_TRUE"] for i in range(1, 5)])
    np.testing.assert_allclose(14.7 / afr, 1.0 / cylinder_lambdas(1.0, (0.25, 0, 0, 0)) / 1.0)
    # the mean IMEP is BMEP (4 pi T / Vd) plus friction; the rich cylinder makes the most
    bmep = 4 * math.pi * TORQUE / CylinderParams().displacement / 1e5
    assert imep.mean() == pytest.approx(bmep + CylinderParams().fmep)
    assert np.argmax(imep) == 0 and imep[1] == imep[2] == imep[3]
    assert [s[f"FUEL_OFFSET_CYL_{i}_TRUE"] for i in range(1, 5)] == [0.25, 0.0, 0.0, 0.0]


def _series(stream):
    return np.concatenate([v for _, _, v in stream])


def test_every_6_deg_sample_in_frames_of_four_under_1000_frames_per_second(run):
    _, frames, streams = run
    for name in ("AFR_UEGO", "N_CRANK", "AFR_MANIFOLD_TRUE", "N_CYL_TRUE"):
        idx = np.array([i for _, i, _ in streams[name]])
        assert np.all(np.diff(idx) % 120 == 4)  # consecutive, no gap, wrapping at 720 deg
        n = 4 * len(idx)
        assert n == pytest.approx(RPM / 60 * 360 / 6 * 2.0, abs=24)  # 1500 samples/s
    sensor = len(streams["AFR_UEGO"]) + len(streams["N_CRANK"])
    assert sensor / 2.0 < 1000.0
    ts = [f.timestamp for f in frames]
    assert ts == sorted(ts)


def _cycles(stream, skip=0.5):
    """Samples from the first cycle start after ``skip`` s, in whole cycles."""
    t = np.concatenate([np.full(4, ts) for ts, _, _ in stream])
    idx = np.concatenate([(i + np.arange(4)) % 120 for _, i, _ in stream])
    x = _series(stream)
    start = np.nonzero((t > skip) & (idx == 0))[0][0]
    n = (len(x) - start) // 120 * 120
    return x[start:start + n]


def test_the_manifold_mixes_the_cylinders_in_firing_order(run):
    comp, _, streams = run
    w = _cycles(streams["AFR_MANIFOLD_TRUE"]).reshape(-1, 120)
    afr = np.array([comp.signals[f"AFR_CYL_{i}_TRUE"] for i in range(1, 5)])
    # the cycle mean is the mean of the cylinders' AFR, within the mixing's smoothing
    assert w.mean() == pytest.approx(afr.mean(), rel=0.01)
    # cylinder 1's exhaust (the rich one) reaches the sensor once per cycle: one dip
    prof = w.mean(axis=0)
    assert prof.min() == pytest.approx(afr[0], abs=0.3) and prof.max() == pytest.approx(afr[1], abs=0.1)
    assert np.sum(prof < (afr[0] + afr[1]) / 2) == pytest.approx(30, abs=4)  # 180 deg of 720


def test_the_uego_is_two_first_order_lags_of_the_manifold_afr(run):
    _, _, streams = run
    w, y = _series(streams["AFR_MANIFOLD_TRUE"]), _series(streams["AFR_UEGO"])
    p = CylinderParams()
    dt = 6.0 / (6.0 * RPM)
    t = np.arange(len(w)) * dt
    num, den = [1.0], np.polymul([p.tau1, 1.0], [p.tau2, 1.0])
    _, ref, _ = lsim((num, den), w - w[0], t)  # from rest at the first value
    ref = ref + w[0]
    tail = slice(len(w) // 4, None)
    err = y[tail] - ref[tail]
    assert abs(err.mean()) < 0.02 and err.std() < 2.0 * p.afr_noise


def test_the_rod_filters_the_speed_next_to_the_cylinders(run):
    _, _, streams = run
    x2, x1 = _cycles(streams["N_CYL_TRUE"]), _cycles(streams["N_CRANK"])
    assert x2.mean() == pytest.approx(RPM, rel=0.005)
    p = CylinderParams()
    # the firing frequency is the 4th harmonic of the cycle: 2 per radian of crank angle
    k = 4 * (len(x2) // 120)
    X1, X2 = np.fft.rfft(x1)[k], np.fft.rfft(x2)[k]
    s = 2j
    H = (2 * p.xi * p.omega_bar * s + p.omega_bar**2) / (s**2 + 2 * p.xi * p.omega_bar * s
                                                        + p.omega_bar**2)
    assert abs(X1 / X2) == pytest.approx(abs(H), rel=0.05)
    assert np.angle(X1 / X2) == pytest.approx(np.angle(H), abs=0.1)


def test_a_scenario_frame_changes_the_offsets_mid_run(db):
    comp = Composition("t", [SteadyEngine(), Cylinders()])
    sim = Simulator(comp, db)
    assert comp.signals["FUEL_OFFSET_CYL_3_TRUE"] == 0.0
    for f in scenario_frames(db, {"fuel_offset_cyl_3": -0.2}):
        assert sim.receive(f)
    sim.step()
    offsets = [comp.signals[f"FUEL_OFFSET_CYL_{i}_TRUE"] for i in range(1, 5)]
    assert offsets == [0.0, 0.0, pytest.approx(-0.2), 0.0]
    assert comp.signals["AFR_CYL_3_TRUE"] > comp.signals["AFR_CYL_1_TRUE"]


def test_si_turbo_takes_imbalance_and_crank_options():
    from cell.bus.dbc import load

    db = load()
    s = Settings.build({"engine": "si-turbo", "duty": "steady", "imbalance": "2:-0.1"}, environ={})
    sim = build(s, db)
    assert sim.plant.plant("cylinders").default_offsets == (0.0, -0.1, 0.0, 0.0)
    assert {la.name for _, la, _ in sim.streams} == {"AFR_UEGO", "N_CRANK", "AFR_MANIFOLD_TRUE",
                                                     "N_CYL_TRUE"}
    off = build(Settings.build({"engine": "si-turbo", "crank": "off"}, environ={}), db)
    assert not off.streams and "cylinders" not in [p.name for p in off.plant.plants]
    with pytest.raises(ConfigError, match="--imbalance .*cylinder 7"):
        Settings.build({"engine": "si-turbo", "imbalance": "7:0.1"}, environ={})
    with pytest.raises(ConfigError, match="--crank must be on or off"):
        Settings.build({"engine": "si-turbo", "crank": "yes"}, environ={})
    assert si_turbo("steady", imbalance="1:+0.25").about["imbalance"] == "1:+0.25"


def test_a_stopped_crank_sends_no_samples(db):
    comp = Composition("t", [SteadyEngine(rpm=0.0), Cylinders()])
    sim = Simulator(comp, db)
    frames = list(Lockstep(sim).frames(20))
    ids = {db.message(m).frame_id for m in ("CRANK_AFR_UEGO", "CRANK_N")}
    assert not [f for f in frames if f.arbitration_id in ids]


def test_a_plant_stream_the_dbc_does_not_carry_is_refused(db):
    class Odd(Cylinders):
        streams = ("AFR_UEGO", "KNOCK")

    with pytest.raises(ConfigError, match="plant cylinders produces sample stream KNOCK, which no "
                                          "SIM message"):
        Simulator(Composition("t", [SteadyEngine(), Odd()]), db)


def test_samples_wait_in_the_plant_until_the_simulator_takes_them(db):
    """With a lockstep stride, frames are made only every few steps: no sample is lost."""
    from cell.runtime.scheduler import Runtime

    comp = Composition("t", [SteadyEngine(), Cylinders()])
    sim = Simulator(comp, db)
    rt = Runtime(db)
    seen = []
    Lockstep(sim, rt, stride=10, wire=lambda fs: seen.extend(fs) or fs).run(1.0)
    la = find_sample_streams(db.messages)["AFR_UEGO"]
    idx = [la.unpack(db.decode(f)[1])[0] for f in seen
           if f.arbitration_id == db.message(la.message).frame_id]
    # the last exchange is at 0.9 s: every sample up to it, consecutive
    assert 4 * len(idx) == pytest.approx(0.9 * 1500, abs=8)
    assert np.all(np.diff(idx) % 120 == 4)
