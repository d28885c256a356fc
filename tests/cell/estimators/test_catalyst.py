"""The catalyst's dual EKF block (cell/estimators/catalyst.py): its Jacobians, its robustness and
its place in the runtime and the service."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from tests.helpers.client import local_client

from cell.app import cli
from cell.app.cell import Cell
from cell.bus.dbc import load
from cell.core.errors import ParamError
from cell.estimators.core import numerical_jacobian
from cell.estimators.catalyst import (
    MODEL_KINETICS,
    Operating,
    TWCObserver,
    model_A,
    model_C,
    model_f,
    model_g,
    predict,
)
from cell.plant.catalyst_model import TWCKinetics
from cell.runtime.scheduler import Runtime
from cell.core.settings import Settings
from cell.app.tuning import TuningStore
from service.main import create_app

RNG = np.random.default_rng(7)
POINTS = [
    (np.array([*RNG.uniform(0.05, 0.95, 3), RNG.uniform(0.3, 1.6)]),
     (RNG.uniform(0.003, 0.05), RNG.uniform(300.0, 750.0), lam))
    for lam in (0.93, 0.97, 1.0, 1.02, 1.2, 10.0)
]
WARM = {"EXH_MASS_FLOW": 0.01, "T_CAT": 450.0, "LAMBDA_PRE": 1.0, "LAMBDA_MID": 1.0}


@pytest.mark.parametrize("x,u", POINTS)
def test_state_jacobian_matches_finite_differences(x, u):
    A = model_A(x, u)
    An = numerical_jacobian(lambda v: model_f(v, u), x)
    np.testing.assert_allclose(A, An, rtol=1e-5, atol=1e-6 * np.abs(An).max())
    assert np.all(A[3] == 0.0)  # dOSC/dt = 0 (eq. 21)
    assert np.all(np.triu(A[:3, :3], 1) == 0.0)  # a cell sees only the gas from upstream


@pytest.mark.parametrize("x,u", POINTS)
def test_output_jacobian_matches_finite_differences(x, u):
    C = model_C(x, u)
    Cn = numerical_jacobian(lambda v: [model_g(v, u)], x)
    np.testing.assert_allclose(C, Cn, rtol=1e-5, atol=1e-7 * max(np.abs(Cn).max(), 1e-3))


@pytest.mark.parametrize("x,u", POINTS[:4])
def test_transition_jacobian_matches_finite_differences(x, u):
    op = Operating(u, MODEL_KINETICS)
    x_new, Phi = predict(list(x), op, 0.1, 0.01, (0.05, 4.0))
    Pn = numerical_jacobian(lambda v: predict(list(v), op, 0.1, 0.01, (0.05, 4.0))[0], x)
    np.testing.assert_allclose(np.array(Phi), Pn, rtol=1e-5, atol=1e-8)
    # Euler sub-steps: the same as ten steps of x + h f(x) written out here
    ref = np.array(x, dtype=float)
    for _ in range(10):
        ref = np.clip(ref + 0.01 * model_f(ref, u), [0, 0, 0, 0.05], [1, 1, 1, 4.0])
    np.testing.assert_allclose(x_new, ref, rtol=1e-12)


def test_lambda_mid_of_a_saturated_or_cold_catalyst_is_lambda_pre():
    u_cold = (0.01, 20.0, 1.03)  # no kinetics at 20 °C: the gas passes unchanged (eq. 12)
    assert model_g([0.5, 0.5, 0.5, 1.0], u_cold) == pytest.approx(1.03, abs=1e-4)
    assert model_g([0.999, 0.999, 0.999, 1.0], (0.01, 500.0, 1.02)) > 1.01  # full: O2 slips
    assert model_g([0.5, 0.5, 0.5, 1.0], (0.01, 500.0, 1.02)) == pytest.approx(1.0, abs=1e-3)


def test_states_stay_bounded_and_outputs_are_named():
    ob = TWCObserver(osc_init=0.06, phi_init=0.99)
    out = None
    for k in range(300):
        lam = 10.0 if (k // 50) % 2 else 0.9
        out = ob.step(k * 0.1, {"EXH_MASS_FLOW": 0.03, "T_CAT": 600.0, "LAMBDA_PRE": lam,
                                "LAMBDA_MID": lam})
        x = ob.core.x
        assert np.all((x[:3] >= 0.0) & (x[:3] <= 1.0)) and x[3] > 0.0
        P = ob.core.P
        np.testing.assert_allclose(P, P.T, atol=0)
        assert np.linalg.eigvalsh(P).min() > 0.0
    assert set(out) == {"SOX_EST", "PHI_1_EST", "PHI_2_EST", "PHI_3_EST", "OSC_EST",
                        "LAMBDA_MID_EST", "TWC_CONF", "OSC_EST_SD", "SOX_EST_SD"}
    # the bands come from P: OSC's own variance, and that of the mean of the three φ
    assert out["OSC_EST_SD"] == pytest.approx(math.sqrt(P[3, 3]))
    assert out["SOX_EST_SD"] == pytest.approx(math.sqrt(np.ones(3) @ P[:3, :3] @ np.ones(3)) / 3)
    assert out["SOX_EST"] == pytest.approx((out["PHI_1_EST"] + out["PHI_2_EST"]
                                            + out["PHI_3_EST"]) / 3)


@pytest.mark.parametrize("channel,value,needle", [
    ("LAMBDA_PRE", math.nan, "input LAMBDA_PRE is nan"),
    ("EXH_MASS_FLOW", math.inf, "input EXH_MASS_FLOW is inf"),
    ("LAMBDA_MID", 0.2, "LAMBDA_MID = 0.2 outside its plausible range [0.5, 16]"),
    ("T_CAT", 2000.0, "T_CAT = 2000 outside its plausible range [-50, 1200]"),
    ("EXH_MASS_FLOW", -0.01, "EXH_MASS_FLOW = -0.01 outside"),
])
def test_bad_inputs_are_refused_and_the_state_is_kept(channel, value, needle):
    ob = TWCObserver()
    for k in range(20):
        ob.step(k * 0.1, dict(WARM, LAMBDA_PRE=1.0 + 0.02 * (-1) ** k))
    x, P, t = ob.core.x.copy(), ob.core.P.copy(), ob._t
    with pytest.raises(ArithmeticError, match=re_escape(needle)):
        ob.step(2.0, dict(WARM, **{channel: value}))
    np.testing.assert_array_equal(ob.core.x, x)
    np.testing.assert_array_equal(ob.core.P, P)
    assert ob._t == t and ob.core.resets == 0


def re_escape(text):
    import re

    return re.escape(text)


def test_a_long_gap_is_not_predicted_over_but_widens_p():
    ob = TWCObserver()
    for k in range(10):
        ob.step(k * 0.1, WARM)
    x, p = ob.core.x.copy(), np.diag(ob.core.P).copy()
    ob.step(0.9 + 5.0, dict(WARM, LAMBDA_PRE=1.05))  # inputs silent for 5 s
    assert ob.skipped_gaps == 1
    assert np.diag(ob.core.P)[3] > p[3]
    assert ob.core.x[3] == pytest.approx(x[3], abs=0.05)


def test_divergence_resets_with_the_reason_shown():
    ob = TWCObserver(nis_window=3, nis_gate=0.5, innovation_limit=0.0, osc_init=0.8)
    raised = None
    for k in range(30):  # the model says λ_mid = λ_pre; the "sensor" says far rich
        try:
            ob.step(k * 0.1, dict(WARM, LAMBDA_PRE=1.0, LAMBDA_MID=0.9 if k > 5 else 1.0))
        except ArithmeticError as exc:  # the runtime marks the tick's outputs invalid
            raised = exc
            break
    assert raised is not None and "NIS above" in str(raised)
    state = ob.state()
    assert state["resets"] >= 1 and "NIS above" in state["last_reset_reason"]
    assert ob.core.x[3] == pytest.approx(0.8)  # back at the initial guess


def test_parameters_validate_as_a_whole_and_osc_init_restarts():
    ob = TWCObserver()
    for k in range(10):
        ob.step(k * 0.1, WARM)
    before = ob.params()
    for bad, field in (({"Q": [1e-4, 1e-4, 0.0, 2e-5]}, "Q"), ({"Q": [1e-4, 1e-4, 1e-4]}, "Q"),
                       ({"R": -1.0}, "R"), ({"osc_init": 0.0}, "osc_init"),
                       ({"R": 1e-3, "Q": [[1, 2], [3, 4]]}, "Q")):
        with pytest.raises(ParamError) as err:
            ob.set_params(bad)
        assert err.value.field == field
        assert ob.params() == before  # all or nothing
    ob.set_params({"Q": [1e-4, 1e-4, 1e-4, 2e-4], "R": 2e-4})
    assert ob.core.Q[3, 3] == 2e-4 and ob.core.R[0, 0] == 2e-4 and ob.core.resets == 0
    ob.set_params({"osc_init": 0.6})
    assert ob.core.x[3] == 0.6 and ob.core.resets == 1
    assert ob.state()["last_reset_reason"] == "restarted: osc_init = 0.6"


def test_observer_model_is_not_the_plant():
    plant = TWCKinetics()
    assert MODEL_KINETICS.A1 != plant.A1 and MODEL_KINETICS.A2 != plant.A2
    assert MODEL_KINETICS.osc_fresh == plant.osc_fresh  # the normalisation is shared
    other = TWCObserver(kinetics=plant.scaled(A1=0.5))
    assert other.kinetics.A1 == 0.5 * plant.A1


# -- in the runtime and the service -------------------------------------------------------------
def frames(db, t0, t1, skip=()):
    """The catalyst's sensor frames every 10 ms (without the messages in ``skip``)."""
    out = []
    for i in range(round(t0 * 100), round(t1 * 100)):
        t = i / 100
        lam = 1.0 + 0.02 * math.sin(2 * math.pi * t)
        if "TWC_LAMBDA" not in skip:
            out.append(db.encode("TWC_LAMBDA", {"LAMBDA_PRE": lam, "LAMBDA_MID": 1.0}, t))
        if "TWC_FLOW" not in skip:
            out.append(db.encode("TWC_FLOW", {"EXH_MASS_FLOW": 0.01}, t))
        if i % 10 == 0:
            out.append(db.encode("TWC_TEMP", {"T_EXH": 480.0, "T_CAT": 450.0}, t))
    return out


