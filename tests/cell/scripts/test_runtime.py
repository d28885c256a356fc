"""Runtime behaviour: contained errors, constants, hot swap, multi-rate sets, the runtime."""

import json
import math

import pytest

from cell.core.errors import ParamError
from cell.scripts import (
    DIALECTS,
    CyflexBlock,
    FdvBlock,
    ScriptBlock,
    ScriptError,
    load_script,
    shipped_scripts,
)
from cell.runtime.scheduler import Rates, Runtime

from tests.helpers.listings import FDV

ERRS = """[init]
dim acc
[formulas]
public a
public b
public c
public d
public e
a = 1 / x
b = log(x)
c = x * 2
d = a + 1
acc = acc + 1 / x
e = acc
"""


def test_runtime_errors_are_contained_per_output_and_cleared_next_tick():
    blk = FdvBlock("errs.fdv", ERRS)
    out = blk.step(0.0, {"x": 2.0})
    assert out == {"a": 0.5, "b": math.log(2.0), "c": 4.0, "d": 1.5, "e": 0.5}
    assert blk.errors == {}
    out = blk.step(0.1, {"x": 0.0})
    assert math.isnan(out["a"]) and "division by zero" in blk.errors["a"]
    assert "line 9:1" in blk.errors["a"]
    assert math.isnan(out["b"]) and "domain error" in blk.errors["b"]
    assert out["c"] == 0.0 and "c" not in blk.errors
    assert math.isnan(out["d"]) and "division by zero" in blk.errors["d"]  # depends on a
    assert math.isnan(out["e"])  # acc failed: its state is held, not poisoned
    assert blk.values()["acc"] == 0.5
    out = blk.step(0.2, {"x": -1.0})
    assert out["a"] == -1.0 and out["d"] == 0.0 and "domain error" in blk.errors["b"]
    assert set(blk.errors) == {"b"}
    out = blk.step(0.3, {"x": 4.0})
    assert blk.errors == {} and out["e"] == 0.5 - 1.0 + 0.25
    assert blk.error_counts["a"] == 1 and blk.error_counts["b"] == 2
    assert blk.error_counts["acc"] == 1


def test_overflow_and_nan_results_are_errors():
    blk = FdvBlock("o.fdv", "[formulas]\npublic a\npublic b\na = exp(x)\nb = x * x\n")
    out = blk.step(0.0, {"x": 1000.0})
    assert math.isnan(out["a"]) and "overflow" in blk.errors["a"]
    assert out["b"] == 1e6
    out = blk.step(0.0, {"x": 1e200})
    assert "result is inf" in blk.errors["b"]


def test_cyflex_runtime_errors_and_statistic_errors():
    labels = ("r none 3 5 MED OFF 1.0\n{1 / x}\n"
              "s none 3 0 MED OFF 1.0\n{x * 2}\n"
              "u none 3 0 MED OFF 1.0\nr + 1[none]\n")
    blk = CyflexBlock("e.labels", labels, "r 3 MED a_r\n")
    out = blk.step(0.0, {"x": 0.0}, frozenset({"MED"}))
    assert math.isnan(out["r"]) and "division by zero" in blk.errors["r"]
    assert out["s"] == 0.0
    assert math.isnan(out["u"]) and "division by zero" in blk.errors["u"]
    assert all(math.isnan(out[f"a_r.{s}"]) for s in ("AV", "FV"))  # no valid sample
    assert blk.values()["a_r.NM"] == 0.0
    out = blk.step(0.1, {"x": 4.0}, frozenset({"MED"}))
    assert blk.errors == {} and out["a_r.FV"] == 0.25 and out["a_r.NM"] == 1.0


def test_set_constants_takes_effect_on_the_next_step_and_bad_ones_change_nothing():
    a, b = FdvBlock("k.fdv", FDV), FdvBlock("k.fdv", FDV)
    ys = [680.0 + (k % 7) for k in range(40)]
    for y in ys[:20]:
        a.step(0.0, {"EXH_BP_R": y})
        b.step(0.0, {"EXH_BP_R": y})
    before = a.constants()
    for bad in ({"Q": 1.0}, {"Q_EXH_BP_R": float("nan")}, {"Q_EXH_BP_R": True},
                {"Q_EXH_BP_R": "1e-5"}, {"Q_EXH_BP_R": 1e-5, "R_EXH_BP_R": math.inf},
                {"P_EXH_BP_R": 1.0}, {}, [1]):
        with pytest.raises(ParamError):
            a.set_constants(bad)
        assert a.constants() == before
    with pytest.raises(ParamError) as info:
        a.set_constants({"Q_EXH_BP_R": 1e-5, "Qq": 1.0})
    assert "Qq" in str(info.value) and "Q_EXH_BP_R, R_EXH_BP_R" in str(info.value)
    assert a.set_constants({"Q_EXH_BP_R": 1e-5}) == {"Q_EXH_BP_R": 1e-5, "R_EXH_BP_R": 1e-4}
    # the change is used from the very next step: compare against a hand update
    s = b.values()
    y = ys[20]
    K = s["P_EXH_BP_R"] / (s["P_EXH_BP_R"] + 1e-4)
    P = (1 - K) * s["P_Prev_EXH_BP_R"] * (1 - K) + K * 1e-4 * K
    a.step(0.0, {"EXH_BP_R": y})
    assert a.values()["P_Prev_EXH_BP_R"] == pytest.approx(P + 1e-5, rel=1e-12)
    assert a.params() == a.constants()  # the Block parameter API routes to constants


