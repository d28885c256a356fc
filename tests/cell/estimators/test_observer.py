"""ObserverBlock: plumbing against filterpy, the runtime, PATCH-like tuning and divergence."""

import json
import logging
import math

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter

from cell.runtime.channels import INVALID, OK
from cell.core.errors import ParamError
from cell.estimators.core import GainSchedule, Model, bounds
from cell.estimators.observer import ObserverBlock
from cell.runtime.scheduler import Runtime

TAU = 0.8


def bp_model(**params):
    """Back-pressure behind a valve, with an unknown orifice gain (a bias state, seed 002/003):
    dBP/dt = (GAIN * 100 / VALVE - BP) / tau, dGAIN/dt = 0, measured BP."""

    def f(t, x, u, p):
        if p.get("blow"):
            return x * math.inf
        return np.array([(x[1] * 100.0 / u[0] - x[0]) / p["tau"], 0.0])

    def F(t, x, u, p):
        return np.array([[-1.0 / p["tau"], 100.0 / (u[0] * p["tau"])], [0.0, 0.0]])

    return Model(states=("BP", "GAIN"), inputs=("VALVE",), outputs=("BP", "FLOWISH"),
                 f=f, F=F, h=lambda t, x, u, p: np.array([x[0], x[0] * u[0] / 100.0]),
                 params={"tau": TAU, **params}, max_step=0.05,
                 units={"BP": "mmH2O", "BP_HAT": "unused", "FLOWISH": "a.u."})


def observer(**kw):
    model = kw.pop("model", None) or bp_model()
    settings = dict(inputs={"VALVE": "VALVE_POS_L"}, measurements={"BP": "EXH_BP_L"},
                    Q=[1.0, 1.0], R=[100.0], x0=[0.0, 100.0], P0=[1e4, 1e4], prefix="BPO")
    settings.update(kw)
    return ObserverBlock("bpo", model, **settings)


def test_outputs_follow_the_naming_convention_and_units():
    obs = observer()
    assert obs.family == "observer" and obs.kind == "observer"
    assert obs.inputs == ["VALVE_POS_L", "EXH_BP_L"]
    assert obs.outputs == ["BPO_BP", "BPO_GAIN", "BPO_BP_HAT", "BPO_FLOWISH_HAT", "BPO_CONF"]
    assert obs.units == {"BPO_BP": "mmH2O", "BPO_BP_HAT": "mmH2O", "BPO_FLOWISH_HAT": "a.u.",
                         "BPO_CONF": "1"}
    assert ObserverBlock("x", bp_model(), inputs={"VALVE": "V"}, measurements={"BP": "B"},
                         Q=1.0, R=1.0, units={"x_GAIN": "-"}).units["x_GAIN"] == "-"


def test_block_equals_an_independent_filterpy_ekf_on_irregular_ticks():
    """dt from successive t, inputs of the previous tick held over the prediction, h at the
    new tick's inputs, and _HAT the a-priori prediction."""
    model = bp_model()
    obs = observer(Q=[4.0, 0.5], R=[25.0])
    Q, R = np.diag([4.0, 0.5]), np.array([[25.0]])

    class Ref(ExtendedKalmanFilter):
        def predict_x(self, u=0):
            self.x = model.step(self.t, self.x.ravel(), u, self.dt)[0][:, None]

    ref = Ref(dim_x=2, dim_z=1)
    ref.x, ref.P, ref.Q, ref.R = np.array([[0.0], [100.0]]), np.diag([1e4, 1e4]), Q, R
    rng = np.random.default_rng(8)
    t, t_prev, u_prev = 0.0, None, None
    truth = np.array([500.0, 300.0])
    for k in range(400):
        valve = 40.0 + 20.0 * math.sin(0.05 * k)
        if t_prev is not None:
            truth = model.step(t_prev, truth, u_prev, t - t_prev)[0]
        z = truth[0] + rng.normal(0, 5.0)
        out = obs.step(t, {"VALVE_POS_L": valve, "EXH_BP_L": z})
        u = np.array([valve])
        if t_prev is not None:
            ref.t, ref.dt = t_prev, t - t_prev
            ref.F = model.step(t_prev, ref.x.ravel(), u_prev, t - t_prev, jacobian=True)[1]
            ref.predict(u_prev)
        hat = model.output(t, ref.x.ravel(), u)
        ref.update(np.array([[z]]), lambda x: np.array([[1.0, 0.0]]), lambda x: x[:1])
        np.testing.assert_allclose([out["BPO_BP"], out["BPO_GAIN"]], ref.x.ravel(), rtol=1e-9)
        np.testing.assert_allclose([out["BPO_BP_HAT"], out["BPO_FLOWISH_HAT"]], hat, rtol=1e-9)
        np.testing.assert_allclose(obs.core.P, ref.P, rtol=1e-9, atol=1e-9)
        t_prev, u_prev = t, u
        t = round(t + (0.1 if k % 7 else 0.3), 9)  # a skipped tick now and then
    assert out["BPO_GAIN"] == pytest.approx(300.0, rel=0.02)