@pytest.mark.parametrize("silent", ["TWC_LAMBDA", "TWC_FLOW"])
def test_silent_lambda_or_flow_frames_make_the_outputs_stale(silent):
    db = load()
    rt = Runtime(db, [TWCObserver()])
    rt.ingest_many(frames(db, 0.0, 5.0))
    rt.advance(5.0)
    assert rt.channel("OSC_EST").status == "ok"
    sent = len(rt.take_outbox())
    assert sent > 0  # TWC_OBSERVER frames on the bus
    rt.ingest_many(frames(db, 5.0, 7.0, skip=(silent,)))
    rt.advance(7.0)
    for name in ("SOX_EST", "OSC_EST", "LAMBDA_MID_EST"):
        status, reason = rt.channel(name).status_at(7.0)
        assert status == "stale" and ("LAMBDA" in reason or "EXH_MASS_FLOW" in reason)
    assert rt.take_outbox() == [] or all(db.decode(m)[0].name not in ("TWC_OBSERVER",)
                                         for m in rt.take_outbox())
    rt.ingest_many(frames(db, 7.0, 9.0))
    rt.advance(9.0)
    assert rt.channel("OSC_EST").status == "ok"


def test_out_of_range_frame_marks_outputs_invalid_and_keeps_the_state():
    db = load()
    block = TWCObserver()
    rt = Runtime(db, [block])
    rt.ingest_many(frames(db, 0.0, 3.0))
    rt.advance(3.0)
    x = block.core.x.copy()
    # a raw value past the DBC's range: 0xFFFF x 0.00025 = 16.38 > 16
    import can

    bad = can.Message(timestamp=3.05, arbitration_id=0x311, is_extended_id=False,
                      data=bytes([0xFF, 0xFF, 0xA0, 0x0F]))
    rt.ingest(bad)
    rt.advance(3.1)
    status, reason = rt.channel("OSC_EST").status_at(3.1)
    # refused at the door (the DBC's range) before the observer's own range check
    assert status == "invalid" and "LAMBDA_PRE = 16.3837" in reason and "outside" in reason
    np.testing.assert_array_equal(block.core.x, x)