def test_cyflex_constants_are_settable():
    shipped = {n: (t, r) for n, t, r in shipped_scripts()}
    blk = load_script("kalman.labels", *shipped["kalman.labels"])
    blk.set_constants({"R_Gain_EXH_BP_R": 1e-3})
    out = blk.step(0.0, {"EXH_BP_L": 1.0, "EXH_BP_R": 1.0}, frozenset({"MED"}))
    assert out["R_Gain_EXH_BP_R"] == 1e-3 and out["R_Gain_EXH_BP_L"] == 1e-4
    assert out["K_EXH_BP_R"] == pytest.approx(1.0 / (1.0 + 1e-3))
    with pytest.raises(ParamError, match="K_EXH_BP_R"):
        blk.set_constants({"K_EXH_BP_R": 0.5})  # computed, not a constant


def test_hot_swap_keeps_state_of_unchanged_formulas():
    old = FdvBlock("k.fdv", FDV)
    for k in range(30):
        old.step(0.1 * k, {"EXH_BP_R": 680.0 + k % 3})
    old.set_constants({"Q_EXH_BP_R": 2e-6})
    # reformatted but same formulas, plus one changed output formula and a new output
    text = FDV.replace("EXH_BP_R_Kalman = X_hat_EXH_BP_R", "EXH_BP_R_Kalman = 2 * X_hat_EXH_BP_R")
    text = text.replace("P_Prev_EXH_BP_R = P_EXH_BP_R + Q_EXH_BP_R",
                        "P_Prev_EXH_BP_R   =   P_EXH_BP_R+Q_EXH_BP_R // same formula")
    text += "public extra\nextra = X_hat_EXH_BP_R\n"
    new = FdvBlock("k.fdv", text)
    adopted = new.adopt_state(old)
    assert "EXH_BP_R_Kalman" not in adopted and "extra" not in adopted
    assert {"X_hat_EXH_BP_R", "P_EXH_BP_R", "P_Prev_EXH_BP_R", "Q_EXH_BP_R"} <= set(adopted)
    assert new.constants()["Q_EXH_BP_R"] == 2e-6  # tuned constant survives an unchanged [init]
    a = old.step(3.0, {"EXH_BP_R": 681.0})["EXH_BP_R_Kalman"]
    b = new.step(3.0, {"EXH_BP_R": 681.0})["EXH_BP_R_Kalman"]
    assert b == 2 * a
    # a bad replacement does not compile, so the running block is untouched
    with pytest.raises(ScriptError):
        FdvBlock("k.fdv", text + "y = (\n")
    assert old.values()["X_hat_EXH_BP_R"] == a
    # a different dialect adopts nothing
    assert CyflexBlock("x.labels", "x none 3 0 MED OFF 1.0\n1\n").adopt_state(old) == []


def test_hot_swap_of_a_cyflex_set_keeps_running_average_windows():
    shipped = {n: (t, r) for n, t, r in shipped_scripts()}
    text, ravg = shipped["maf.labels"]
    old = load_script("maf.labels", text, ravg)
    for k in range(40):
        old.step(0.1 * k, {"EXH_BP_L": float(k), "EXH_BP_R": 2.0 * k}, frozenset({"MED"}))
    new_ravg = ravg.replace("EXH_BP_R 30 MED", "EXH_BP_R 10 MED")
    new = load_script("maf.labels", text, new_ravg)
    adopted = new.adopt_state(old)
    assert "a_EXH_BP_L_maf" in adopted and "a_EXH_BP_R_maf" not in adopted
    assert "EXH_BP_L_MAF_CYF" in adopted
    out = new.step(4.0, {"EXH_BP_L": 40.0, "EXH_BP_R": 80.0}, frozenset({"MED"}))
    assert out["a_EXH_BP_L_maf.AV"] == pytest.approx(sum(range(11, 41)) / 30)
    assert out["a_EXH_BP_R_maf.NM"] == 1.0  # changed definition starts afresh