def bp_frames(db, t, bp, valve=50.0):
    return [db.encode("EXH_BP", {"EXH_BP_L": bp, "EXH_BP_R": bp}, t),
            db.encode("VALVE_POS", {"VALVE_POS_L": valve, "VALVE_POS_R": valve}, t)]


def run(rt, db, t0, t1, bp=600.0, noise=None):
    rng = np.random.default_rng(9)
    for i in range(int(round(t0 * 100)), int(round(t1 * 100))):
        t = i / 100
        rt.ingest_many(bp_frames(db, t, bp + (rng.normal(0, noise) if noise else 0.0)))
    rt.advance(t1)


def test_observer_in_the_runtime_estimates_the_bias_state(db):
    obs = observer()
    rt = Runtime(db, [obs])
    run(rt, db, 0.0, 60.0, noise=10.0)
    chans = rt.channels
    for name in obs.outputs:
        assert chans[name].status == OK, (name, chans[name].reason)
    assert chans["BPO_GAIN"].value == pytest.approx(300.0, rel=0.02)  # 600 mmH2O at 50 % open
    assert chans["BPO_BP"].value == pytest.approx(600.0, rel=0.02)
    st = obs.state()
    json.dumps(st, allow_nan=False)
    assert st["updates"] == 601 and st["resets"] == 0 and st["mode"] == "full"
    assert st["x"] == [chans["BPO_BP"].value, chans["BPO_GAIN"].value]
    assert st["nis"] is not None and st["log_likelihood"] is not None
    assert len(st["P_diag"]) == 2 and np.shape(st["K"]) == (2, 1)


BAD = [
    ({"Q": [1.0, 2.0, 3.0]}, "Q", "2 diagonal elements"),
    ({"Q": [[1.0, 0.5], [0.5, 1.0]]}, "Q", "diagonal"),
    ({"Q": [1.0, math.nan]}, "Q", "finite"),
    ({"Q": [1.0, math.inf]}, "Q", "finite"),
    ({"Q": [1.0, 0.0]}, "Q", "positive definite"),
    ({"Q": [1.0, -2.0]}, "Q", "positive definite"),
    ({"Q": "big"}, "Q", "list"),
    ({"Q": [1.0, True]}, "Q", "list"),
    ({"R": [1.0, 1.0]}, "R", "1 diagonal"),
    ({"R": [-1.0]}, "R", "positive definite"),
    ({"x0": [1.0]}, "x0", "2 numbers"),
    ({"x0": [1.0, math.nan]}, "x0", "finite"),
    ({"P0": [0.0, 1.0]}, "P0", "positive definite"),
    ({"nis_window": -1}, "nis_window", ">= 0"),
    ({"nis_gate": 1.0}, "nis_gate", "<="),
    ({"G": 1.0}, "G", "not a parameter"),
    ({"R": [2.0], "Q": [1.0, -1.0]}, "Q", "positive definite"),  # all or nothing
]


@pytest.mark.parametrize("changes,field,words", BAD)
def test_bad_changes_name_the_field_and_change_nothing(db, changes, field, words):
    obs = observer()
    rt = Runtime(db, [obs])
    run(rt, db, 0.0, 2.0)
    before, state, Q, R = obs.params(), obs.state(), obs.core.Q.copy(), obs.core.R.copy()
    with pytest.raises(ParamError) as err:
        rt.set_params("bpo", changes, family="observer")
    assert err.value.field == field and words in err.value.message
    assert obs.params() == before and obs.state() == state
    np.testing.assert_array_equal(obs.core.Q, Q)
    np.testing.assert_array_equal(obs.core.R, R)