def test_patch_observer_refuses_a_non_positive_definite_q_with_422(tmp_path):
    db = load()
    rt = Runtime(db, [TWCObserver()])
    rt.ingest_many(frames(db, 0.0, 2.0))
    rt.advance(2.0)
    store = TuningStore(tmp_path / "tuning.json")
    client = local_client(create_app(Cell(runtime=rt, tuning=store)))
    before = client.get("/observers/twc").json()
    assert before["params"]["Q"] == [1e-4, 1e-4, 1e-4, 2e-5]
    r = client.patch("/observers/twc", json={"Q": [1e-4, 1e-4, -1e-4, 2e-5]})
    assert r.status_code == 422
    assert r.json()["detail"][0]["loc"] == ["body", "Q"]
    assert "positive definite" in r.json()["detail"][0]["msg"]
    assert client.get("/observers/twc").json()["params"] == before["params"]
    r = client.patch("/observers/twc", json={"Q": [1e-4, 1e-4, 1e-4, 2e-4], "osc_init": 0.5})
    assert r.status_code == 200
    body = r.json()
    assert body["params"]["Q"][3] == 2e-4 and body["state"]["x"][3] == 0.5
    assert body["state"]["last_reset_reason"] == "restarted: osc_init = 0.5"
    assert store.data["observers"]["twc"]["osc_init"] == 0.5


