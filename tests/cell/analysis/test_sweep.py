"""Q/R sweeps (seed 004, Tables 1-2, Figures 7-8): the vectorised filter bank against the
runtime's ScalarKalman and filterpy, the grids, the scores against closed forms, the CLI."""

import argparse
import json

import can
import numpy as np
import pytest

from cell.analysis import sweep as sw
from cell.errors import ConfigError, LogFormatError
from cell.estimators.filters import MovingAverage, ScalarKalman, native_filters
from cell.sim import simulate
from cell.runtime import Runtime
from cell.sim import write_log


def scalar_reference(y, Q, R, P0=1.0):
    """ScalarKalman stepped by hand; a NaN sample is skipped (state held), as the runtime does."""
    kf = ScalarKalman("k", "y", Q=Q, R=R, P0=P0)
    out = []
    for v in y:
        out.append(kf.step(0.0, {"y": v})["k"] if np.isfinite(v) else np.nan)
    return np.array(out)


@pytest.fixture(scope="module")
def noisy_walk():
    rng = np.random.default_rng(4)
    y = 500.0 + np.cumsum(rng.normal(0, 3, 3000)) + rng.standard_t(5, 3000) * 40
    y[[0, 1, 700, 701, 702, 2999]] = np.nan  # stale ticks, including the first ones
    return y


# -- the bank ---------------------------------------------------------------------------
def test_bank_equals_scalar_kalman_for_all_table2_pairs(noisy_walk):
    pairs = sw.table2()
    Q, R = np.array(pairs).T
    x, e, S = sw.kalman_bank(noisy_walk, Q, R)
    assert x.shape == e.shape == S.shape == (noisy_walk.size, 72)
    for i in range(72):
        ref = scalar_reference(noisy_walk, Q[i], R[i])
        np.testing.assert_array_equal(np.isnan(x[:, i]), np.isnan(ref))
        np.testing.assert_allclose(x[:, i], ref, rtol=0, atol=1e-9, equal_nan=True)
    # innovation of a tick: sample minus the previous estimate; none at the first sample
    j = np.flatnonzero(np.isfinite(noisy_walk))
    assert np.isnan(e[j[0]]).all()
    np.testing.assert_allclose(e[j[1:], 3], noisy_walk[j[1:]] - x[j[:-1], 3])


def test_bank_matches_filterpy(noisy_walk):
    from filterpy.kalman import KalmanFilter

    y = noisy_walk[2:700]  # no gaps: filterpy has no notion of a stale sample
    pairs = [(1e-6, 1e-4), (4e-6, 1e-3), (9e-5, 1e-4), (10.0, 1600.0)]
    x, e, S = sw.kalman_bank(y, *np.array(pairs).T)
    for i, (q, r) in enumerate(pairs):
        kf = KalmanFilter(dim_x=1, dim_z=1)
        kf.F[:] = kf.H[:] = 1.0
        kf.Q[:], kf.R[:], kf.x[:], kf.P[:] = q, r, y[0], 1.0
        for k in range(1, y.size):
            kf.predict()
            kf.update(y[k])
            assert x[k, i] == pytest.approx(kf.x[0, 0], abs=1e-9, rel=1e-12)
            assert S[k, i] == pytest.approx(kf.S[0, 0], rel=1e-9)
            assert e[k, i] == pytest.approx(kf.y[0, 0], abs=1e-9, rel=1e-12)


def test_gain_sequence_converges_to_the_riccati_fixed_point():
    K, _ = sw.gain_sequence([1e-6, 1e-2, 5.0], [1e-4, 1e-4, 100.0], 1.0, steps=100_000)
    assert K.shape[0] < 100_000  # stopped once converged
    np.testing.assert_allclose(K[-1], sw.steady_state_gain([1e-6, 1e-2, 5.0], [1e-4, 1e-4, 100.0]),
                               rtol=1e-12)
    kf = ScalarKalman("k", "y", Q=1e-6, R=1e-4)
    assert K[-1, 0] == pytest.approx(kf.steady_state_gain(), rel=1e-12)


def test_bank_rejects_bad_covariances():
    with pytest.raises(ConfigError, match="R must be finite and > 0"):
        sw.kalman_bank([1.0, 2.0], 1e-6, [1e-4, -1.0])


def test_moving_average_equals_the_runtime_block(noisy_walk):
    block = MovingAverage("m", "y", samples=30)
    ref = [block.step(0.0, {"y": v})["m"] if np.isfinite(v) else np.nan for v in noisy_walk]
    np.testing.assert_allclose(sw.moving_average(noisy_walk), ref, rtol=1e-12, equal_nan=True)


# -- the series from a log, and the runtime itself ---------------------------------------
@pytest.fixture(scope="module")
def gap_log(db, tmp_path_factory):
    """20 s of the transient cycle from t = 30 s, with 1.5 s of EXH_BP frames missing."""
    path = tmp_path_factory.mktemp("gap") / "gap.log"
    with can.Logger(str(path)) as w:
        for msg in simulate(db, "transient", seed=3, duration=50.0):
            if msg.timestamp < 30.0:
                continue
            if 40.0 <= msg.timestamp < 41.5 and msg.arbitration_id == 257:
                continue
            w.on_message_received(msg)
    return path