def test_multi_rate_set_runs_each_label_at_its_interval():
    labels = ("fast none 3 0 FAS OFF 1.0\nfast + 1[none]\n"
              "slow none 3 0 SLO OFF 1.0\nslow + 1[none]\n"
              "med none 3 0 MED OFF 1.0\n{x}\n")
    blk = CyflexBlock("m.labels", labels, "med 5 MED a_med\nfast 2 FAS a_fast\n",
                      rates=Rates(FAS=100.0, MED=20.0, SLO=2.0))
    assert blk.rates == ("FAS", "MED", "SLO")
    assert blk.inputs == ["x"]
    counts = {"fast": 0, "slow": 0, "med": 0}
    for i in range(100):  # one second of FAS ticks at 100 Hz
        t = i / 100
        ticking = {"FAS"} | ({"MED"} if i % 5 == 0 else set()) | ({"SLO"} if i % 50 == 0 else set())
        out = blk.step(t, {"x": t}, frozenset(ticking))
        for name in counts:
            counts[name] += name in out
        assert ("a_med.AV" in out) == ("MED" in ticking)
    assert counts == {"fast": 100, "slow": 2, "med": 20}
    st = blk.values()
    assert st["fast"] == 100 and st["slow"] == 2
    assert st["a_fast.RA"] == 100.0 and st["a_med.RA"] == 20.0
    # IN is the rectangle integral with dt = 1/rate of the running average's own task
    assert st["a_med.IN"] == pytest.approx(sum([0.75, 0.8, 0.85, 0.9, 0.95]) / 20.0)
    assert st["a_fast.IN"] == pytest.approx((99 + 100) / 100.0)
    assert blk.step(2.0, {"x": 0.0}, frozenset()) == {}


def test_registry_dispatches_on_the_suffix():
    assert set(DIALECTS) == {".fdv", ".labels", ".ravg"}
    assert load_script("a.FDV", "[formulas]\npublic y\ny = 1\n").kind == "fdv"
    ravg_only = load_script("s.ravg", "x 3 SLO a_x\n")
    assert ravg_only.kind == "cyflex" and ravg_only.rates == ("SLO",)
    assert ravg_only.inputs == ["x"] and len(ravg_only.outputs) == 22
    with pytest.raises(ScriptError, match="known suffixes: .fdv, .labels, .ravg"):
        load_script("a.py", "")


def test_describe_is_json_ready_and_rate_directive_works():
    blk = FdvBlock("r.fdv", "// rate: fas\n[formulas]\npublic y\ny = x\n")
    assert blk.rates == ("FAS",) and blk.family == "script" and blk.dialect == "fdv"
    text = "// rate: FAS\n[formulas]\npublic y\ny = x\n"
    assert FdvBlock("r.fdv", text, rate="SLO").rate == "SLO"
    for b in [blk] + [load_script(n, t, r) for n, t, r in shipped_scripts()]:
        d = json.loads(json.dumps(b.describe(), allow_nan=False))  # as Starlette sends it
        assert d["source"] == b.source and d["family"] == "script"
        assert isinstance(b, ScriptBlock)


def test_shipped_scripts_run_in_the_cell_runtime(db):
    blocks = [load_script(n, t, r) for n, t, r in shipped_scripts()]
    rt = Runtime(db, blocks)
    for i in range(300):
        t = i * 0.01
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 680.0 + (i % 5), "EXH_BP_R": 650.0}, t))
    rt.advance(3.0)
    for name in ("EXH_BP_L_Kalman_FDV", "EXH_BP_R_Kalman_CYF", "EXH_BP_R_MAF_FDV",
                 "EXH_BP_L_MAF_CYF", "a_EXH_BP_R_maf.AV"):
        ch = rt.channels[name]
        assert ch.status == "ok", (name, ch.reason)
    assert rt.channels["EXH_BP_R_MAF_FDV"].value == pytest.approx(650.0)
    assert rt.channels["EXH_BP_R_Kalman_FDV"].value == pytest.approx(650.0, abs=0.5)
    # a statistic that is undefined is marked invalid with its reason, others keep running
    assert rt.channels["a_EXH_BP_R_maf.EL"].status == "ok"
    bad = FdvBlock("bad.fdv", "[formulas]\npublic Z1\npublic Z2\nZ1 = 1 / (EXH_BP_R - 650)\n"
                   "Z2 = EXH_BP_R\n")
    rt.add_block(bad)
    rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 680.0, "EXH_BP_R": 650.0}, 3.05))
    rt.advance(3.1)
    assert rt.channels["Z1"].status == "invalid"
    assert "division by zero" in rt.channels["Z1"].reason
    assert rt.channels["Z2"].status == "ok"