def test_osc_init_is_a_setting_of_up_and_replay(tmp_path):
    s = Settings.build({"osc_init": 0.7}, environ={})
    blocks = cli.build_runtime(Settings.build({"osc_init": 0.7, "engine": "si-turbo"},
                                              environ={}))[0].blocks
    assert blocks["twc"].osc_init == 0.7 and s.blocks["osc_init"] == 0.7
    assert Settings.build({}, environ={"TESTCELL_OSC_INIT": "1.4"}).blocks["osc_init"] == 1.4
    from cell.core.errors import ConfigError

    with pytest.raises(ConfigError, match=r"--osc-init must be in \(0.05, 4\]"):
        Settings.build({"osc_init": 9.0}, environ={})
    parser = cli.build_parser()
    args = parser.parse_args(["replay", "x.log", "--out", "x.csv", "--osc-init", "0.8"])
    assert Settings.from_args(args, environ={}).blocks["osc_init"] == 0.8


# -- the sensor model and designs (issue 18) ---------------------------------------------------
def test_undoing_the_composition_lag_recovers_the_feed_lambda():
    from cell.estimators.catalyst import undo_composition_lag
    from cell.plant.catalyst_model import feed_gas

    k = MODEL_KINETICS
    a = 1.0 - math.exp(-0.1 / 0.1)
    feed = [10.0, 10.0, 0.93, 0.93, 0.95, 1.02, 1.3, 4.0, 0.97]
    # the sensor, written plainly: each species' mole fraction lagged, λ of eq. 12 of the mix
    o2, co, c = feed_gas(feed[0], 1.0, k)
    lagged = [o2, co, c]
    m_prev = None
    state = None
    for lam in feed[1:]:
        g = feed_gas(lam, 1.0, k)
        lagged = [v + a * (w - v) for v, w in zip(lagged, g)]
        o2, co, c = lagged
        m = (2.0 * (o2 + c - co) + co) / (2.0 * c)
        if state is None:
            D = 2.0 * feed_gas(feed[0], 1.0, k)[2]
            state = (feed[0] * D, D)
        got, *state = undo_composition_lag(m, *state, a, k)
        assert got == pytest.approx(lam, rel=1e-9)
        m_prev = m
    assert m_prev is not None


def test_a_design_round_trips_and_a_bad_one_keeps_the_previous():
    from cell.estimators.contract import DesignError

    ob = TWCObserver()
    d = {"observer": "twc", "identified": {"lambda_lag": "composition", "tau_lambda": 0.15,
                                           "dead_time": 0.03, "kinetics_scale": 1.4}}
    ob.load_design(d, "test")
    assert ob.sensor_model() == {"lambda_lag": "composition", "tau_lambda": 0.15,
                                 "dead_time": 0.03, "kinetics_scale": 1.4}
    assert ob.kinetics.A1 == pytest.approx(1.4 * MODEL_KINETICS.A1)
    other = TWCObserver()
    other.load_design(ob.design(), "round trip")
    assert other.sensor_model() == ob.sensor_model()
    for bad, needle in (({"identified": {"lambda_lag": "voltage"}}, "identified.lambda_lag"),
                        ({"identified": {"tau_lambda": -1}}, "identified.tau_lambda"),
                        ({"identified": {"colour": 1}}, "identified.colour: unknown"),
                        ({"observer": "airpath"}, "names observer 'airpath'")):
        with pytest.raises(DesignError, match=re_escape(needle)):
            ob.load_design({"observer": "twc", **bad}, "bad")
        assert ob.sensor_model()["tau_lambda"] == 0.15