def test_bank_over_a_log_equals_the_runtime_kalman_output(db, gap_log):
    series = sw.channel_series(gap_log, "EXH_BP_R", progress=False)
    assert series.truth_channel == "EXH_BP_R_TRUE"
    assert np.isnan(series.y).sum() > 5  # the gap went stale
    rt = Runtime(db, native_filters())
    got = []

    def on_tick(t):
        ch = rt.channels["EXH_BP_R_Kalman"]
        got.append(ch.value if ch.status_at(t)[0] == "ok" else np.nan)

    rt.tick_listeners.append(on_tick)
    last = None
    for msg in can.LogReader(str(gap_log)):
        rt.ingest(msg)
        last = msg.timestamp
    rt.advance(last)
    x, _, _ = sw.kalman_bank(series.y, 1e-6, 1e-4)
    np.testing.assert_allclose(x[:, 0], np.array(got), atol=1e-9, equal_nan=True)


def test_missing_channel_is_named_with_the_channels_the_log_has(gap_log):
    with pytest.raises(ConfigError) as err:
        sw.channel_series(gap_log, "EXH_BP_X", progress=False)
    assert "EXH_BP_X" in str(err.value) and "EXH_BP_R_TRUE" in str(err.value)
    with pytest.raises(ConfigError, match="NOPE"):
        sw.channel_series(gap_log, "EXH_BP_R", truth="NOPE", progress=False)


def test_malformed_log_line_gives_its_line_number(gap_log, tmp_path):
    lines = gap_log.read_text().splitlines(keepends=True)
    lines[99] = "(31.000000) vcan0 101#zz\n"
    bad = tmp_path / "bad.log"
    bad.write_text("".join(lines))
    with pytest.raises(LogFormatError) as err:
        sw.channel_series(bad, "EXH_BP_R", progress=False)
    assert err.value.line == 100 and ":100:" in str(err.value)


# -- grids ------------------------------------------------------------------------------
def test_paper_tables():
    t1, t2 = sw.parse_grid("table1"), sw.parse_grid("TABLE2")
    assert len(t1) == 32 and len(sw.unique_pairs(t1)) == 28
    assert len(t2) == 72 and len(sw.unique_pairs(t2)) == 68
    assert {(1.0, 1e-3), (1e-7, 1e-4), (1e-5, 1e-7), (1e-6, 1.0)} <= set(t1)
    q_half = {(k * 10.0**e, r) for k in range(1, 10) for e in (-6, -5) for r in (1e-3, 1e-4)}
    r_half = {(q, k * 10.0**e) for k in range(1, 10) for e in (-3, -4) for q in (1e-5, 1e-6)}
    close = {(round(q, 15), round(r, 15)) for q, r in t2}
    assert close == {(round(q, 15), round(r, 15)) for q, r in q_half | r_half}
    dup = {p for p in t2 if t2.count(p) > 1}
    assert dup == {(1e-5, 1e-3), (1e-5, 1e-4), (1e-6, 1e-3), (1e-6, 1e-4)}
    assert (3e-6, 1e-4) in t2 and (1e-6, 7e-4) in t2  # exact decimal literals


def test_range_and_list_grids():
    g = sw.parse_grid("Q=1e-7:1e-5:9,R=1e-4:1e-3:2")
    assert len(g) == 18
    qs = sorted({q for q, _ in g})
    np.testing.assert_allclose(np.diff(np.log10(qs)), 0.25)  # log-spaced, ends included
    assert qs[0] == pytest.approx(1e-7) and qs[-1] == pytest.approx(1e-5)
    assert sw.parse_grid("Q=1e-6,2e-6,5e-6,R=1e-4") == [(1e-6, 1e-4), (2e-6, 1e-4), (5e-6, 1e-4)]
    assert sw.parse_grid(" q = 1:3:3:lin ; r=2") == [(1.0, 2.0), (2.0, 2.0), (3.0, 2.0)]


@pytest.mark.parametrize(
    "text, pos, words",
    [
        ("Q=1e-7:1e-5,R=1", 3, "a:b:n"),
        ("Q=abc,R=1", 3, "not a number"),
        ("Q=1,R=0", 7, "> 0"),
        ("Z=1,R=2", 1, "unknown name 'Z'"),
        ("Q=1e-6", 7, "R is missing"),
        ("Q=1,,R=2", 5, "empty value"),
        ("Q=1,R=1,Q=2", 9, "given twice"),
        ("Q=1:2:x,R=1", 7, "whole number"),
        ("tabel2", 1, "not a grid"),
    ],
)
def test_bad_grids_name_the_text_and_position(text, pos, words):
    with pytest.raises(ConfigError) as err:
        sw.parse_grid(text)
    msg = str(err.value)
    assert repr(text) in msg and f"position {pos}:" in msg and words in msg