def test_good_changes_apply_and_params_round_trip_through_json(db):
    obs = observer()
    rt = Runtime(db, [obs])
    run(rt, db, 0.0, 5.0)
    x = obs.core.x.copy()
    out = rt.set_params("bpo", {"Q": [[2.0, 0.0], [0.0, 3.0]], "R": 50.0, "x0": [1.0, 2.0],
                                "nis_window": 20}, family="observer")
    assert out == {"Q": [2.0, 3.0], "R": [50.0], "x0": [1.0, 2.0], "P0": [1e4, 1e4],
                   "nis_gate": 0.9999, "nis_window": 20}
    np.testing.assert_array_equal(obs.core.Q, np.diag([2.0, 3.0]))
    np.testing.assert_array_equal(obs.core.R, [[50.0]])
    np.testing.assert_array_equal(obs.core.x, x)  # the estimate is kept
    assert obs.core.nis_window == 20
    text = json.dumps(obs.params(), allow_nan=False)
    assert obs.set_params(json.loads(text)) == obs.params()  # what it gives, it takes
    obs.reset()  # a reset takes the new x0
    np.testing.assert_array_equal(obs.core.x, [1.0, 2.0])
    assert obs.state()["resets"] == 1 and obs.state()["last_reset_reason"] == "reset requested"


def test_divergence_marks_outputs_invalid_resets_and_shows_in_state(db, caplog):
    model = bp_model()
    obs = observer(model=model)
    rt = Runtime(db, [obs])
    run(rt, db, 0.0, 3.0)
    model.params["blow"] = True
    with caplog.at_level(logging.WARNING, logger="cell.estimators.core"):
        run(rt, db, 3.0, 3.1)
    chans = rt.channels
    for name in obs.outputs:
        assert chans[name].status == INVALID
        assert "non-finite state after predict" in chans[name].reason
    st = obs.state()
    assert st["resets"] >= 1 and "non-finite state" in st["last_reset_reason"]
    assert st["x"] == [0.0, 100.0]  # back at x0
    json.dumps(st, allow_nan=False)
    assert "bpo diverged" in caplog.text and "non-finite state" in caplog.text
    model.params["blow"] = False  # the observer recovers by itself
    run(rt, db, 3.1, 20.0, noise=5.0)
    assert all(rt.channels[n].status == OK for n in obs.outputs)
    assert rt.channels["BPO_GAIN"].value == pytest.approx(300.0, rel=0.05)
    assert rt.block_errors["bpo"] >= 1


def test_nis_window_resets_when_the_model_is_wrong(caplog):
    obs = observer(Q=[1e-6, 1e-8], R=[1.0], x0=[600.0, 300.0], P0=[1.0, 1.0], nis_window=3)
    for k in range(3):
        obs.step(0.1 * k, {"VALVE_POS_L": 50.0, "EXH_BP_L": 600.0})
    with pytest.raises(ArithmeticError, match="NIS above"):
        for k in range(3, 6):
            obs.step(0.1 * k, {"VALVE_POS_L": 50.0, "EXH_BP_L": 900.0})  # a step the model denies
    assert obs.state()["resets"] == 1 and "NIS above" in obs.state()["last_reset_reason"]


def test_non_finite_input_is_refused_without_a_reset():
    obs = observer()
    with pytest.raises(ArithmeticError, match="EXH_BP_L is nan"):
        obs.step(0.0, {"VALVE_POS_L": 50.0, "EXH_BP_L": math.nan})
    assert obs.state()["resets"] == 0 and obs.state()["updates"] == 0


def test_scheduled_gain_observer_reads_its_scheduling_channel():
    sched = GainSchedule([1000.0, 3000.0], [[[0.1], [0.0]], [[0.5], [0.0]]])
    obs = observer(gain=sched, schedule=["ENGINE_SPEED"], P0=[10.0, 10.0],
                   constraint=bounds([0.0, 0.0], [1000.0, 1000.0]))
    assert "ENGINE_SPEED" in obs.inputs and obs.state()["mode"] == "scheduled"
    out = obs.step(0.0, {"VALVE_POS_L": 50.0, "EXH_BP_L": 100.0, "ENGINE_SPEED": 2000.0})
    assert out["BPO_BP"] == pytest.approx(0.3 * 100.0)  # K = 0.3 halfway along the grid
    np.testing.assert_array_equal(obs.core.P, np.diag([10.0, 10.0]))  # not propagated
    obs.set_params({"P0": [20.0, 20.0]})
    np.testing.assert_array_equal(obs.core.P, np.diag([20.0, 20.0]))


def test_bad_wiring_is_refused_at_construction():
    with pytest.raises(ParamError) as err:
        observer(inputs={"THROTTLE": "X"})
    assert err.value.field == "inputs"
    with pytest.raises(ParamError) as err:
        observer(measurements={"LAMBDA": "X"})
    assert err.value.field == "measurements"
    with pytest.raises(ParamError) as err:
        observer(schedule=["ENGINE_SPEED"])
    assert err.value.field == "schedule"
    with pytest.raises(ParamError) as err:
        observer(gain=np.zeros((3, 1)))
    assert err.value.field == "gain"
    with pytest.raises(ParamError) as err:
        observer(Q=[1.0, -1.0])
    assert err.value.field == "Q"