def test_put_design_loads_live_and_refuses_a_bad_one_with_422(tmp_path):
    db = load()
    rt = Runtime(db, [TWCObserver()])
    rt.ingest_many(frames(db, 0.0, 1.0))
    rt.advance(1.0)
    client = local_client(create_app(Cell(runtime=rt)))
    r = client.put("/observers/twc/design", json={"observer": "twc",
                                                  "identified": {"tau_lambda": 0.2}})
    assert r.status_code == 200 and r.json()["state"]["sensor_model"]["tau_lambda"] == 0.2
    r = client.put("/observers/twc/design", json={"observer": "twc",
                                                  "identified": {"tau_lambda": "slow"}})
    assert r.status_code == 422 and "identified.tau_lambda" in r.json()["detail"]
    r = client.put("/observers/twc/design", json={"observer": "other"})
    assert r.status_code == 422 and "names observer 'other'" in r.json()["detail"]
    assert client.get("/observers/twc").json()["state"]["sensor_model"]["tau_lambda"] == 0.2
    assert client.put("/observers/nope/design", json={"observer": "nope"}).status_code == 422


def test_a_design_put_live_is_saved_and_survives_a_restart(tmp_path):
    db = load()
    path = tmp_path / "state" / "tuning.json"
    store = TuningStore(path)
    store.load()
    client = local_client(create_app(Cell(runtime=Runtime(db, [TWCObserver()]), tuning=store)))
    design = {"observer": "twc", "identified": {"lambda_lag": "composition", "tau_lambda": 0.15}}
    assert client.put("/observers/twc/design", json=design).status_code == 200
    assert json.loads(path.read_text())["designs"]["twc"] == design
    # a bad design is refused and the saved one stays
    bad = {"observer": "twc", "identified": {"tau_lambda": 9.0}}
    assert client.put("/observers/twc/design", json=bad).status_code == 422
    assert json.loads(path.read_text())["designs"]["twc"] == design

    # the restart: a new runtime and store over the same file
    rt = Runtime(db, [TWCObserver()])
    again = TuningStore(path)
    again.load()
    assert again.restore(rt) == []
    assert rt.blocks["twc"].sensor_model() == {"lambda_lag": "composition", "tau_lambda": 0.15,
                                               "dead_time": 0.0, "kinetics_scale": 1.0}
    # a design given on the command line (--design) wins over the saved one
    rt = Runtime(db, [TWCObserver()])
    assert again.restore(rt, keep_designs=["twc"]) == []
    assert rt.blocks["twc"].lambda_lag == "lambda"


def test_a_saved_design_that_no_longer_loads_is_skipped_by_name(tmp_path):
    path = tmp_path / "tuning.json"
    path.write_text(json.dumps({"designs": {"twc": {"observer": "twc",
                                                    "identified": {"lambda_lag": "voltage"}}},
                                "observers": {"twc": {"R": [3e-4]}}}))
    rt = Runtime(load(), [TWCObserver()])
    store = TuningStore(path)
    store.load()
    skipped = store.restore(rt)
    assert len(skipped) == 1 and "designs/twc" in skipped[0]
    assert "identified.lambda_lag" in skipped[0]
    assert rt.blocks["twc"].lambda_lag == "lambda" and rt.blocks["twc"].R[0] == 3e-4


def test_a_design_that_cannot_be_saved_is_not_loaded(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    store = TuningStore(blocker / "tuning.json")  # its folder is a file: no write succeeds
    rt = Runtime(load(), [TWCObserver()])
    client = local_client(create_app(Cell(runtime=rt, tuning=store)))
    r = client.put("/observers/twc/design", json={"observer": "twc",
                                                  "identified": {"tau_lambda": 0.2}})
    assert r.status_code >= 400 and "cannot save tuning" in r.json()["detail"]
    assert rt.blocks["twc"].tau_lambda == 0.1 and "designs" not in store.data


def test_design_and_state_files_on_replay(tmp_path):
    from cell.app.assemble import build_runtime

    good = tmp_path / "twc.json"
    good.write_text(json.dumps({"observer": "twc", "identified": {"lambda_lag": "composition"}}))
    state = tmp_path / "tuning.json"
    state.write_text(json.dumps({"observers": {"twc": {"R": [3e-4]}}}))
    rt, _ = build_runtime(Settings.build({"engine": "si-turbo", "designs": (str(good),),
                                          "state": state}, environ={}))
    assert rt.blocks["twc"].lambda_lag == "composition" and rt.blocks["twc"].R[0] == 3e-4
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"observer": "catalyst-x"}))
    code = cli.main(["replay", str(tmp_path / "none.log"), "--out", str(tmp_path / "o.csv"),
                     "--engine", "si-turbo", "--design", str(bad)])
    assert code == 2 and not (tmp_path / "o.csv").exists()