# -- scores against closed forms --------------------------------------------------------
def test_nis_and_whiteness_of_a_consistent_filter():
    rng = np.random.default_rng(7)
    n, Q, R = 20_000, 4.0, 100.0
    y = np.cumsum(rng.normal(0, 2.0, n)) + rng.normal(0, 10.0, n)
    # true Q, R (P0 = R: the exact prior after x0 = y0), and a badly tuned Q either side
    _, e, S = sw.kalman_bank(y, [Q, Q * 100, Q / 100], R, P0=R)
    s = sw.innovation_scores(e, S)
    assert s["nis"][0] == pytest.approx(1.0, abs=0.04)
    assert s["whiteness"][0] < 4 / np.sqrt(n)
    assert s["ljung_box"][0] < 30  # chi2(10) 99.9 % = 29.6
    assert s["whiteness"][1] > 0.3 and s["whiteness"][2] > 0.3
    assert s["nis"][2] > 2


def test_truth_scores_of_known_signals():
    rate = 10.0
    truth = np.r_[np.full(200, 100.0), np.full(200, 400.0), np.full(200, 250.0)]
    series = sw.Series.from_arrays(truth + 1.0, truth, rate)
    delayed = np.r_[np.full(7, 100.0), truth[:-7]]  # truth 0.7 s late
    sc = sw.score_estimates(series, np.column_stack([truth + 5.0, delayed]))
    assert sc["rmse"][0] == pytest.approx(5.0) and sc["max_err"][0] == pytest.approx(5.0)
    assert sc["ss_std"][0] == pytest.approx(0.0, abs=1e-12)
    assert sc["lag_s"][0] == pytest.approx(0.0, abs=1e-9)
    assert sc["lag_s"][1] == pytest.approx(0.7)
    assert sc["max_err"][1] == pytest.approx(300.0)
    assert sc["rmse"][1] == pytest.approx(np.sqrt((7 * 300**2 + 7 * 150**2) / 600))
    steps = sw.find_steps(series.t, truth, sw.steady_mask(truth, rate))
    assert [(s.before, s.after) for s in steps] == [(100.0, 400.0), (400.0, 250.0)]


def test_sweep_ranks_by_rmse_with_truth_and_by_whiteness_without():
    rng = np.random.default_rng(2)
    truth = np.repeat(rng.uniform(100, 700, 12), 300)
    y = truth + rng.normal(0, 60, truth.size)
    pairs = [(q, 1e-4) for q in (1e-8, 1e-6, 1e-5, 1e-4, 1e-2)] + [(1e-6, 1e-4)]
    ranked = sw.sweep(sw.Series.from_arrays(y, truth), pairs)
    assert len(ranked) == 5  # the duplicate is scored once
    assert [r["rank"] for r in ranked] == [1, 2, 3, 4, 5]
    rmse = [r["rmse"] for r in ranked]
    assert rmse == sorted(rmse)
    assert {"Q", "R", "gain", "rmse", "ss_std", "lag_s", "max_err", "whiteness", "nis"} <= set(ranked[0])
    blind = sw.sweep(sw.Series.from_arrays(y), pairs)
    assert "rmse" not in blind[0]
    lb = [r["ljung_box"] for r in blind]
    assert lb == sorted(lb)


# -- command line -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "transient.log"
    write_log(path, "transient", seed=5, duration=80.0, progress=False)
    return path


def run_cli(argv):
    parser = argparse.ArgumentParser()
    sw.add_arguments(parser)
    return sw.main(parser.parse_args(argv))


def test_cli_writes_csv_png_jsonl_and_prints_json(small_log, tmp_path, capsys):
    out = tmp_path / "out"
    assert run_cli([str(small_log), "--channel", "EXH_BP_R", "--grid", "table2",
                    "--out-dir", str(out), "--quiet", "--top", "5"]) == 0
    text = capsys.readouterr().out
    assert "72 pairs listed, 68 distinct" in text and "reference MAF-30" in text
    for suffix in ("csv", "png", "jsonl"):
        assert (out / f"sweep_EXH_BP_R.{suffix}").stat().st_size > 0
    header = (out / "sweep_EXH_BP_R.csv").read_text().splitlines()[0].split(",")
    assert header[:4] == ["rank", "Q", "R", "gain"] and "rmse" in header

    assert run_cli([str(small_log), "--grid", "Q=1e-7:1e-4:7,R=1e-4", "--out-dir", str(out),
                    "--quiet", "--json", "--no-plot"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    rows = [json.loads(line) for line in lines]
    assert len(rows) == 7
    for row in rows:
        assert {"Q", "R", "rmse", "ss_std", "lag_s", "max_err", "whiteness", "nis"} <= set(row)
    assert [r["rmse"] for r in rows] == sorted(r["rmse"] for r in rows)


def test_cli_refuses_a_bad_grid_before_reading_the_log(tmp_path):
    with pytest.raises(ConfigError, match="position"):
        run_cli([str(tmp_path / "missing.log"), "--grid", "Q=1:2,R=1"])
